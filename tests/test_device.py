"""Warp starts quietly: its missing-driver line is dropped, anything else on stderr is kept."""

import os

from synthbos.device import _filtered_native_stderr, describe_device, resolve_device


def test_native_stderr_filter_drops_only_the_named_line(capfd):
    with _filtered_native_stderr("no driver here"):
        os.write(2, b"Warp CUDA warning: no driver here, fine.\nsomething real went wrong\n")
    err = capfd.readouterr().err
    assert "no driver here" not in err
    assert "something real went wrong" in err


def test_device_is_resolved_and_described_once():
    device = resolve_device(None)
    assert device in ("cpu", "cuda:0")
    line = describe_device(device)
    assert line.startswith(f"device: {device}")
    assert resolve_device("cpu") == "cpu"


def test_a_graph_is_recorded_while_no_other_thread_launches():
    """A recorder waits for the thread inside ``launching``; a thread that wants to launch meanwhile waits
    for the recording to end; a recorder inside its own ``launching`` block does not wait for itself."""
    import threading
    import time

    from synthbos.correlation.device_pass import _graph_replay

    from synthbos.device import launching, recording_graph

    log = []
    inside, leave = threading.Event(), threading.Event()

    def render(name, started=None):
        with launching():
            log.append(f"{name} in")
            if started is not None:
                started.set()
                leave.wait(5)
            log.append(f"{name} out")

    first = threading.Thread(target=render, args=("first", inside))
    first.start()
    assert inside.wait(5)
    threading.Timer(0.1, leave.set).start()
    with recording_graph():
        log.append("recording")
        second = threading.Thread(target=render, args=("second",))
        second.start()
        time.sleep(0.1)
        log.append("recorded")
    second.join(5)
    first.join(5)
    assert log == ["first in", "first out", "recording", "recorded", "second in", "second out"]
    with launching(), recording_graph():
        pass

    class Cuda:
        is_cuda = True

    assert _graph_replay(Cuda())


def test_a_kernel_module_part_is_found_by_its_own_name_and_not_with_its_python_module():
    from synthbos.raytrace import kernels

    from synthbos.device import _warp_modules

    part = kernels.render_module(kernels.MediumHalf)
    assert [m.name for m in _warp_modules(part)] == [part]
    whole = [m.name for m in _warp_modules("synthbos.raytrace.kernels")]
    assert whole == ["synthbos.raytrace.kernels"]  # its 21 render modules and 2 truth modules are parts
    try:
        _warp_modules("synthbos.raytrace.kernels.render_NoSuchMedium")
    except ModuleNotFoundError as err:
        assert "render_NoSuchMedium" in str(err)
    else:
        raise AssertionError("an unknown part was found")


def test_warp_verbose_on_request_only():
    """``SYNTHBOS_WARP_VERBOSE=1`` makes Warp print every module's load with its time (how to find what
    holds a first run up); without it synthbos keeps Warp quiet."""
    import subprocess
    import sys

    code = ("import synthbos.tracking.stats_kernels as k, warp as wp; "
            "wp.force_load(device='cpu', modules=[wp.get_module(k.__name__)])")
    out = {}
    for flag in ("1", ""):
        env = {**os.environ, "SYNTHBOS_WARP_VERBOSE": flag}
        run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        out[flag] = run.stdout + run.stderr
    assert "Module synthbos.tracking.stats_kernels" in out["1"] and " took " in out["1"]
    assert "Module synthbos.tracking.stats_kernels" not in out[""] and "Warp 1." not in out[""]


def test_the_correlation_kernels_are_compiled_ahead_for_the_block_sizes_they_are_launched_with():
    """Warp compiles a module once per block size, and ``load_kernels`` builds each module's default:
    the line kernels' default is their launch's ``LOOP_BLOCK`` (in ``pass_kernels``, launched at 256
    elsewhere, they made a first GPU run compile that whole module twice), and the default passes'
    window kernels exist from import with their launch's ``n // 2`` threads."""
    from synthbos.correlation import line_kernels, pass_kernels
    from synthbos.correlation.rules import WINDOW_SIZES

    from synthbos.device import _warp_modules

    (lines,) = _warp_modules(line_kernels.__name__)
    assert lines.options["block_dim"] == line_kernels.LOOP_BLOCK == 32
    names = {m.name for m in _warp_modules(pass_kernels.__name__)}
    for n in WINDOW_SIZES:
        kernel = pass_kernels.correlate_windows_kernel(n, False)
        assert kernel.module.name in names and kernel.module.options["block_dim"] == n // 2


