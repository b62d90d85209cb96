"""Timing helper shared by the speed benchmarks."""

from __future__ import annotations

import time

__all__ = ["best_time", "best_times"]


def best_time(fn, repeat, *, warmup=False):
    """Best wall time of ``repeat`` calls of ``fn`` and the last call's result.

    With ``warmup`` one untimed call goes first (kernel compilation, FFT plans).
    """
    if warmup:
        fn()
    times = []
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def best_times(fn, repeat):
    """Best wall time and best CPU time (this process, all threads) of ``repeat`` calls, and the last result.

    On a loaded machine the wall time includes waiting for a core; the CPU time does not, and with one
    thread it stays at most the wall time: the pair bounds what the code itself costs.
    """
    walls, cpus = [], []
    out = None
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        cpus.append(time.process_time() - c0)
        walls.append(time.perf_counter() - w0)
    return min(walls), min(cpus), out
