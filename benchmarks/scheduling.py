"""How a campaign's work items run: in this process, or in a pool of worker processes.

Items are ``(args)`` tuples for one top-level function; each writes its own output file atomically,
so whichever way they run, a finished item is never redone and an interrupted run loses only the items
in flight.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context

from tqdm.auto import tqdm

__all__ = ["default_workers", "run_items"]


def default_workers() -> int:
    """The CPU cores this process may use."""
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def _pool(workers: int):
    return ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"))


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
