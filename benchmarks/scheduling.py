"""How a campaign's work items run: in this process, in a pool of worker processes, or as a pipeline.

Items are ``(args)`` tuples for one top-level function; each writes its own output file atomically,
so whichever way they run, a finished item is never redone and an interrupted run loses only the items
in flight.

``run_items`` runs the items of one kind (render, or score) in a pool of processes: the way for the
CPU, where every core renders or processes. ``run_pipeline`` is the way for a GPU: this process does
all the device work, pair after pair (render, noise, each method's processing), and hands each
result to a pool of worker processes for the host work (scoring, density integration, the score
file), so the device never waits for the host and no worker initialises CUDA; a thread renders the
next pair meanwhile. Both give
byte-identical files: every item computes the same thing from the same seeds, only where differs.
The pipeline can also track the tracking items in stacks of several pairs (``stacks``: one
``tracking.stack.track_pairs`` call per stack, the default on a GPU), whose results equal the
item-by-item ones to floating-point rounding.

Worker processes die with the campaign: each asks Linux to send it SIGKILL when its parent exits
(``prctl(PR_SET_PDEATHSIG)``; the parent is the campaign process, or the multiprocessing fork server,
which exits when the campaign process does), and checks that its parent is still the one that started
it and the campaign process still alive, so a campaign killed with SIGKILL leaves no worker behind to
write more files (and the multiprocessing resource tracker, whose pipe the workers held, exits too).
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import os
import select
import signal
import sys
import threading
import time
import traceback
import weakref
from collections import deque
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, ThreadPoolExecutor, as_completed, wait

from threadpoolctl import threadpool_limits
from tqdm.auto import tqdm

from synthbos import SynthbosError
from synthbos.device import init_warp, launching, load_kernels

from .drivers import (
    Claims,
    driver_context,
    ignoring_sigint_forkserver,
    join_drivers,
    quiet_resource_tracker,
    start_drivers,
    stop_drivers,
)

__all__ = ["PIPELINE_DRIVERS", "PIPELINE_MAX_WORKERS", "PIPELINE_WORKER_DEVICE", "build_in_pool", "campaign_kernels",
           "default_workers", "die_with_parent", "host_pool", "pair_tasks", "pipeline_workers", "render_kernels",
           "run_items", "run_pipeline", "same_image_runs", "score_kernels", "split_items", "submit_builds",
           "worker_kernels", "worker_pool"]

#: Where a GPU campaign's worker processes run the methods that are not device resident (tracking), unless
#: told otherwise. On an H200 host with 16 cores, ``paper --full`` took 13.7-15.5 s with them on the CPU and
#: 16.8-17.5 s with them on the GPU, which the 14 processes share by time slices (2026-11-22 03:15-03:17).
PIPELINE_WORKER_DEVICE = "cpu"

_PR_SET_PDEATHSIG = 1
#: How much lower the scheduling priority of ``run_pipeline``'s workers is (``os.nice``): the process that
#: drives the device, whose threads keep its queue filled, goes first when the cores are busy.
WORKER_NICE = 10
#: Measured batches (each a few hundred kB) that may wait for ``run_pipeline``'s workers, per worker.
PENDING_PER_WORKER = 16

#: Processes that drive one GPU through a campaign's pipeline unless told (``run_pipeline(drivers=...)``,
#: ``--drivers``). One: on one H100 (2026-11-28), ``paper --full`` took 22.0 and 23.0 s with one, 22.7 and
#: 23.7 s with two and 26.6 s with three. Two measured the pairs 1.39 times as fast, but the campaign's
#: process waited 2.4 s for the first helper to start before it loaded its kernels; helpers now start in
#: a thread, not yet measured on a GPU (Dask GPU workers that share a GPU, started before the run, are
#: faster: ``distributed.LOCAL_WORKERS_PER_GPU``; docs/benchmarks.md).
PIPELINE_DRIVERS = 1

#: Threads that render ``run_pipeline``'s pairs: while one waits for its kernels, the other plans its pair
#: or reads its images back. More pairs than threads are queued (``renders_ahead``), so that a thread
#: that finishes takes the next pair at once instead of waiting for this process to ask for it.
RENDER_THREADS = 2


def default_workers() -> int:
    """The CPU cores this process may use."""
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


#: The most host processes one GPU's pipeline starts when none are asked for: one GPU keeps about this many
#: busy, and more were slower on every larger host measured (H100 hosts, `bench_scaling`'s baselines,
#: pairs/s with 16 against all cores: 32 cores 2.24 / 2.04; 64 cores 2.43 / 1.39, 2.50 / 1.61, 3.45 / 2.14,
#: 2.81 / 1.93; docs/benchmarks.md).
PIPELINE_MAX_WORKERS = 16


def pipeline_workers(gpus: int = 1) -> int:
    """Host processes of each of ``gpus`` GPU pipelines on this host when none are asked for: a share of
    the cores, at most :data:`PIPELINE_MAX_WORKERS`.

    Examples
    --------
    >>> 1 <= pipeline_workers() <= PIPELINE_MAX_WORKERS
    True
    """
    return max(1, min(default_workers() // max(1, gpus), PIPELINE_MAX_WORKERS))


def die_with_parent(parent_pid: int, preload=(), kernels=(), nice: int = 0) -> None:
    """Worker initialiser: be killed (SIGKILL) when the process that started it exits; exit now if the
    campaign process ``parent_pid`` already has.

    A worker is started by the campaign process itself or by the multiprocessing fork server, which
    exits with the campaign process. Then lower this process's scheduling priority by ``nice``
    (``os.nice``), import the modules ``preload`` names, and load the Warp kernels of the
    ``(module, device)`` pairs of ``kernels`` (Warp hashes a module's code before it finds its binary, a
    second or so per process for the tracking kernels), so the work that needs them later does not wait
    for them.
    """
    started_by = os.getppid()
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != started_by or not _alive(parent_pid):  # died before prctl took effect
        os._exit(1)
    if started_by != parent_pid:  # started by the fork server, which outlives the campaign process while
        _exit_with(parent_pid)  # workers hold its pipe: exit with the campaign process instead
    if nice and hasattr(os, "nice"):
        os.nice(int(nice))
    # One thread for the BLAS and OpenMP libraries: a worker has its core, and a dozen workers each
    # starting a thread per core for a dot product or a solve ran the GPU campaign 1.3-1.6x slower.
    threadpool_limits(limits=1)
    for name in preload:
        importlib.import_module(name)
    if kernels:
        load_kernels(kernels, max_workers=1)  # (a Python module's Warp modules, or one named under it)


def _exit_with(pid: int) -> None:
    """End this process (``os._exit``) as soon as process ``pid`` ends: a daemon thread waits for it, on a
    Linux pidfd where there is one, else by polling."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        os._exit(1)
    except (AttributeError, OSError):
        fd = None

    def watch():
        if fd is not None:
            select.select([fd], [], [])  # readable once the process has ended
        else:
            while _alive(pid):
                time.sleep(0.2)
        os._exit(1)

    threading.Thread(target=watch, name="synthbos-exit-with-campaign", daemon=True).start()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _pool(workers: int, preload=(), kernels=(), nice: int = 0):
    """A pool of ``workers`` processes. Where it can, the fork server starts them: it imports the
    ``preload`` modules (and the items' module) once and forks each worker from itself, so the workers
    begin with them imported (never with CUDA initialised: the fork server imports only); elsewhere
    each worker is a fresh interpreter that imports them itself."""
    preload = _pool_preload(preload)
    context = driver_context(preload)
    return ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=die_with_parent,
                               initargs=(os.getpid(), tuple(preload), tuple(kernels), nice))


