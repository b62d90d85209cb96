"""Warp start-up without noise, and the device a command runs on.

Warp's native library probes for the CUDA driver when ``wp.init()`` first runs and, on a machine
without one, writes "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver ..." straight to
file descriptor 2, which no Python setting silences. ``init_warp`` runs that first initialisation with
descriptor 2 caught in a temporary file and passes on everything except that one line, so a real
error still shows. Worker processes call it too (each spawned process initialises Warp afresh).
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from synthbos import SynthbosError
from synthbos.shipped_kernels import seed_kernel_cache

__all__ = ["check_device", "copy_to_host", "describe_device", "init_warp", "launching", "load_kernels",
           "recording_graph", "resolve_device"]

# What Warp's native library prints when no CUDA driver can be loaded: expected on a CPU machine.
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"
_initialised = False


@contextlib.contextmanager
def _filtered_native_stderr(drop: str):
    """Catch what native code writes to descriptor 2; write it back without the lines containing ``drop``."""
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no descriptor 2 (a detached process): nothing to filter
        yield
        return
    with tempfile.TemporaryFile(mode="w+b") as caught:
        os.dup2(caught.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            text = caught.read().decode(errors="replace")
            kept = [line for line in text.splitlines(keepends=True) if drop not in line]
            if kept:
                sys.stderr.write("".join(kept))
                sys.stderr.flush()


#: Set (to anything but "" or "0") to have Warp print every module's build and load with its time, in
#: every synthbos process: how to find what holds a first run up (``SYNTHBOS_WARP_VERBOSE=1 synthbos ...``).
VERBOSE_ENV = "SYNTHBOS_WARP_VERBOSE"


def quiet_warp() -> None:
    """Warp's messages for synthbos: warnings and errors only (no greeting, no module-load lines), unless
    ``SYNTHBOS_WARP_VERBOSE`` asks for every module's build and load time. Every kernel module calls it
    as it is imported, since importing Warp resets nothing but a module may be imported first.

    Examples
    --------
    >>> quiet_warp()
    >>> wp.config.log_level == wp.LOG_WARNING or bool(os.environ.get(VERBOSE_ENV, "").strip("0"))
    True
    """
    if os.environ.get(VERBOSE_ENV, "").strip("0"):
        wp.config.verbose = True
        wp.config.quiet = False
        if hasattr(wp, "LOG_INFO"):
            wp.config.log_level = wp.LOG_INFO
        return
    wp.config.quiet = True
    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = wp.LOG_WARNING


def init_warp() -> None:
    """Initialise Warp once, quietly (:func:`quiet_warp`): no greeting, no module-load lines, no
    missing-driver warning; then put the CPU kernels shipped with the package into Warp's kernel cache
    where it lacks them (:func:`synthbos.shipped_kernels.seed_kernel_cache`)."""
    quiet_warp()
    global _initialised
    if _initialised:
        return
    with _filtered_native_stderr(_NO_DRIVER):
        wp.init()  # a no-op if Warp was initialised already
    seed_kernel_cache()
    _initialised = True


def check_device(device):
    """Return ``device`` if Warp has it on this machine (None stays None: Warp's default); else ``SynthbosError``.

    Names the device as the user gave it (``--device``), so a typo or ``cuda:0`` on a machine without
    a GPU gives one line before any work.
    """
    if device is None:
        return None
    init_warp()
    name = str(device)
    cuda = wp.is_cuda_available()
    if name.startswith("cuda") and not cuda:
        raise SynthbosError(f"device {name!r}: no CUDA GPU is visible to Warp on this machine; use cpu")
    try:
        wp.get_device(name)
    except (ValueError, RuntimeError):
        known = ["cpu"] + [f"cuda:{i}" for i in range(wp.get_cuda_device_count())] if cuda else ["cpu"]
        raise SynthbosError(f"device {name!r} is not a Warp device on this machine; use one of {known}") from None
    return name


def resolve_device(device=None) -> str:
    """The Warp device to use: ``device`` if given (checked), else ``cuda:0`` when present, else ``cpu``."""
    init_warp()
    if device is None:
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    return check_device(device)


def describe_device(device: str) -> str:
    """One line for a command's output: ``device: cpu (no CUDA device found)``, ``device: cuda:0 (NVIDIA H100)``."""
    init_warp()
    if device == "cpu":
        return "device: cpu" if wp.is_cuda_available() else "device: cpu (no CUDA device found)"
    return f"device: {device} ({wp.get_device(device).name})"


class _LaunchGate:
    """Threads that launch Warp work side by side, and one that records a CUDA graph alone.

    A graph records every launch on its device's stream while the capture is open, and another
    thread's launch, copy or allocation meanwhile lands in the graph or breaks it (and that thread's
    call). A thread that launches while others may record goes :meth:`launching`; a recorder
    (:meth:`recording`) waits until no other thread is inside, and keeps new ones out (they wait) until
    its capture is closed. Each records a graph once, so the wait is rare.
    """

    def __init__(self):
        self._cond = threading.Condition()
        self._inside: dict[int, int] = {}  # thread -> how deep inside launching()
        self._recorder = None  # the thread recording now
        self._waiting = 0  # recorders waiting: no new launching thread meanwhile

    @contextlib.contextmanager
    def launching(self):
        me = threading.get_ident()
        with self._cond:
            while self._recorder not in (None, me) or (self._waiting and me not in self._inside):
                self._cond.wait()
            self._inside[me] = self._inside.get(me, 0) + 1
        try:
            yield
        finally:
            with self._cond:
                self._inside[me] -= 1
                if not self._inside[me]:
                    del self._inside[me]
                self._cond.notify_all()

    @contextlib.contextmanager
    def recording(self):
        me = threading.get_ident()
        with self._cond:
            self._waiting += 1
            try:
                while self._recorder is not None or any(t != me for t in self._inside):
                    self._cond.wait()
            finally:
                self._waiting -= 1
            self._recorder = me
        try:
            yield
        finally:
            with self._cond:
                self._recorder = None
                self._cond.notify_all()


_GATE = _LaunchGate()


def launching():
    """A block in which this thread launches Warp work while other threads of the process may record
    CUDA graphs (:func:`recording_graph`): a campaign's render threads. It waits while a graph is being
    recorded.

    Examples
    --------
    >>> with launching():
    ...     pass
    """
    return _GATE.launching()


def recording_graph():
    """A block in which this thread records a CUDA graph (``wp.ScopedCapture``) with the devices to
    itself: it waits until no other thread is inside :func:`launching`, and keeps them out until it ends.

    Examples
    --------
    >>> import threading
    >>> inside = threading.Event(); leave = threading.Event()
    >>> def render():
    ...     with launching():
    ...         inside.set(); leave.wait()
    >>> t = threading.Thread(target=render); t.start(); _ = inside.wait()
    >>> threading.Timer(0.05, leave.set).start()
    >>> with recording_graph():  # waits for the other thread's block to end
    ...     leave.is_set()
    True
    >>> t.join()
    """
    return _GATE.recording()


#: Page-locked staging of :func:`copy_to_host`: buffers of this many bytes, as many as host threads that
#: copy them on (eight: a 400-pair table on an H100 host was 7 ms sooner than with four, 2026-11-27).
STAGE_BYTES = 8 << 20
STAGE_BUFFERS = 8


class _Staging:
    """A CUDA device's page-locked buffers, copy stream and host threads (:func:`copy_to_host`)."""

    def __init__(self, device):
        with launching():  # a page-locked allocation must not fall inside another thread's graph recording
            self.buffers = [wp.empty(STAGE_BYTES, dtype=wp.uint8, device="cpu", pinned=True)
                            for _ in range(STAGE_BUFFERS)]  # fmt: skip
        self.views = [b.numpy() for b in self.buffers]
        self.stream = wp.Stream(device)
        self.threads = ThreadPoolExecutor(STAGE_BUFFERS, thread_name_prefix="synthbos-copy")
        self.lock = threading.Lock()  # one copy at a time through them


_staging: dict = {}
_staging_lock = threading.Lock()


def copy_to_host(src, out):
    """Copy the contiguous Warp array ``src`` into the C-contiguous NumPy array ``out`` of as many bytes, after
    the work queued on ``src``'s device; return ``out``.

    From a CUDA device the copy goes through a few page-locked buffers (``STAGE_BUFFERS`` of ``STAGE_BYTES``,
    made once per device): the device copies chunk after chunk into them on a stream of its own, and host
    threads copy each chunk on into ``out`` as it lands. A copy into pageable memory is bound by one host
    thread's memcpy: a 246 MB table took 23-25 ms on an H100 host, 12-14 ms through four buffers (2026-11-27).

    Examples
    --------
    >>> import numpy as np, warp as wp
    >>> init_warp()
    >>> copy_to_host(wp.array(np.arange(4.0), dtype=wp.float64, device="cpu"), np.empty(4))
    array([0., 1., 2., 3.])
    """
    nbytes = out.nbytes
    if not out.flags.c_contiguous or not src.is_contiguous or src.capacity != nbytes:
        raise ValueError(f"copy_to_host needs contiguous arrays of one size, got {src.capacity} and {nbytes} bytes")
    if nbytes == 0:
        return out
    raw = wp.array(ptr=src.ptr, dtype=wp.uint8, shape=(nbytes,), device=src.device)
    if not src.device.is_cuda:
        wp.copy(wp.array(ptr=out.ctypes.data, dtype=wp.uint8, shape=(nbytes,), device="cpu"), raw)
        return out
    flat = out.reshape(-1).view(np.uint8)
    with _staging_lock:
        if src.device.alias not in _staging:
            _staging[src.device.alias] = _Staging(src.device)
        st = _staging[src.device.alias]
    with st.lock:
        st.stream.wait_stream(wp.get_stream(src.device))
        pending = [None] * STAGE_BUFFERS
        for k, lo in enumerate(range(0, nbytes, STAGE_BYTES)):
            n, b = min(STAGE_BYTES, nbytes - lo), k % STAGE_BUFFERS
            if pending[b] is not None:
                pending[b].result()  # the buffer's last chunk has been copied on
            wp.copy(st.buffers[b], raw, 0, lo, n, stream=st.stream)
            pending[b] = st.threads.submit(_land, st.stream.record_event(), st.views[b], flat, lo, n)
        for p in pending:
            if p is not None:
                p.result()
    return out


def _land(ready, staged, flat, lo, n):
    wp.synchronize_event(ready)
    flat[lo : lo + n] = staged[:n]


def _warp_modules(name: str) -> list:
    """The Warp modules ``name`` stands for: those of Python module ``name`` (its own and those of its
    ``module="unique"`` kernels), or the one Warp module that a Python module declares under a name of
    its own, ``<Python module>.<part>`` (the renderer's, one per medium: ``raytrace.kernels.render_module``).
    """
    from warp._src.context import user_modules  # Warp's registry of modules (no public listing)

    try:
        importlib.import_module(name)
    except ModuleNotFoundError as e:
        if e.name != name:
            raise
        importlib.import_module(name.rpartition(".")[0])  # declares its parts as it is imported
        if name not in user_modules:
            raise
        return [user_modules[name]]

    def kernels(m):
        return m.kernels.values() if isinstance(m.kernels, dict) else m.kernels

    return [m for m in list(user_modules.values())
            if m.name == name or (not m.name.startswith(name + ".")
                                  and any(getattr(k.func, "__module__", None) == name for k in kernels(m)))]


def load_kernels(pairs, *, max_workers=None) -> None:
    """Compile (or find in Warp's kernel cache) the kernels of ``(Python module, device)`` ``pairs`` now,
    several modules at a time.

    Warp compiles a module on its first launch, one module after another; a campaign calls this before
    its work starts, so that a first run on a machine with an empty kernel cache compiles all of them in
    parallel (``max_workers`` at a time, default one per CPU core) instead of one by one, and its worker
    processes find them compiled. Warp generates every module's source under one lock per process, and
    for a tile FFT that includes building the FFT's device code (5-7 s each), so the CUDA modules
    missing from the cache are built in as many processes (:func:`_build_in_processes`); the rest, and
    every CPU module, in threads here (the compilers release the GIL).

    Examples
    --------
    >>> load_kernels([("synthbos.tracking.moment_kernels", "cpu")])
    """
    init_warp()
    by_device: dict[str, dict] = {}  # device -> {Warp module: the Python module that named it first}
    for name, device in pairs:
        mods = by_device.setdefault(str(device), {})
        for m in _warp_modules(name):
            mods.setdefault(m, name)
    if not by_device:  # nothing to build (a campaign with nothing left to do)
        return
    workers = max_workers if max_workers is not None else (os.cpu_count() or 1)
    missing = [(name, d, m.name) for d, mods in by_device.items() if wp.get_device(d).is_cuda
               for m, name in mods.items() if not _cached(m, d)]
    if workers > 1 and len(missing) > 1:
        _build_in_processes(missing, workers)
    if len(by_device) == 1:
        (device, mods), = by_device.items()
        wp.force_load(device=device, modules=list(mods), max_workers=workers)
        return
    with ThreadPoolExecutor(len(by_device), thread_name_prefix="synthbos-compile") as pool:  # devices side by side
        for fut in [pool.submit(wp.force_load, device=d, modules=list(mods), max_workers=workers)
                    for d, mods in by_device.items()]:
            fut.result()


def _cached(module, device) -> bool:
    """Whether Warp's kernel cache holds ``module``'s binary for ``device`` at the block size ``force_load``
    builds (one thread on the CPU, the module's default on a GPU; False where that cannot be told)."""
    try:
        dev = wp.get_device(device)
        block_dim = 1 if dev.is_cpu else module.options["block_dim"]
        folder = os.path.join(wp.config.kernel_cache_dir, module.get_module_identifier(block_dim))
        return os.path.exists(os.path.join(folder, module._get_compile_output_name(dev, block_dim=block_dim)))
    except Exception:  # Warp's internals moved: build as if missing (processes are only the faster way)
        return False


#: The longest a build process may take for one module (its largest took 25 s on an H100 host); one that
#: takes longer is stopped and the module built in the campaign process.
BUILD_TIMEOUT_S = 600


def _build_in_processes(missing, workers: int) -> None:
    """Build each ``(Python module, device, Warp module name)`` of ``missing`` into Warp's kernel cache in
    a Python process of its own, at most ``workers`` at a time (each imports Warp afresh and generates its
    module's source under its own lock); this process then loads them from there. The processes run
    ``python -c``, not ``multiprocessing``, so a user's script without a ``__main__`` guard is not run
    again in them. A module that fails to build there is built here, where its error is raised."""
    import subprocess

    code = "import sys; from synthbos.device import _build_one; _build_one(*sys.argv[1:])"

    def build(job):
        name, device, module_name = job
        env, device = _one_gpu(device)
        try:
            subprocess.run([sys.executable, "-c", code, name, device, module_name, wp.config.kernel_cache_dir],
                           check=False, timeout=BUILD_TIMEOUT_S, env=env)
        except subprocess.TimeoutExpired:  # killed: this process builds the module instead
            pass

    with ThreadPoolExecutor(min(workers, len(missing)), thread_name_prefix="synthbos-build") as pool:
        for fut in [pool.submit(build, job) for job in missing]:
            fut.result()


def _one_gpu(device: str, environ=None) -> tuple[dict, str]:
    """The environment and device name under which a build process sees only ``device``'s GPU.

    Each process that Warp starts on initialises every GPU it sees (and their peer access); on a host
    of several GPUs, 30 build processes each doing so for all of them slowed a first run from 47 to 84 s
    (H100 hosts, 2026-11-27). The kernel cache does not depend on the ordinal, so the build process
    builds for its ``cuda:0``, the same GPU. CPU devices keep the environment as it is.

    Examples
    --------
    >>> env, dev = _one_gpu("cuda:1", {"CUDA_VISIBLE_DEVICES": "4,5,6"})
    >>> env["CUDA_VISIBLE_DEVICES"], dev
    ('5', 'cuda:0')
    >>> _one_gpu("cpu", {})[1]
    'cpu'
    """
    env = dict(os.environ if environ is None else environ)
    kind, _, ordinal = str(device).partition(":")
    if kind != "cuda":
        return env, str(device)
    visible = [v.strip() for v in env.get("CUDA_VISIBLE_DEVICES", "").split(",") if v.strip()]
    k = int(ordinal or 0)
    if "CUDA_VISIBLE_DEVICES" in env and k >= len(visible):
        return env, str(device)  # not a list this can map (e.g. UUIDs beyond it): keep the device as named
    env["CUDA_VISIBLE_DEVICES"] = visible[k] if visible else str(k)
    return env, "cuda:0"


def _build_one(name: str, device: str, module_name: str, cache: str) -> None:
    """Build Warp module ``module_name`` of Python module ``name`` for ``device`` into the kernel cache
    ``cache`` (a task of :func:`_build_in_processes`)."""
    init_warp()
    wp.config.kernel_cache_dir = cache  # after Warp's start, which would add its version to a path given before
    wp.force_load(device=device, modules=[m for m in _warp_modules(name) if m.name == module_name], max_workers=0)
