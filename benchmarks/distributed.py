"""Campaigns and sweeps on a Dask cluster: the GPUs of one node, or many nodes through a scheduler.

``--scheduler local`` starts a local Dask cluster (a ``distributed.SpecCluster``, the class that
``LocalCluster`` builds on) with :data:`LOCAL_WORKERS_PER_GPU` single-threaded worker processes per GPU
(or ``--workers`` in all), each pinned to its GPU
through ``CUDA_VISIBLE_DEVICES`` so that its ``cuda:0`` is that GPU (dask-cuda's rule), or ``--workers``
CPU workers when the campaign renders on the CPU. ``--scheduler tcp://HOST:PORT`` or
``--scheduler FILE.json`` (a scheduler file) joins a running cluster instead (``dask scheduler`` and
``dask worker`` by hand, dask-jobqueue on SLURM or PBS, dask-cuda's ``LocalCUDACluster``); its workers
must import this same synthbos and see the campaign folder at the same path.

On CPU workers the unit of work is the pair: one task renders a pair (when its file is missing) and then
processes and scores it with every method at every noise level on the same worker, reading the pair file
it has just written, so images never travel through the scheduler; only file paths, settings and item
counts do. A GPU worker instead runs the single-node pipeline (``scheduling.run_pipeline``) over the pairs
it takes, with its own pool of host processes (its share of the host's cores), so that it keeps its GPU as
busy as a campaign without Dask does: one task per GPU worker, each given every pair, and each taking the
next pair no worker has taken as it frees up (``drivers.FileClaims``: a file per pair, created atomically,
in a folder of the run beside the pair files), so a faster worker does more pairs and none waits at the
end for a slower one. Every file is written atomically by the worker that makes it, and finished files are
skipped, so the folder layout and the resume are those of a run in one process, and since every seed comes
from the campaign spec the results are byte-identical to it whatever the number and kind of workers.

Failures: a worker that dies loses only the item it was writing; the scheduler hands its task to another
worker, which skips the files already there (a pipeline task's pairs stay taken: once the other workers
are done the client runs the pairs still missing again, with new claims). Interrupting the client (Ctrl-C)
cancels every task: a cluster this module started is shut down with its worker processes; on a cluster
that was joined, each worker stops after the item it is writing (an atomic write, seconds on a GPU), and
the client waits for that before it returns, so no task is left writing into the folder (a second Ctrl-C
stops waiting).

Dask is imported only here, and only when a scheduler is asked for.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import shutil
import signal
import threading
import time
import uuid
from collections import defaultdict
from pathlib import Path

from tqdm.auto import tqdm

from synthbos import SynthbosError
from synthbos.values import shorten

from .drivers import FileClaims, ignoring_sigint_forkserver, quiet_resource_tracker
from .integrate import floor_current, pair_floor
from .items import render_item, score_item
from .scheduling import (
    PIPELINE_WORKER_DEVICE,
    default_workers,
    host_pool,
    pair_tasks,
    pipeline_workers,
    run_pipeline,
    worker_kernels,
)

__all__ = ["LOCAL_WORKERS_PER_GPU", "PIPELINE_ROUNDS", "PROGRESS_POLL_S", "DaskRunner", "campaign_runner",
           "check_address", "check_scheduler", "finished_pairs", "pair_task", "pipeline_task", "run_pairs",
           "task_outputs", "visible_gpus"]

DASHBOARD_ADDRESS = ":8787"
TASK_PREFIX = "synthbos-pair"
#: Environment variable giving a local GPU worker the size of its pool of host processes; set by the user
#: (a positive integer), it replaces each GPU worker's share of the cores (``pipeline_workers``).
HOST_WORKERS_VAR = "SYNTHBOS_HOST_WORKERS"
#: Local GPU workers per GPU unless ``--workers`` says otherwise: two pipelines share each GPU, each with
#: half the GPU's share of the cores. One H100 (16 cores), 50 pairs of the full campaign, warm workers
#: (2026-11-27/28): 3.6 pairs/s with one worker, 5.0 and 4.6 with two, 5.3 with three; the plain campaign
#: on the same machines 3.7 and 2.9 pairs/s (docs/benchmarks.md).
LOCAL_WORKERS_PER_GPU = 2
#: Rounds of pipeline tasks a run may take: the first runs every pair; a later one only the pairs left
#: missing when the workers of the one before had finished (a worker died with pairs it had taken).
PIPELINE_ROUNDS = 3

# Worker-process state: the runs told to stop, and the runs with an item in flight (run token -> count).
_STOPPED: set[str] = set()
_IN_FLIGHT: dict[str, int] = defaultdict(int)
_LOCK = threading.Lock()


def _distributed():
    try:
        import distributed
    except ImportError:
        raise SynthbosError("--scheduler needs Dask: pip install 'dask[distributed]' "
                            "(or synthbos with its 'dask' extra)") from None
    return distributed


#: Dask's communication protocols a scheduler address may name.
PROTOCOLS = ("tcp", "tls", "ws", "wss", "ucx", "inproc")
#: Largest scheduler file read (Dask's own are a few hundred bytes).
MAX_SCHEDULER_FILE = 1 << 20
_SCHEDULER_HINT = "'local', PROTOCOL://HOST:PORT (e.g. tcp://10.0.0.1:8786) or a scheduler file (JSON)"


def check_address(address, *, what="--scheduler") -> str:
    """Check a Dask scheduler address ``PROTOCOL://HOST:PORT`` (or ``HOST:PORT``, TCP); return it."""
    if not isinstance(address, str) or not address or len(address) > 1024:
        raise SynthbosError(f"{what}: the scheduler address must be text {_SCHEDULER_HINT}, got {shorten(address)}")
    protocol, sep, rest = address.partition("://")
    if not sep:
        protocol, rest = "tcp", address
    if protocol not in PROTOCOLS:
        raise SynthbosError(f"{what} {shorten(address)}: unknown protocol {shorten(protocol)}; "
                            f"Dask knows {', '.join(PROTOCOLS)}")
    if protocol == "inproc":
        return address
    host, colon, port = rest.rpartition(":")
    if not colon or not host or any(c.isspace() or c in "/?#@" for c in host):
        raise SynthbosError(f"{what} {shorten(address)}: expected {protocol}://HOST:PORT")
    if not (port.isdigit() and 1 <= int(port) <= 65535):
        raise SynthbosError(f"{what} {shorten(address)}: the port must be a number 1 to 65535, got {shorten(port)}")
    return address