def _nothing() -> None:
    """A task that starts a worker process and does nothing."""


def _start_workers(pool, n: int, ready) -> None:
    """Start the ``n`` processes of ``pool`` (each submit starts one while none is idle), then set ``ready``."""
    try:
        for _ in range(n):
            pool.submit(_nothing)
    except RuntimeError:  # the pool was shut down meanwhile (the campaign failed)
        pass
    finally:
        ready.set()


def worker_kernels(scores, *, worker_device=None, stack=0) -> list[tuple[str, str]]:
    """The ``(kernel module, device)`` pairs that the worker processes of :func:`run_pipeline` launch: those
    of the methods that are not device resident (``Method.kernels_on``) nor tracked in stacks (with
    ``stack``), on their processing devices."""
    return score_kernels(split_items(scores, worker_device=worker_device, stack=stack)[2])


def score_kernels(scores) -> list[tuple[str, str]]:
    """The ``(kernel module, device)`` pairs that the score items ``scores`` launch: their methods'
    (``Method.kernels_on``), on their processing devices (the items' last entry)."""
    from .registry import get_method

    return sorted({(name, str(args[-1])) for args in scores if args[-1] is not None
                   for name in get_method(args[1]).kernels_on(args[-1])})


def render_kernels(renders) -> list[tuple[str, str]]:
    """The ``(kernel module, device)`` pairs that the render items ``renders`` launch
    (``raytrace.render_modules`` of each item's configuration, on its device)."""
    from synthbos.raytrace.render import render_modules  # here: scheduling stays free of the algorithm packages

    return sorted({(name, str(args[2])) for args in renders if args[2] is not None
                   for name in render_modules(args[0], device=args[2])})