def test_image_dtypes_do_not_change_the_correlation_kernels():
    """Launching the image kernels on float32 and float64 images (how the device engine uploads them)
    leaves the kernel module's content, and so its hash, as import made it: an overload made at a launch
    changed it, and every GPU worker that met a new dtype compiled the whole module again."""
    import subprocess
    import sys

    code = """
import warp as wp
from synthbos.device import init_warp
init_warp()
from synthbos.correlation import line_kernels as pk
from warp._src.context import user_modules
m = user_modules[pk.__name__]
before = m.get_module_hash(1)
stats = wp.zeros((4, 4), dtype=wp.float64, device="cpu")
for dtype in (wp.float32, wp.float64):
    wp.launch(pk.column_stats, 4, [wp.ones((4, 4), dtype=dtype, device="cpu"), stats], device="cpu")
print(m.get_module_hash(1) == before)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    assert out.stdout.strip().splitlines()[-1] == "True", out.stdout + out.stderr


def test_modules_missing_from_the_cache_are_built_in_other_processes(tmp_path, monkeypatch):
    """A first GPU run builds the missing modules in a process each (Warp generates the sources of one
    process's modules one at a time): here on the CPU, one module into an empty cache, which this
    process then finds there."""
    import warp as wp

    from synthbos.device import _build_in_processes, _cached, _warp_modules

    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    name = "synthbos.tracking.wide_search_kernels"
    (module,) = _warp_modules(name)
    assert not _cached(module, "cpu")
    _build_in_processes([(name, "cpu", module.name)], 2)
    assert _cached(module, "cpu")


def test_building_in_other_processes_does_not_run_a_users_script_again(tmp_path):
    """A user's script without a ``__main__`` guard runs once: the build processes do not import it (as
    ``multiprocessing``'s spawned processes would, and then start their own build processes)."""
    import subprocess
    import sys

    log = tmp_path / "runs.txt"
    script = tmp_path / "user_script.py"
    script.write_text(f"""
import warp as wp
from synthbos.device import _build_in_processes, _cached, _warp_modules, init_warp
with open({str(log)!r}, "a") as f:
    f.write("run\\n")
init_warp()
wp.config.kernel_cache_dir = {str(tmp_path / "cache")!r}
(module,) = _warp_modules("synthbos.tracking.wide_search_kernels")
_build_in_processes([("synthbos.tracking.wide_search_kernels", "cpu", module.name)], 2)
print(_cached(module, "cpu"))
""")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True"]
    assert log.read_text() == "run\n"


def test_load_kernels_of_nothing_returns():
    """A campaign with nothing left to do (every item on disk) asks for no module: ``load_kernels([])``
    returns instead of starting a pool of no threads (``paper`` rerun in a finished folder on a GPU
    stopped there with "max_workers must be greater than 0")."""
    from synthbos.device import load_kernels

    assert load_kernels([]) is None
    assert load_kernels([], max_workers=4) is None


def test_a_steps_gpu_engine_is_a_module_named_under_its_kernel_module(monkeypatch):
    """Each step's GPU engine (``GPU_MODULE``, e.g. ``synthbos.tracking.claim_kernels.gpu``) is a Warp module
    named under its Python module, kept apart from that module's own, and a worker loads it by that name
    (``scheduling.die_with_parent`` -> ``load_kernels``: a GPU campaign's workers stopped on importing it
    as a Python module)."""
    import warp as wp
    from synthbos.benchmarks import scheduling
    from synthbos.tracking import claim_kernels

    from synthbos.device import _warp_modules

    assert claim_kernels.GPU_MODULE == "synthbos.tracking.claim_kernels.gpu"
    assert [m.name for m in _warp_modules(claim_kernels.GPU_MODULE)] == [claim_kernels.GPU_MODULE]
    assert claim_kernels.GPU_MODULE not in {m.name for m in _warp_modules(claim_kernels.__name__)}
    loaded = []
    monkeypatch.setattr(wp, "force_load", lambda device, modules, max_workers: loaded.extend(m.name for m in modules))
    monkeypatch.setattr(scheduling.ctypes, "CDLL", lambda *a, **k: type("L", (), {"prctl": staticmethod(lambda *a: 0)}))
    monkeypatch.setattr(scheduling.os, "getppid", lambda: 1)  # started by the campaign process, pid 1
    monkeypatch.setattr(scheduling, "_exit_with", lambda pid: None)
    monkeypatch.setattr(scheduling, "threadpool_limits", lambda limits: None)
    scheduling.die_with_parent(1, kernels=[(claim_kernels.GPU_MODULE, "cpu")])
    assert loaded == [claim_kernels.GPU_MODULE]


def test_copy_to_host_lands_every_chunk_after_the_queued_work(device):
    """A table of 2.6 staging buffers and an odd tail, assigned by work still queued when the copy starts
    (on a GPU: through the page-locked buffers); a struct array; a wrong size is refused."""
    import numpy as np
    import pytest
    import warp as wp
    from synthbos.tracking.settings import TRACK_DTYPE

    from synthbos.device import STAGE_BYTES, copy_to_host, init_warp

    init_warp()
    n = int(2.6 * STAGE_BYTES) // 8 + 3
    src = wp.zeros(n, dtype=wp.float64, device=device)
    values = np.arange(n, dtype=np.float64) * 0.5
    src.assign(values)  # queued on the device's stream
    out = np.full(n, -1.0)
    assert copy_to_host(src, out) is out
    np.testing.assert_array_equal(out, values)
    rows = np.zeros(1001, dtype=TRACK_DTYPE)
    rows["u"] = np.linspace(0.0, 1.0, 1001)
    rows["status"] = np.arange(1001)
    table = wp.array(rows.view(np.uint8), dtype=wp.uint8, device=device)
    got = np.empty(1001, dtype=TRACK_DTYPE)
    copy_to_host(table, got)
    assert got.tobytes() == rows.tobytes()
    with pytest.raises(ValueError, match="one size"):
        copy_to_host(src, np.empty(n - 1))