def check_scheduler(scheduler) -> dict | None:
    """Check a ``--scheduler`` value before any work; return how to join it (None for ``"local"``).

    Returns ``{"address": ...}`` for an address, ``{"scheduler_file": ...}`` for a scheduler file whose
    JSON object names a valid ``address``. Anything else (a missing, empty, unreadable or over-large
    file, JSON that is not an object, no address, an unknown protocol, a bad port) is refused with
    one line; for ``"local"``, so is a :data:`HOST_WORKERS_VAR` that is not a positive integer.
    """
    text = str(scheduler)
    if text == "local":
        _host_workers_told()
        return None
    path = Path(text) if len(text) <= 4096 and "\0" not in text else None
    looks_like_file = path is not None and (text.endswith(".json") or path.is_file())
    if not looks_like_file:
        if "://" not in text and ":" not in text:
            raise SynthbosError(f"--scheduler must be {_SCHEDULER_HINT}, got {shorten(text)}")
        return {"address": check_address(text)}
    if not path.is_file():
        raise SynthbosError(f"scheduler file {path} does not exist")
    if path.stat().st_size > MAX_SCHEDULER_FILE:
        raise SynthbosError(f"scheduler file {path} is {path.stat().st_size:,} bytes: not a Dask scheduler file")
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
        raise SynthbosError(f"scheduler file {path} is not JSON (Dask writes one with `dask scheduler "
                            "--scheduler-file FILE`)") from None
    except OSError as err:
        raise SynthbosError(f"cannot read scheduler file {path}: {err.strerror}") from None
    if not isinstance(data, dict):
        raise SynthbosError(f"scheduler file {path} holds a JSON {type(data).__name__}, not an object "
                            "with the scheduler's address")
    if "address" not in data:
        raise SynthbosError(f"scheduler file {path} names no address (its keys: {shorten(sorted(data))})")
    check_address(data["address"], what=f"scheduler file {path}:")
    return {"scheduler_file": str(path)}