def campaign_kernels(renders, scores, *, worker_device=None, stack=0) -> list[tuple[str, str]]:
    """Every ``(kernel module, device)`` pair that :func:`run_pipeline` launches: the renderer's on each
    render device, the device-resident methods' here, ``track_pairs``'s here (with ``stack``: stacked
    tracking) and :func:`worker_kernels`."""
    from .registry import STACK_CPU_KERNELS, STACK_KERNELS

    here, stacked, _ = split_items(scores, worker_device=worker_device, stack=stack)
    pairs = set(render_kernels(renders)) | set(score_kernels(here))
    pairs |= {(name, str(args[-1])) for args in stacked
              for name in (STACK_KERNELS if str(args[-1]).startswith("cuda") else STACK_CPU_KERNELS)}
    return sorted(pairs | set(worker_kernels(scores, worker_device=worker_device, stack=stack)))


def run_items(items, fn, *, workers: int, desc: str, progress: bool, kernels=(), pool=None, build_after=()) -> None:
    """Run every ``args`` tuple of ``items`` through ``fn``, in a process pool when ``workers > 1``.

    ``kernels``: the ``(kernel module, device)`` pairs the items launch. With a pool, its processes
    build (or find in Warp's kernel cache) one module each first, all of them before any item starts:
    on a first run, each module is compiled once, the cores side by side, instead of by every process
    that launches it, at the same time (see :func:`build_in_pool`).
    ``pool``: a pool of :func:`worker_pool` to run them in, kept open for the next call (each process
    that compiles builds Warp's precompiled headers once, about 1.6 s on a core); None: a pool of its
    own. ``build_after``: such pairs that the pool's processes build after the last item is handed out,
    for the next call's items, while the last items finish (tasks nobody waits for here: the next
    call's ``kernels`` waits for them).
    """
    if not items:
        return
    bar = tqdm(total=len(items), desc=desc, unit="item", disable=not progress)
    with bar:
        if pool is None and workers <= 1:
            for args in items:
                fn(*args)
                bar.update(1)
            return
        with contextlib.nullcontext(pool) if pool is not None else _pool(workers) as pool:
            build_in_pool(pool, kernels)
            futures = [pool.submit(fn, *args) for args in items]
            later = submit_builds(pool, build_after)
            try:
                for fut in as_completed(futures):
                    fut.result()
                    bar.update(1)
            except BaseException:
                for fut in futures + later:
                    fut.cancel()
                raise


def worker_pool(workers: int):
    """A pool of ``workers`` processes for several calls of :func:`run_items` (their ``pool``), or a
    context giving None where ``workers <= 1`` (the items then run in this process)."""
    return _pool(workers) if workers > 1 else contextlib.nullcontext()


def host_pool(workers: int, kernels=()):
    """A started pool of ``workers`` host processes as :func:`run_pipeline` starts its own (the fork
    server, a lower priority, ``kernels`` loaded), for a caller that keeps it between pipelines
    (``run_pipeline(pool=...)``); the caller shuts it down."""
    pool = _pool(workers, (), kernels, nice=WORKER_NICE)
    _start_workers(pool, workers, threading.Event())
    return pool


