"""Timing helper shared by the speed benchmarks."""

from __future__ import annotations

import time

__all__ = ["best_time"]


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