def visible_gpus() -> list[str]:
    """The CUDA devices this process may use, as ``CUDA_VISIBLE_DEVICES`` entries (indices or UUIDs)."""
    import warp as wp

    from synthbos.device import init_warp

    init_warp()
    n = wp.get_cuda_device_count()
    listed = [d.strip() for d in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if d.strip()]
    if "CUDA_VISIBLE_DEVICES" in os.environ:
        return listed[:n]
    return [str(i) for i in range(n)]


# --- what runs on a worker -------------------------------------------------------------------------


def _thread_share(n_workers: int) -> dict:
    """Environment giving one of ``n_workers`` local workers its share of the host's cores for the
    thread pools of NumPy's BLAS and OpenMP (as dask-cuda gives each GPU worker its CPUs): without it
    every worker starts a pool as large as the host and the workers oversubscribe the cores. GPU
    workers get a share per GPU of the host, however many of the GPUs a run uses, so that runs on 1, 2
    or 4 GPUs give each worker the same cores."""
    k = str(max(1, default_workers() // max(1, n_workers)))
    return {var: k for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def pair_task(render, scores, token: str) -> tuple[int, int]:
    """Render one pair (``render`` args, or None when its file exists) and score it (``scores`` args).

    Runs on a worker; skips every output that exists and stops between items once the run ``token``
    is told to stop. Returns ``(items written, 1)`` (one pair, as :func:`pipeline_task` counts).
    """
    done = 0
    with _LOCK:
        _IN_FLIGHT[token] += 1
    try:
        if render is not None and not Path(render[1]).exists() and token not in _STOPPED:
            render_item(*render)
            done += 1
        for args in scores:
            if token in _STOPPED:
                break
            if not Path(args[4]).exists():
                score_item(*args)
                done += 1
    finally:
        with _LOCK:
            _IN_FLIGHT[token] -= 1
    return done, 1


def _host_workers_told() -> str | None:
    """The user's :data:`HOST_WORKERS_VAR` where it is a positive integer (else None; anything else is refused)."""
    told = os.environ.get(HOST_WORKERS_VAR, "").strip()
    if not told:
        return None
    if not told.isdigit() or int(told) < 1:
        raise SynthbosError(f"{HOST_WORKERS_VAR}={told!r}: give a positive number of host processes per GPU worker")
    return told


def host_workers() -> int:
    """On a worker: the size of its pipeline's pool of host processes. A local GPU worker is told (its
    share of the host's cores); on a joined cluster, :data:`HOST_WORKERS_VAR` where the worker's host sets
    it, else this host's cores over its visible GPUs; 1 in a daemonic worker process (Dask's default),
    which may not start processes of its own."""
    import multiprocessing

    if multiprocessing.current_process().daemon:
        return 1
    told = _host_workers_told()  # (a bad value is refused here too, in the same line as by the runner)
    return int(told) if told else pipeline_workers(len(visible_gpus()))


def pipeline_task(renders, scores, token: str, worker_device=None, stack=None, claims=None) -> tuple[int, int]:
    """Run a campaign's pairs through the single-node pipeline (``scheduling.run_pipeline``) on this GPU
    worker, with :func:`host_workers` host processes and its tracking items in stacks of ``stack`` pairs
    (None: the pipeline's default, stacks on a GPU), and its pairs' density floors
    (``integrate.pair_floor``) in those processes; starts no further pair once run ``token`` is told to
    stop. ``claims`` (a :class:`~synthbos.benchmarks.drivers.FileClaims` over every pair of the run, which
    every worker is given) shares the pairs out as the workers free up: this worker runs the pairs it
    takes. Without it, every pair whose files are missing. Returns ``(items written, pairs run)``."""
    if claims is None:  # every missing item here
        renders = [r for r in renders if not Path(r[1]).exists()]
        scores = [s for s in scores if not Path(s[4]).exists()]
    # (with claims every worker sees the same list, whose positions the claims name)
    pairs = sorted({str(r[1]) for r in renders} | {str(s[0]) for s in scores})
    there = PIPELINE_WORKER_DEVICE if worker_device is None else worker_device
    workers = host_workers()
    # its campaign pairs' density floors, each as soon as its pair file is there (the table reads them)
    jobs = [(pair_floor, (p,), {p}) for p in pairs if Path(p).parent.name == "pairs" and not floor_current(p)]
    with _LOCK:
        _IN_FLIGHT[token] += 1
    try:
        run_pipeline(renders, scores, workers=workers, progress=False, worker_device=there, jobs=jobs,
                     stop=lambda: token in _STOPPED, stack=stack, claims=claims,
                     pool=lambda: _kept_pool(workers - 1, worker_kernels(scores, worker_device=there, stack=stack)))
    finally:
        with _LOCK:
            _IN_FLIGHT[token] -= 1
    tasks = pair_tasks(renders, scores)
    mine = [tasks[k] for k in claims.taken] if claims is not None else tasks
    return sum(os.path.exists(f) for task in mine for f in task_outputs(task)), len(mine)


#: This worker's pool of host processes, kept between its pipeline tasks: ``(size, pool)``.
_KEPT_POOL: list = []


def _kept_pool(n: int, kernels):
    """This worker's ``n`` host processes (None for none), started by its first pipeline task and kept for
    the next ones: a campaign does not wait for 15 processes to start and load their kernels, on every GPU
    worker of the host at once. Started again where its size changed or a process of it died."""
    if n < 1:
        return None
    with _LOCK:
        if _KEPT_POOL and (_KEPT_POOL[0][0] != n or getattr(_KEPT_POOL[0][1], "_broken", False)):
            _KEPT_POOL.pop()[1].shutdown(wait=False, cancel_futures=True)
        if not _KEPT_POOL:
            _KEPT_POOL.append((n, host_pool(n, kernels)))
        return _KEPT_POOL[0][1]


def _stop_run(token: str) -> int:
    """On a worker: let no task of run ``token`` start another item; return how many are in flight."""
    with _LOCK:
        _STOPPED.add(token)
        return _IN_FLIGHT[token]


def _in_flight(token: str) -> int:
    with _LOCK:
        return _IN_FLIGHT[token]


def task_outputs(task) -> list[str]:
    """The files a pair task (``scheduling.pair_tasks``) writes: its pair file when it renders one, then its
    score files.

    Examples
    --------
    >>> task_outputs((("cfg", "p0.h5", "cpu"), [("p0.h5", "tracking", 1.0, (1, 2), "p0-t.npz")]))
    ['p0.h5', 'p0-t.npz']
    """
    render, items = task
    return [*([str(render[1])] if render is not None else []), *(str(s[4]) for s in items)]


#: Seconds between two looks at the files of a round's pipeline tasks, for the progress bar.
PROGRESS_POLL_S = 1.0


def finished_pairs(outputs) -> tuple[list, int]:
    """Of ``outputs`` (each pair's output files, its score files last), the pairs not finished yet, and how
    many are: a pair is finished once all its files are there (checked from the last, which most often
    is not yet).

    Examples
    --------
    >>> import os, tempfile
    >>> folder = tempfile.mkdtemp()
    >>> done = os.path.join(folder, "a.npz"); open(done, "w").close()
    >>> finished_pairs([[done], [done, os.path.join(folder, "b.npz")]])[1]
    1
    """
    left = [files for files in outputs if not all(os.path.exists(f) for f in reversed(files))]
    return left, len(outputs) - len(left)


def _watch_pairs(outputs, bar, ended: threading.Event) -> None:
    """Advance ``bar`` by each pair of ``outputs`` as its files appear, until ``ended`` (then once more)."""
    while outputs:
        stop = ended.wait(PROGRESS_POLL_S)
        outputs, n = finished_pairs(outputs)
        bar.update(n)
        if stop:
            return


# --- the client side -------------------------------------------------------------------------------


_pair_tasks = pair_tasks  # one home: scheduling


def _remove_stale_temporaries(paths) -> None:
    """Temporary files of finished outputs (left by a worker that died while writing one)."""
    for folder in {Path(p).parent for p in paths}:
        for tmp in folder.glob(".*.tmp"):
            final = tmp.name[1:-len(".tmp")].rsplit(".", 1)[0]
            if (folder / final).exists():
                tmp.unlink(missing_ok=True)


# A local cluster's workers log only what is critical: their errors reach this process through the tasks, and a
# Ctrl-C, which closes the scheduler under workers still busy, would otherwise print their lost heartbeats.
WORKER_LOG_LEVEL = logging.CRITICAL

def _leave_sigint_to_the_client() -> None:
    """In a local cluster's worker: ignore SIGINT (Ctrl-C), which the client handles by closing the cluster;
    the worker would otherwise end with a traceback. Runs on the worker's event loop, its main thread."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _deferred_sigint():
    """Hold a Ctrl-C back while a local cluster starts and raise it (KeyboardInterrupt) once it stands, so
    that the cluster is whole when it is closed again (one interrupted half-way fails its own closing)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    old = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
    if caught:
        raise KeyboardInterrupt


class DaskRunner:
    """A Dask client for a campaign or a sweep: a local cluster it starts, or a cluster it joins.

    Parameters
    ----------
    scheduler : str
        ``"local"``, a scheduler address (``tcp://host:port``) or a scheduler file (JSON).
    device : str, optional
        The campaign's Warp device: a ``cuda`` device makes a local cluster of GPU workers,
        :data:`LOCAL_WORKERS_PER_GPU` per GPU.
    process_device : str, optional
        The campaign's processing device, when it differs from ``device``; a ``cuda`` one also makes
        the local cluster of GPU workers.
    workers : int, optional
        Local cluster: how many workers (default :data:`LOCAL_WORKERS_PER_GPU` per GPU, or every CPU core
        for CPU workers);
        with more workers than GPUs they share the GPUs in turn.
    gpus : sequence of str, optional
        Local cluster: the GPUs to pin workers to (default every visible one).
    progress : bool
        Show a tqdm bar over the pair tasks.
    dashboard_address : str
        Local cluster: where its dashboard listens.
    pipeline : bool, optional
        Run each worker's share of the pairs through the single-node pipeline with a pool of host
        processes (:func:`pipeline_task`) instead of one task per pair; default: on GPU workers.
    """

    def __init__(self, scheduler: str, *, device=None, workers=None, gpus=None, progress=True,
                 dashboard_address=DASHBOARD_ADDRESS, process_device=None, pipeline=None):
        self.scheduler = str(scheduler)
        self.pipeline = str(device or "").startswith("cuda") if pipeline is None else bool(pipeline)
        self.device = device
        self.process_device = process_device
        self.workers = workers
        self.gpus = None if gpus is None else [str(g) for g in gpus]
        self.progress = progress
        self.dashboard_address = dashboard_address
        self.cluster = None
        self.client = None
        self.description = ""
        self._bar = None
        self._futures: set = set()
        self._lock = threading.Lock()
        self._tokens: set[str] = set()

    # opening and closing

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()

    def open(self) -> DaskRunner:
        try:
            self._open()
        except BaseException:  # a bad address, Ctrl-C during start-up: leave no cluster behind
            self.close()
            raise
        need = "" if self.cluster is None or importlib.util.find_spec("bokeh") else " (pip install bokeh to see it)"
        print(f"dask: {self.description}; dashboard {self.client.dashboard_link}{need}", flush=True)
        return self

    def _open(self) -> None:
        distributed = _distributed()
        if self.scheduler == "local":
            import dask

            # A terminal's Ctrl-C reaches the whole process group; this process closes the workers in order,
            # and the workers, forked from a fork server that ignores SIGINT, ignore it from their start.
            quiet_resource_tracker()
            ignoring_sigint_forkserver()
            # Not daemonic: a GPU worker runs the pipeline, with a pool of host processes of its own.
            with _deferred_sigint(), dask.config.set({"distributed.worker.multiprocessing-method": "forkserver",
                                                      "distributed.worker.daemon": False}):
                self.cluster = self._local_cluster(distributed)
                self.client = distributed.Client(self.cluster)
                self.client.run(_leave_sigint_to_the_client)
        else:
            address = self.scheduler
            where = check_scheduler(address)
            try:
                self.client = distributed.Client(**where, timeout="30s")
            except OSError as err:  # TimeoutError included
                raise SynthbosError(f"cannot reach the Dask scheduler at {address}: {err}") from None
            n = len(self.client.nthreads())
            self.description = f"joined the Dask scheduler at {self.client.scheduler.address} ({n} workers)"

    def local_worker_specs(self, distributed) -> dict:
        """The local cluster's workers: ``{name: {"cls": Nanny, "options": ...}}``; sets ``description``."""
        cuda = [str(d) for d in (self.device, self.process_device) if d is not None and str(d).startswith("cuda")]
        if cuda:
            for d in cuda:
                if d not in ("cuda", "cuda:0"):
                    raise SynthbosError(f"--device {d}: with --scheduler local every worker has its own GPU, "
                                        "its cuda:0; choose the GPUs with CUDA_VISIBLE_DEVICES")
            host_gpus = visible_gpus()
            gpus = self.gpus if self.gpus is not None else host_gpus
            if not gpus:
                raise SynthbosError(f"--device {cuda[0]} but no CUDA device is visible")
            n = self.workers or len(gpus) * LOCAL_WORKERS_PER_GPU
            pinned = [gpus[i % len(gpus)] for i in range(n)]
            names = [f"gpu{g}" if n == len(gpus) else f"gpu{g}-{i}" for i, g in enumerate(pinned)]
            per_gpu = -(-n // len(gpus))  # workers sharing one GPU: each gets that share of a GPU's cores
            share = max(n, per_gpu * len(gpus), per_gpu * len(host_gpus))
            threads = {**_thread_share(share), HOST_WORKERS_VAR: _host_workers_told() or str(pipeline_workers(share))}
            envs = [{"CUDA_VISIBLE_DEVICES": g, **threads} for g in pinned]
            self.description = f"local cluster of {n} GPU worker(s) on GPU(s) {', '.join(pinned)}"
        else:
            n = self.workers or default_workers()
            names, envs = [f"cpu{i}" for i in range(n)], [_thread_share(n)] * n
            self.description = f"local cluster of {n} CPU worker(s)"
        memory = distributed.system.MEMORY_LIMIT // n
        return {
            name: {"cls": distributed.Nanny, "options": {
                "nthreads": 1, "host": "127.0.0.1", "memory_limit": memory, "silence_logs": WORKER_LOG_LEVEL,
                "env": env,
            }}
            for name, env in zip(names, envs, strict=True)
        }

    def _local_cluster(self, distributed):
        workers = self.local_worker_specs(distributed)
        scheduler = {"cls": distributed.Scheduler,
                     "options": {"host": "127.0.0.1", "dashboard_address": self.dashboard_address}}
        return distributed.SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.ERROR,
                                       name="synthbos")

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        if self.client is not None:
            self.client.close()
            self.client = None
        if self.cluster is not None:  # ours: its worker processes end with it
            self.cluster.close()
            self.cluster = None

    # running

    def _progress_bar(self, n: int):
        with self._lock:
            if self._bar is None:
                self._bar = tqdm(total=n, desc="render+process", unit="pair", disable=not self.progress)
            else:
                self._bar.total += n
                self._bar.refresh()
            return self._bar

    def map(self, fn, *iterables) -> list:
        """``fn`` over ``iterables`` as tasks on the cluster's workers; the results in order (a campaign's
        results table, its groups side by side: ``tables.summarise``)."""
        return self.client.gather(self.client.map(fn, *iterables, pure=False))

    def run_pairs(self, renders, scores, *, stack=None) -> int:
        """Run a campaign's render and score items on the cluster; return the items written.

        CPU workers run one task per pair. GPU workers (``pipeline``) run one :func:`pipeline_task` each,
        every task given every pair and the run's :class:`~synthbos.benchmarks.drivers.FileClaims` (a folder
        beside the pair files), so each worker takes the next pair no one has taken as it frees up. Pairs
        left missing (a worker that died kept the pairs it had taken) are run again, with new claims, up to
        :data:`PIPELINE_ROUNDS` rounds in all.

        ``stack``: pairs per stack of the pipeline tasks' tracking items (:func:`pipeline_task`; None:
        the pipeline's default); refused (> 0) where the workers run one task per pair.
        Safe to call from several threads at once (a sweep runs its points together).
        """
        if stack and not self.pipeline:
            raise SynthbosError(f"--stack {stack}: these Dask workers run one task per pair; stacks are tracked "
                                "by workers that run the pipeline (GPU workers)")
        tasks = _pair_tasks(renders, scores)
        bar = self._progress_bar(len(tasks)) if tasks else None
        written = 0
        for _ in range(PIPELINE_ROUNDS if self.pipeline else 1):
            if not tasks:
                break
            written += self._run_round(tasks, stack, bar)
            tasks = [(r if r is not None and not Path(r[1]).exists() else None,
                      [s for s in items if not Path(s[4]).exists()]) for r, items in tasks]
            tasks = [(r, items) for r, items in tasks if r is not None or items]
        if tasks and self.pipeline:
            raise SynthbosError(f"{len(tasks)} pair(s) still missing after {PIPELINE_ROUNDS} rounds of the Dask "
                                "workers (did workers die?); run the campaign again to finish them")
        return written

    def _run_round(self, tasks, stack, bar) -> int:
        """One round of :meth:`run_pairs` over ``tasks``: submit, wait, count; the items written. The bar
        counts pair tasks as they end, or, for pipeline tasks (one a worker, ending together), each pair as
        its files appear (:func:`finished_pairs`, every :data:`PROGRESS_POLL_S` seconds)."""
        distributed = _distributed()
        token = uuid.uuid4().hex
        with self._lock:
            self._tokens.add(token)
        outputs = [task_outputs(task) for task in tasks]
        claims = watcher = None
        if self.pipeline:
            first = tasks[0][0][1] if tasks[0][0] is not None else tasks[0][1][0][0]
            claims = FileClaims(Path(first).parent / f".claims-{token}", len(tasks))
            Path(claims.folder).mkdir(parents=True)
            ended = threading.Event()
            watcher = threading.Thread(target=_watch_pairs, args=(outputs, bar, ended), daemon=True,
                                       name="synthbos-dask-progress")
            watcher.start()
        futures = self._submit(tasks, token, stack, claims)
        with self._lock:
            self._futures.update(futures)
        written = 0
        try:
            for fut in distributed.as_completed(futures):
                try:
                    items, pairs = fut.result()
                except distributed.KilledWorker as err:
                    raise SynthbosError(f"a pair task took several workers down with it (out of memory?): "
                                        f"{err}") from None
                written += items
                if watcher is None:
                    bar.update(pairs)
        except BaseException:
            self.abort()
            raise
        finally:
            with self._lock:
                self._futures.difference_update(futures)
            if watcher is not None:
                ended.set()
                watcher.join()
            if claims is not None:
                shutil.rmtree(claims.folder, ignore_errors=True)
        _remove_stale_temporaries([f for files in outputs for f in files])
        return written

    def _submit(self, tasks, token: str, stack=None, claims=None) -> dict:
        """Submit ``tasks`` (``scheduling.pair_tasks``); return their futures. With ``pipeline`` (GPU
        workers), one :func:`pipeline_task` per worker over every pair, sharing them through ``claims``,
        each first offered to its own worker; else (CPU workers), one :func:`pair_task` per pair."""
        if not self.pipeline:
            return {self.client.submit(pair_task, render, items, token, pure=False, retries=0,
                                       key=f"{TASK_PREFIX}-{Path(render[1] if render else items[0][0]).stem}"
                                           f"-{token[:8]}")
                    for render, items in tasks}
        renders = [r for r, _ in tasks if r is not None]
        scores = [s for _, items in tasks for s in items]
        workers = sorted(self.client.nthreads())
        return {self.client.submit(pipeline_task, renders, scores, token, stack=stack, claims=claims, pure=False,
                                   retries=0, key=f"{TASK_PREFIX}s-{i}-of-{len(workers)}-{token[:8]}",
                                   workers=[worker], allow_other_workers=True)
                for i, worker in enumerate(workers)}

    def abort(self) -> None:
        """Cancel every task; on a joined cluster, wait until no worker writes an item of ours."""
        with self._lock:
            futures, tokens = list(self._futures), list(self._tokens)
            self._futures.clear()
        if self.client is None:
            return
        try:
            if self.cluster is None:
                for token in tokens:
                    self.client.run(_stop_run, token, on_error="ignore")
            self.client.cancel(futures, force=True)
            if self.cluster is not None:  # ours: closing it ends its workers
                return
            waited = time.monotonic()
            while True:
                busy = sum(sum(self.client.run(_in_flight, t, on_error="ignore").values()) for t in tokens)
                if not busy:
                    return
                if time.monotonic() - waited > 2:
                    print(f"dask: waiting for {busy} item(s) in flight to finish writing "
                          "(Ctrl-C again to leave them)", flush=True)
                    waited = float("inf")
                time.sleep(0.2)
        except OSError:  # the scheduler is gone (CommClosedError is an OSError): nothing of ours can run
            pass


def campaign_runner(scheduler, *, needed: bool = True, device=None, workers=None, progress=True,
                    process_device=None):
    """A context giving the :class:`DaskRunner` of ``scheduler``: the runner itself when it is one (left
    open), else one opened here and closed on leaving; None where nothing is ``needed`` (a finished
    campaign starts no cluster)."""
    if isinstance(scheduler, DaskRunner):
        return contextlib.nullcontext(scheduler)
    if not needed:
        return contextlib.nullcontext(None)
    return DaskRunner(scheduler, device=device, workers=workers, progress=progress, process_device=process_device)


def run_pairs(renders, scores, *, scheduler, device=None, workers=None, progress=True, process_device=None,
              stack=None) -> int:
    """Run a campaign's items on a Dask cluster: ``scheduler`` is a :class:`DaskRunner` or its address;
    ``stack``: see :meth:`DaskRunner.run_pairs`."""
    with campaign_runner(scheduler, needed=bool(renders or scores), device=device, workers=workers,
                         progress=progress, process_device=process_device) as runner:
        return 0 if runner is None else runner.run_pairs(renders, scores, stack=stack)