def build_in_pool(pool, kernels) -> None:
    """Build the Warp modules of the ``(kernel module, device)`` pairs ``kernels`` in the processes of
    ``pool``, one task per module (an idle process takes the next), and wait for all of them.

    Warp compiles a module when a process first launches one of its kernels, and processes that start
    alike all compile the same one at once: on two cores, the renderer's twice side by side, and the
    cores idle at the end. A module built here is compiled by one process; the others find it in Warp's
    kernel cache. Warm, each task only finds its module there (the processes that launch it later find
    it too, as they would anyway).
    """
    for fut in submit_builds(pool, kernels):
        fut.result()


_BUILDS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # pool -> {(module, device): its build task}


def submit_builds(pool, kernels) -> list:
    """Hand ``pool`` a build task (``load_kernels``) for each ``(kernel module, device)`` pair of ``kernels``
    that it was not handed before; return the tasks of all of them, earlier ones included (a module in
    the middle of its build is not built a second time beside it)."""
    builds = _BUILDS.setdefault(pool, {})
    for pair in kernels:
        if tuple(pair) not in builds:
            builds[tuple(pair)] = pool.submit(load_kernels, [tuple(pair)], max_workers=1)
    return [builds[tuple(pair)] for pair in kernels]


def _launching(fn, *args):
    """``fn(*args)`` inside ``synthbos.device.launching``: a thread that launches beside this process's
    main thread, which may record a CUDA graph meanwhile."""
    with launching():
        return fn(*args)


def pair_tasks(renders, scores):
    """Group a campaign's items by pair file: ``[(render args or None, [score args])]``, in campaign order.

    Render items are ``(config, pair path, device)``; score items start with the pair path.
    """
    by_pair: dict[str, list] = {}
    for args in renders:
        by_pair[str(args[1])] = [args, []]
    for args in scores:
        by_pair.setdefault(str(args[0]), [None, []])[1].append(args)
    return [(r, s) for r, s in by_pair.values()]


def split_by_residency(run, *, worker_device=None) -> tuple[list, list]:
    """Split score items into those whose method is device resident (run by the process that drives
    the GPU) and the others (run by worker processes), the latter moved to ``worker_device`` when given.

    Score items are ``(pair path, method, noise, seeds, out, overrides, processing device)``.
    """
    from .registry import get_method

    here = [args for args in run if get_method(args[1]).device_resident]
    there = [args for args in run if not get_method(args[1]).device_resident]
    if worker_device is not None:
        there = [(*args[:-1], worker_device) for args in there]
    return here, there


def split_items(run, *, worker_device=None, stack=0) -> tuple[list, list, list]:
    """Split score items three ways: the device-resident ones (:func:`split_by_residency`), those tracked in
    stacks (with ``stack`` > 0: ``stacks.split_stacked``), both measured by the process that drives the
    device, and the others, measured by worker processes (on ``worker_device`` when given)."""
    stacked, rest = [], list(run)
    if stack:
        from .stacks import split_stacked  # here: scheduling stays free of the algorithm packages

        stacked, rest = split_stacked(run)
    here, there = split_by_residency(rest, worker_device=worker_device)
    return here, stacked, there


def same_image_runs(scores) -> list[list]:
    """Split score items into runs of consecutive items on the same noisy images (same pair, noise and seeds).

    Score items are ``(pair path, method, noise, seeds, ...)``; a campaign lists a noise level's methods
    one after another.
    """
    def images(args):
        return str(args[0]), float(args[2]), tuple(args[3])

    runs: list[list] = []
    for args in scores:
        if runs and images(runs[-1][-1]) == images(args):
            runs[-1].append(args)
        else:
            runs.append([args])
    return runs


