"""Timing helper shared by the speed benchmarks.

As :mod:`timeit` does, the garbage collector is off while a call is timed (a collection triggered by an
earlier call's garbage would otherwise land in a random repeat), and the best of several repeats is
reported: on a shared machine the slower ones measure the other processes.
"""

from __future__ import annotations

import contextlib
import gc
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
        with _gc_off():
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
        with _gc_off():
            w0, c0 = time.perf_counter(), time.process_time()
            out = fn()
            cpus.append(time.process_time() - c0)
            walls.append(time.perf_counter() - w0)
    return min(walls), min(cpus), out


@contextlib.contextmanager
def _gc_off():
    """The garbage collector disabled for the block (re-enabled after it if it was on), as in timeit."""
    was_on = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        if was_on:
            gc.enable()
