"""Several processes driving one GPU: the pairs of a pipeline shared out as each process becomes free.

One process that drives a GPU through a campaign (``scheduling.run_pipeline``) keeps the device only
partly busy: its render threads, noise threads, device loop and writers share one interpreter lock,
and the device waits for the host between their launches. Two or three such processes on one GPU,
each with its own threads and host processes, fill it better (one H100, 50 pairs of the full
campaign through Dask GPU workers on the same GPU, 2026-11-27: 3.6 pairs/s with one, 5.0 with two,
5.3 with three; docs/benchmarks.md).

The process that runs the campaign starts the others (*helpers*) from the multiprocessing fork server,
which has the campaign's modules imported and never initialises CUDA, so a helper starts without
importing anything and initialises CUDA itself. Every process takes the next pair that no one has
taken (:class:`Claims`: a counter in shared memory), so a helper that starts late, or a pair that
takes long, leaves no process idle while pairs remain. Each pair's results depend only on its seeds,
so which process takes it never changes a file.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
from multiprocessing import get_all_start_methods, get_context

from synthbos import SynthbosError

__all__ = ["Claims", "FileClaims", "driver_context", "ignoring_sigint_forkserver", "join_drivers",
           "quiet_resource_tracker", "start_drivers", "stop_drivers"]

# The warning multiprocessing's resource tracker prints at its exit for the semaphores of processes that a
# Ctrl-C ended (it removes them all the same): noise after the one line of an interrupted run.
_TRACKER_WARNING = "ignore:resource_tracker:UserWarning"


def driver_context(preload=()):
    """The multiprocessing context that starts helpers and host processes: the fork server where there is
    one (it imports ``preload`` once, before its first fork), else spawn."""
    if "forkserver" in get_all_start_methods():
        context = get_context("forkserver")
        context.set_forkserver_preload(sorted(preload))  # no effect once the server runs
        return context
    return get_context("spawn")


def quiet_resource_tracker() -> None:
    """Silence the resource tracker's leak warning in the processes started from now on (they read it from
    ``PYTHONWARNINGS``), and in the tracker, where this process has not started it yet."""
    current = os.environ.get("PYTHONWARNINGS", "")
    if _TRACKER_WARNING not in current.split(","):
        os.environ["PYTHONWARNINGS"] = ",".join(w for w in (current, _TRACKER_WARNING) if w)


def ignoring_sigint_forkserver() -> None:
    """Start multiprocessing's fork server (if not yet running) with SIGINT ignored: every process forked
    from it (a local Dask cluster's workers, a campaign's helpers and host processes) then ignores SIGINT
    from its first instruction, so a terminal's Ctrl-C, which reaches the whole process group, ends none
    of them with a traceback of its own (the server's imports included); the campaign's process stops
    them. Only the server's launch, a fraction of a second, runs with SIGINT ignored here."""
    from multiprocessing import forkserver

    main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        forkserver.ensure_running()
    finally:
        if old is not None:
            signal.signal(signal.SIGINT, old)


class Claims:
    """The ``n`` tasks of a pipeline shared by the processes that drive one device.

    :meth:`take` gives each caller the next task no process has taken (None once all are taken);
    :meth:`advance` counts finished items across the processes (for one progress bar); a helper that
    fails leaves its message with :meth:`fail`, which the campaign's process reads (:meth:`failures`).
    Made in the campaign's process and handed to each helper as it starts.

    Examples
    --------
    >>> claims = Claims(3, driver_context())
    >>> claims.take(0), claims.take(1), claims.take(0), claims.take(1)
    (0, 1, 2, None)
    >>> claims.counts(2)
    [2, 1]
    >>> claims.advance(3), claims.advance(0)
    (3, 3)
    """

    def __init__(self, n: int, context):
        self.n = int(n)
        self._next = context.Value("q", 0)
        self._done = context.Value("q", 0)
        self._taker = context.Array("b", max(1, self.n), lock=False)  # which process took each task
        self._errors = context.SimpleQueue()

    def take(self, driver: int = 0) -> int | None:
        """The next task no process has taken, now taken by process number ``driver`` (None: none left)."""
        with self._next.get_lock():
            k = self._next.value
            if k >= self.n:
                return None
            self._next.value = k + 1
            self._taker[k] = int(driver)
            return k

    def counts(self, drivers: int) -> list[int]:
        """The tasks each of the processes numbered ``0 .. drivers - 1`` took."""
        with self._next.get_lock():
            taken = list(self._taker[: self._next.value])
        return [taken.count(d) for d in range(int(drivers))]

    def advance(self, n: int) -> int:
        """Add ``n`` finished items; return the count over every process."""
        with self._done.get_lock():
            self._done.value += int(n)
            return self._done.value

    def fail(self, message: str) -> None:
        self._errors.put(str(message))

    def failures(self) -> list[str]:
        out = []
        while not self._errors.empty():
            out.append(self._errors.get())
        return out


class FileClaims:
    """The ``n`` tasks of a pipeline shared by processes that need not share a host: a Dask cluster's GPU
    workers, each running the pipeline over every task of a campaign and taking the next one no worker
    has taken, so that a worker that runs faster (a faster GPU, a less busy host) does more pairs and
    none waits at the end for a slower one's fixed share.

    A task is taken by creating its file in ``folder`` (``O_CREAT | O_EXCL``: atomic, on a shared file
    system too, where every worker sees the campaign's folder), which then names the host and process
    that took it; the folder belongs to one run (the client makes it and removes it). Sent to the workers
    inside a task's arguments; :attr:`taken` holds the tasks this copy took. A worker that dies keeps its
    tasks taken: the client runs what is left missing again, with new claims
    (``distributed.DaskRunner.run_pairs``).

    Examples
    --------
    >>> import tempfile
    >>> folder = tempfile.mkdtemp()
    >>> a, b = FileClaims(folder, 3), FileClaims(folder, 3)  # two workers' copies
    >>> a.take(), b.take(), b.take(), a.take()
    (0, 1, 2, None)
    >>> a.taken, b.taken
    ([0], [1, 2])
    """

    def __init__(self, folder, n: int):
        self.folder = os.fspath(folder)
        self.n = int(n)
        self.taken: list[int] = []
        self._next = 0
        self._done = 0
        self._errors: list[str] = []

    def take(self, driver: int = 0) -> int | None:
        """The next task no worker has taken, now taken here (None: none left); ``driver`` is not used."""
        while self._next < self.n:
            k = self._next
            self._next += 1
            try:
                fd = os.open(os.path.join(self.folder, str(k)), os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                continue
            try:  # who took it: the host and process, for a person looking at a run
                os.write(fd, f"{socket.gethostname()} {os.getpid()}\n".encode())
            finally:
                os.close(fd)
            self.taken.append(k)
            return k
        return None

    def counts(self, drivers: int) -> list[int]:
        """The tasks taken here (this copy's process only)."""
        return [len(self.taken)]

    def advance(self, n: int) -> int:
        """Add ``n`` finished items; return this copy's count."""
        self._done += int(n)
        return self._done

    def fail(self, message: str) -> None:
        self._errors.append(str(message))

    def failures(self) -> list[str]:
        out, self._errors = self._errors, []
        return out


def start_drivers(n: int, target, args, context) -> list:
    """Start ``n`` helper processes running ``target(*args, number, campaign_pid)`` (``number``: 1 .. n,
    this process being 0; ``campaign_pid``: this process, which they die with) in ``context``
    (:func:`driver_context`); return them.

    Not daemonic: a helper starts host processes of its own.
    """
    procs = []
    for i in range(int(n)):
        proc = context.Process(target=target, args=(*args, i + 1, os.getpid()), name=f"synthbos-driver-{i + 1}")
        proc.start()
        procs.append(proc)
    return procs


def join_drivers(procs, claims: Claims, *, poll=None, interval: float = 0.2) -> None:
    """Wait for the helpers ``procs``, calling ``poll()`` every ``interval`` seconds meanwhile (a progress
    bar, jobs whose files are now there); raise the first failure one of them reported, or name one
    that ended without reporting (killed)."""
    for proc in procs:
        while proc.is_alive():
            proc.join(interval)
            if poll is not None:
                poll()
    failures = claims.failures()
    if failures:
        raise SynthbosError(failures[0])
    for proc in procs:
        if proc.exitcode != 0:
            raise SynthbosError(f"{proc.name}, a process that drove the GPU, ended with exit status {proc.exitcode} "
                                "before its pairs were done; run the campaign again to finish them")


def stop_drivers(procs) -> None:
    """End the helpers ``procs`` at once (the campaign failed or was interrupted): their finished items
    are in their files, the ones in flight are lost, as in any interrupted run."""
    for proc in procs:
        if proc.is_alive():
            proc.kill()
    for proc in procs:
        proc.join(5)