def run_pipeline(renders, scores, *, workers: int, progress: bool, desc: str = "render+process",
                 worker_device=None, jobs=(), renders_ahead: int = 4, on_items_done=None, stop=None, stack=None,
                 stacks_log=None, pool=None, drivers: int = 1, drivers_log=None, claims=None, driver: int = 0) -> list:
    """Run a campaign's items with the device work here and the host work in ``workers - 1`` processes.

    Pair after pair, this process reads the pair and, for each of its score items whose method is
    device resident (``Method.device_resident``: the correlation's Warp path), adds the noise and runs
    the method on the item's processing device (``items.measure_item``); the result goes to a worker
    process that scores it and writes the score file (``items.finish_item``) while this process goes
    on with the next item; the items of a pair measured here, every noise level of it, go to one worker
    together, which reads the pair file and does the pair's share of the scoring once (``synthbos.memo``).
    Methods with host work between their kernels (tracking) would hold this
    process up, so workers measure them, on the item's processing device or on ``worker_device`` when
    given (score items end with their processing device). Consecutive items on the
    same noisy images (one noise level's methods) go to a worker together (``items.process_items``),
    so the work they share is done once there (``tracking`` and ``tracking-cc`` read one
    ``track_pair`` and one triangulation). Meanwhile :data:`RENDER_THREADS` threads render the next
    ``renders_ahead`` pairs (when their files are missing): while one waits for its kernels, the other
    plans its pair or reads its images back, so the device always has a render queued. This process
    measures a rendered pair from memory while a writer thread writes its file; the workers get its items
    once it is written. At most
    ``PENDING_PER_WORKER * workers`` batches wait for a worker, so memory stays bounded when the host is the
    slower side (while the workers start, the device goes on).
    With ``workers <= 1`` everything runs here, item after item (``worker_device`` still applies).

    ``drivers``: processes that drive the device, this one included (``benchmarks.drivers``). With more
    than one, this process starts ``drivers - 1`` helpers, each running this pipeline with its own
    threads and ``workers // drivers - 1`` host processes; every process takes the next pair no one has
    taken (``claims``: the shared :class:`~synthbos.benchmarks.drivers.Claims` a helper is given). A job
    of one pair runs in the process that took that pair; the other jobs, and the results returned,
    are this process's, after every helper has finished (a job run by a helper returns None here).
    ``drivers_log`` (a list) receives the pairs each process took (this one first). ``claims`` and
    ``driver`` (its number) are a helper's.

    ``stack``: pairs per stack of tracking items (``stacks``). With ``stack`` > 0 this process also
    tracks the items of the trackers whose settings ``track_pairs`` runs (``registry.stack_settings``),
    the noisy image pairs of every noise level of up to ``stack`` pairs in one ``track_pairs`` call on
    their processing device, and hands each item's result to the workers to score and write, as it does
    the device-resident methods'; 0 leaves them to the workers, item by item; None (the default) is
    ``stacks.default_stack``: stacks on a GPU, item by item on the CPU. An interrupted run loses the
    items of the stacks still open as well as those in flight; a run again stacks the missing items
    only, with the same results. ``stacks_log`` (a list) receives one entry per ``track_pairs`` call
    (``stacks.Stacks``).

    ``jobs``: ``(fn, args, pairs)`` tuples of other host work (tables, figures), run by the worker
    processes: as soon as every pair file in ``pairs`` is there when ``pairs`` is a set of pair paths, or
    after the last item when it is None (``on_items_done()``, when given, is called just before).
    Returns their results, in order.

    ``stop``: a callable asked before each pair; once it returns True no further pair is started (the
    items already handed out finish and are written; the jobs still run). A Dask task uses it.

    ``pool``: a callable giving the ``workers - 1`` host processes to hand the work to, kept open by the
    caller (:func:`host_pool`: a Dask GPU worker keeps its own between tasks); called once the kernels are
    built, so that new processes find them in the cache instead of each compiling them. None starts the
    processes here and shuts them down at the end.
    """
    from synthbos.raytrace import read_pair, write_pair  # here: scheduling stays free of the algorithm packages

    from .items import finish_item, measure_item, prepared_inputs, process_items, render_only
    from .stacks import Stacks, default_stack

    stack = default_stack(scores) if stack is None else int(stack)
    stacks = Stacks(stack, log=stacks_log) if stack else None
    tasks = pair_tasks(renders, scores)
    task_paths = [str(r[1]) if r is not None else str(items[0][0]) for r, items in tasks]  # each task's pair file
    task_of = {path: k for k, path in enumerate(task_paths)}
    own_pool = pool is None
    # The workers start with the jobs' modules (matplotlib for figures) imported, as with the items' (``_pool``):
    # a job function's own module, or the one its ``preload`` attribute names (``campaign.draw_figure``).
    preload = sorted({getattr(fn, "preload", fn.__module__) for fn, _, _ in jobs})
    lead = claims is None  # this process runs the jobs of several pairs and returns the results
    helpers = []  # the helper processes, once started
    drivers = max(1, min(int(drivers), len(tasks))) if own_pool and workers > 1 and lead else 1
    starting = None  # the thread that starts them
    if drivers > 1:
        context = driver_context(_pool_preload([*preload, __name__, "synthbos.benchmarks.stacks"]))
        if context.get_start_method() == "forkserver":  # a Ctrl-C: one line, from this process
            quiet_resource_tracker()
            ignoring_sigint_forkserver()
        claims = Claims(len(tasks), context)
        options = {"workers": max(2, workers // drivers), "worker_device": worker_device, "jobs": jobs,
                   "renders_ahead": renders_ahead, "stack": stack}
        # In a thread: a start waits for the fork server, which imports the modules first (2.4 s on an H100's
        # host), while this process loads its kernels and starts rendering meanwhile.
        starting = threading.Thread(
            target=lambda: helpers.extend(start_drivers(drivers - 1, _drive, (renders, scores, claims, options),
                                                        context)), name="synthbos-start-drivers", daemon=True)
        starting.start()
    bar = tqdm(total=len(renders) + len(scores) + len(jobs), desc=desc, unit="item", disable=not progress)
    pending: dict = {}  # future -> how many items it scores
    taken: list = []  # the tasks this process took, in order (every task, without helpers)
    mine: set = set()  # their pair files
    waiting = list(range(len(jobs)))  # jobs not yet started
    started: dict = {}  # job index -> its future (or its result, without a pool)
    writing: set = {str(args[1]) for args in renders}  # pair files this process may render: not yet waited for

    def advance(n: int) -> None:
        """Count ``n`` finished items on the bar (with helpers: every process's, ``Claims.advance``)."""
        if claims is None:
            bar.update(n)
        else:
            bar.update(claims.advance(n) - bar.n)

    def owns(pairs) -> bool:
        """Whether this process runs a job of ``pairs``: a job of one pair where it took that pair (or, the
        lead, where no task has it), any other job where it is the lead."""
        if claims is None:
            return True
        if pairs is not None and len(pairs) == 1:
            path = str(next(iter(pairs)))
            return lead if path not in task_of else path in mine
        return lead

    def written_all(pairs) -> bool:
        """Whether every pair file of a job is there: one this process may render once it has waited for
        its writing (``file_written``), one another process took once it is on the disk."""
        return all(p not in writing or (claims is not None and p not in mine and os.path.exists(p))
                   for p in map(str, pairs))

    def collect(block: bool) -> None:
        if not pending:
            return
        done, _ = wait(pending, timeout=None if block else 0, return_when=FIRST_COMPLETED)
        for fut in done:
            fut.result()  # a worker's error stops the campaign here
            advance(pending.pop(fut))

    def start_jobs(final: bool) -> None:
        if pool is not None and not pool_ready.is_set():
            if not final:
                return  # tried again once the workers are started
            pool_ready.wait()
        for j in list(waiting):
            fn, args, pairs = jobs[j]
            if not owns(pairs):
                continue
            if not (final or (pairs is not None and written_all(pairs))):
                continue
            waiting.remove(j)
            started[j] = pool.submit(fn, *args) if pool is not None else fn(*args)
            if pool is None:
                advance(1)

    def file_written(written, path) -> None:
        """Wait for the pair file ``path`` being ``written`` (the workers and the jobs read it), once; start
        the jobs it completes."""
        if written is not None and path in writing:
            written.result()
            writing.discard(path)
            start_jobs(final=False)

    def make_images(k: int, pair) -> None:
        """Start drawing the noisy images of pair ``k``'s runs that this process measures (NumPy's draws
        release the GIL: they overlap the device work). Once per pair: called by the render thread as
        the pair is done, and by this thread before it measures the pair."""
        with images_lock:
            if k in images:
                return
            images[k] = {}
            for r, run in enumerate(same_image_runs(tasks[k][1])):
                here, stacked, _ = split_items(run, worker_device=worker_device, stack=stack)
                if here or stacked:
                    images[k][r] = noiser.submit(prepared_inputs, pair, run, here)

    def render(k: int):
        args = tasks[k][0]
        if args is None:
            return None
        fut = renderer.submit(_launching, render_only, args[0], args[2])
        if pool is not None:  # the pair's noisy images are drawn as soon as it is rendered
            fut.add_done_callback(lambda f: f.cancelled() or f.exception() is not None or make_images(k, f.result()))
        return fut

    def take_next() -> None:
        """Take the next task (from ``claims`` with helpers, else the next in order) and start its render."""
        k = claims.take(driver) if claims is not None else (len(taken) if len(taken) < len(tasks) else None)
        if k is not None:
            taken.append(k)
            mine.add(task_paths[k])
            rendering.append(render(k))

    def submit_ready(block: bool) -> None:
        """Hand the measured runs to the workers, in order, once their pair file is written and the
        workers are started (``block``: wait for both)."""
        if not pool_ready.is_set():
            if not block:
                return
            pool_ready.wait()
        if waiting:
            start_jobs(final=False)  # jobs whose pair files were written while the workers started
        while deferred and (block or deferred[0][0] is None or deferred[0][0].done()):
            written, path, batch, there, n = deferred.popleft()
            file_written(written, path)
            if n:
                pending[pool.submit(process_items, batch, there)] = n
            collect(block=False)
            while len(pending) >= PENDING_PER_WORKER * workers:
                collect(block=True)

    def hand_out(measured) -> None:
        """Score and write, or hand to the workers, the items that the stacks measured
        (``Stacks.take``: ``((pair file being written, its path), finish_item arguments)``)."""
        for (written, path), hosts in measured:
            if pool is None:
                for host in hosts:
                    finish_item(*host)
                    advance(1)
            else:
                deferred.append((written, path, hosts, [], len(hosts)))
        submit_ready(block=False)

    def poll() -> None:
        """While the helpers finish: the bar, and the jobs whose pair files they wrote."""
        advance(0)
        start_jobs(final=False)

    ahead = max(1, int(renders_ahead))
    images: dict = {}  # task index -> {run index: future of its noisy images}
    images_lock = threading.Lock()
    deferred: deque = deque()  # (pair file being written, its path, measured batch, worker items, count)
    rendering = []  # the render of each task taken, in the order taken (None: its file is there)
    pool_ready = threading.Event()
    threads = []  # the render, writer and noise threads, once started
    try:
        load_kernels(campaign_kernels(renders, scores, worker_device=worker_device, stack=stack))  # a cold cache
        if not own_pool:
            pool = pool()
        elif workers > 1:
            pool = _pool(workers - 1, preload, worker_kernels(scores, worker_device=worker_device, stack=stack),
                         nice=WORKER_NICE)
        renderer = ThreadPoolExecutor(min(ahead, RENDER_THREADS), thread_name_prefix="synthbos-render")
        writer = ThreadPoolExecutor(2, thread_name_prefix="synthbos-write")
        noiser = ThreadPoolExecutor(4, thread_name_prefix="synthbos-noise")
        threads = [renderer, noiser, writer]  # shut down in this order: a pair file being written is finished
        if pool is None or not own_pool:
            pool_ready.set()
        else:  # a thread starts the workers (the fork server imports first), so this one can go on
            threading.Thread(target=_start_workers, args=(pool, workers - 1, pool_ready), daemon=True,
                             name="synthbos-start-workers").start()
        # The render threads launch too (each render inside ``launching``: a graph is recorded here while
        # none is in progress). The BLAS keeps to one thread here too: the workers have the other cores.
        with bar, threadpool_limits(limits=1):
            for _ in range(ahead):
                take_next()
            start_jobs(final=False)
            i = 0
            while i < len(taken):
                if stop is not None and stop():
                    break
                take_next()  # the next pairs render while this one is processed
                k = taken[i]
                render_args, items = tasks[k]
                written = None
                if rendering[i] is not None:  # this process measures from the rendered pair in memory
                    pair = rendering[i].result()
                    written = writer.submit(write_pair, render_args[1], pair)
                    advance(1)
                else:
                    pair = read_pair(items[0][0]) if items else None
                path = None if render_args is None else str(render_args[1])
                if pool is None:
                    file_written(written, path)
                if pool is not None and pair is not None:
                    make_images(k, pair)
                prepared = images.get(k, {})
                to_stack = []  # (noisy images, items) of the pair's runs that stacks track
                measured = []  # the pair's items measured here, every noise level: one worker scores them all
                for r, run in enumerate(same_image_runs(items)):
                    here, stacked, there = split_items(run, worker_device=worker_device, stack=stack)
                    noisy, settings = prepared[r].result() if r in prepared else (None, {})
                    if stacked:
                        to_stack.append((noisy, stacked))
                    if pool is None:
                        for args in [*here, *there]:
                            finish_item(*measure_item(pair, *args), pair=pair)
                            advance(1)
                        continue
                    measured.extend(measure_item(pair, *args, images=noisy, settings=settings.get(id(args)))
                                    for args in here)
                    if there:  # the workers read the pair file: they get the run once it is written
                        deferred.append((written, path, [], there, len(there)))
                        submit_ready(block=False)
                if measured:  # one task: the pair's file read, triangulation and neighbours once, not per run
                    deferred.append((written, path, measured, [], len(measured)))
                    submit_ready(block=False)
                if pool is not None and not items:
                    deferred.append((written, path, None, None, 0))
                images[k] = {}  # drawn and measured: let them go
                if to_stack:
                    stacks.add((written, path), pair, to_stack)
                    hand_out(stacks.take())
                submit_ready(block=False)
                i += 1
            if stacks is not None:  # the pairs started are finished (also when told to stop)
                stacks.flush()
                hand_out(stacks.take())
            submit_ready(block=True)
            while pending:
                collect(block=True)
            if starting is not None:
                starting.join()
                join_drivers(helpers, claims, poll=poll)
            if drivers_log is not None:
                drivers_log.extend(claims.counts(drivers) if starting is not None else [len(taken)])
            if on_items_done is not None:
                on_items_done()
            start_jobs(final=True)
            results = []
            for j in range(len(jobs)):
                if j not in started:  # another process's job
                    results.append(None)
                elif pool is None:
                    results.append(started[j])
                else:
                    results.append(started[j].result())
                    advance(1)
            return results
    except BaseException:
        if starting is not None:
            starting.join()
        stop_drivers(helpers)
        for fut in [*pending, *(f for f in rendering if f is not None)]:
            fut.cancel()
        for fut in started.values() if pool is not None else ():
            fut.cancel()
        raise
    finally:
        for executor in threads:
            executor.shutdown(wait=True)
        if pool is not None and own_pool:
            pool.shutdown(wait=True, cancel_futures=True)


def _pool_preload(preload) -> list[str]:
    """The modules the fork server imports before its first fork: ``preload`` and the items' (``_pool``)."""
    return sorted({"synthbos.benchmarks.items", *preload})


def _drive(renders, scores, claims, options: dict, driver: int, campaign_pid: int) -> None:
    """A helper that drives the device beside the campaign's process (``run_pipeline(drivers=...)``):
    the same pipeline over the pairs it takes from ``claims``; a failure is left with ``claims`` and
    ends the process with status 1."""
    die_with_parent(campaign_pid)
    try:
        init_warp()
        run_pipeline(renders, scores, progress=False, claims=claims, driver=driver, **options)
    except BaseException as err:  # reported to the campaign's process, which raises it
        text = str(err) if isinstance(err, SynthbosError) else "".join(
            traceback.format_exception_only(type(err), err)).strip()
        claims.fail(f"a process that drove the GPU beside the campaign's: {text}")
        sys.exit(1)
