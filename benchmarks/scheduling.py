"""How a campaign's work items run: in this process, or in a pool of worker processes.

Items are ``(args)`` tuples for one top-level function; each writes its own output file atomically,
so whichever way they run, a finished item is never redone and an interrupted run loses only the items
in flight.

Worker processes die with the campaign: each asks Linux to send it SIGKILL when its parent exits
(``prctl(PR_SET_PDEATHSIG)``), and checks that its parent is still the one that started it, so a
campaign killed with SIGKILL leaves no worker behind to write more files (and the multiprocessing
resource tracker, whose pipe the workers held, exits too).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context

from tqdm.auto import tqdm

__all__ = ["default_workers", "die_with_parent", "run_items"]

_PR_SET_PDEATHSIG = 1


def default_workers() -> int:
    """The CPU cores this process may use."""
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def die_with_parent(parent_pid: int) -> None:
    """Worker initialiser: be killed (SIGKILL) when the parent process exits; exit now if it already has."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)


def _pool(workers: int):
    return ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"),
                               initializer=die_with_parent, initargs=(os.getpid(),))


def run_items(items, fn, *, workers: int, desc: str, progress: bool) -> None:
    """Run every ``args`` tuple of ``items`` through ``fn``, in a process pool when ``workers > 1``."""
    if not items:
        return
    bar = tqdm(total=len(items), desc=desc, unit="item", disable=not progress)
    with bar:
        if workers <= 1:
            for args in items:
                fn(*args)
                bar.update(1)
            return
        with _pool(workers) as pool:
            futures = [pool.submit(fn, *args) for args in items]
            try:
                for fut in as_completed(futures):
                    fut.result()
                    bar.update(1)
            except BaseException:
                for fut in futures:
                    fut.cancel()
                raise
