"""Issue 15: every error a user can cause ends as one line, exit status 2, nothing written; no hang.

One fast case of every class of the issue's table (rows 18 and 19, the processors' flags, are tested
with the processors). Most cases call ``main`` in this process (a traceback would fail the test as an
exception); the kill and full-disk cases run the command line as a subprocess.
"""

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from synthbos.benchmarks.cli import main
from synthbos.raytrace import read_pair, render_pair, write_pair
from synthbos.raytrace.config import config_to_toml, load_config

from synthbos import SynthbosError, atomic_output, folder_lock

ROOT = Path(__file__).resolve().parents[2]
BASE = {
    "camera": {"pixels": [96, 96]},
    "rays": {"per_dot": 20},
    "target": {"dots_per_32px": 8.0},
    "volume": {"source": "gaussian"},
}


def _toml(tables):
    lines = []
    for table, values in tables.items():
        lines.append(f"[{table}]")
        for key, value in values.items():
            lines.append(f"{key} = {_value(value)}")
    return "\n".join(lines) + "\n"


def _value(v):
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    return repr(v)


def _config_file(folder, name="cfg.toml", **tables):
    cfg = {k: dict(v) for k, v in BASE.items()}
    for table, values in tables.items():
        cfg.setdefault(table, {}).update(values)
    path = Path(folder) / name
    path.write_text(_toml(cfg))
    return path


def _listing(folder):
    return sorted(str(p.relative_to(folder)) for p in Path(folder).rglob("*"))


def _error_line(capsys, argv, *expected, seconds=20.0):
    """Run ``main(argv)``: exit status 2, one line ``synthbos: error: ...`` naming ``expected``, quickly."""
    t0 = time.perf_counter()
    rc = main([str(a) for a in argv])
    elapsed = time.perf_counter() - t0
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("Warp")]
    assert rc == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith("synthbos: error: ")
    for text in expected:
        assert text in lines[0], lines[0]
    assert elapsed < seconds
    return lines[0]


def _cli(argv, cwd, timeout=120):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "synthbos", *map(str, argv)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def _one_line(result):
    lines = [ln for ln in result.stderr.splitlines() if ln.strip() and not ln.startswith("Warp")]
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and lines[0].startswith("synthbos: error: "), result.stderr
    assert "Traceback" not in result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def pair_file(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pair")
    path = folder / "p.h5"
    write_pair(path, render_pair(BASE, device="cpu"))
    return path


def _tmpfs(path, *options):
    """Mount a 64 KiB tmpfs at ``path`` (root only); skip the test where that is not possible."""
    path.mkdir()
    opts = ",".join(("size=64k", *options))
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode(errors='replace').strip()}")
    return path


def _umount(path):
    subprocess.run(["umount", str(path)], check=False)


# ---------------------------------------------------------------- row 1: a full disk


def test_row01_full_disk_atomic_output_cleans_up(tmp_path, monkeypatch):
    """ENOSPC while writing (simulated): one SynthbosError, no file under the final name, no temporary."""
    target = tmp_path / "out.bin"

    def full_write(*args, **kwargs):
        raise OSError(28, "No space left on device")

    with pytest.raises(SynthbosError, match=r"cannot write .*out\.bin: No space left on device"):
        with atomic_output(target) as tmp, open(tmp, "wb") as f:
            f.write(b"partial")
            monkeypatch.setattr(f, "write", full_write, raising=False)
            full_write()
    assert _listing(tmp_path) == []


def test_row01_full_disk_render_and_process(tmp_path, capsys, pair_file):
    full = _tmpfs(tmp_path / "full")
    try:
        (full / "filler").write_bytes(b"\0" * 60_000)
        with pytest.raises(OSError):  # the disk is full indeed
            (full / "more").write_bytes(b"\0" * 16_384)
        (full / "more").unlink(missing_ok=True)
        cfg = _config_file(tmp_path)
        before = _listing(full)
        line = _one_line(_cli(["render", cfg, "-o", full / "p.h5", "-q"], tmp_path))
        assert "No space left on device" in line and "p.h5" in line
        _error_line(capsys, ["process", pair_file, "--method", "correlation", "-o", full / "r.h5"],
                    "r.h5: No space left on device")
        _error_line(capsys, ["show-density", "-o", full / "d.png", "-q"], "d.png: No space left on device")
        assert _listing(full) == before
    finally:
        _umount(full)


# ---------------------------------------------------------------- row 2: a hang (steps per ray)


@pytest.mark.parametrize(
    ("tables", "expected"),
    [
        ({"rays": {"step_mm": 1e-5}}, ["rays.step_mm", "limits.steps_per_ray"]),
        ({"volume": {"size_mm": [1e-5, 32, 10]}}, ['rays.step_mm = "grid"', "limits.steps_per_ray"]),
    ],
)
def test_row02_tiny_steps_refused_at_once(tmp_path, capsys, tables, expected):
    cfg = _config_file(tmp_path, **tables)
    _error_line(capsys, ["render", cfg, "-o", tmp_path / "p.h5", "-q"], *expected, seconds=10)
    assert _listing(tmp_path) == ["cfg.toml"]


def test_row02_limit_can_be_raised(tmp_path):
    cfg = load_config({**BASE, "rays": {"per_dot": 20, "step_mm": 0.01}, "limits": {"steps_per_ray": 2000}})
    from synthbos.raytrace.render import RenderPlan

    assert RenderPlan(cfg).steps_per_ray == 1000
    with pytest.raises(SynthbosError, match=r"more than limits\.ray_steps = 1e\+06 on this device"):
        render_pair({**BASE, "rays": {"per_dot": 20, "step_mm": 0.01}, "limits": {"ray_steps": 1e6}}, device="cpu")
    # The default depends on the device: 1e10 ray-steps on the CPU.
    from synthbos.raytrace import checks

    big = RenderPlan(load_config({**BASE, "rays": {"per_dot": 10**6}, "limits": {"steps_per_ray": 10**6}}))
    with pytest.raises(SynthbosError, match=r"about 2\.88e\+09 ray-steps .*limits\.ray_steps = 1e\+09"):
        checks.check_ray_steps(RenderPlan(load_config({**BASE, "rays": {"per_dot": 10**6},
                                                       "limits": {"ray_steps": 1e9}})), "cpu")
    checks.check_ray_steps(big, "cpu")  # 2.88e9 < 1e10


# ---------------------------------------------------------------- row 3: SIGKILL to paper


def _children(pid):
    """Every descendant of ``pid`` (the workers are children of the multiprocessing fork server)."""
    parent = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parent[int(entry.name)] = int(fields[1])
    kids, todo = [], [pid]
    while todo:
        p = todo.pop()
        found = [k for k, pp in parent.items() if pp == p]
        kids += found
        todo += found
    return kids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc and PR_SET_PDEATHSIG")
def test_row03_sigkill_paper_leaves_no_worker(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = tmp_path / "camp"
    proc = subprocess.Popen([sys.executable, "-m", "synthbos", "paper", "--quick", "--device", "cpu",
                             "--workers", "2", "--out", str(out), "-q"], env=env, cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 90
        kids = []
        while time.monotonic() < deadline and len(kids) < 3:  # the resource tracker, fork server and workers
            time.sleep(0.2)
            kids = _children(proc.pid)
            assert proc.poll() is None
        assert len(kids) >= 3, kids
        time.sleep(1.0)  # let the workers start rendering
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    deadline = time.monotonic() + 10
    alive = kids
    while alive and time.monotonic() < deadline:
        time.sleep(0.1)
        alive = [k for k in kids if Path(f"/proc/{k}").exists() and "Z" not in _state(k)]
    assert alive == []
    files = _listing(out)
    time.sleep(1.0)
    assert _listing(out) == files  # nothing writes there any more


def _state(pid):
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"


# ---------------------------------------------------------------- row 4: a kill while saving a figure


def test_row04_interrupted_save_leaves_no_partial_png(tmp_path, monkeypatch):
    import matplotlib.figure

    def dying_savefig(self, fname, **kwargs):
        Path(fname).write_bytes(b"\x89PNG\r\n\x1a\n partial")
        raise KeyboardInterrupt  # what a signal does half-way through a save

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", dying_savefig)
    assert main(["show-density", "-o", str(tmp_path / "x.png")]) == 130
    assert _listing(tmp_path) == []


def test_row04_next_write_removes_what_a_killed_writer_left(tmp_path):
    (tmp_path / ".x.png.99999999.abcdefgh.tmp").write_text("a killed writer's")  # no such process
    (tmp_path / f".x.png.{os.getpid()}.abcdefgh.tmp").write_text("a live writer's")
    (tmp_path / ".x.png.5.png.99999999.abcdefgh.tmp").write_text("another output's (x.png.5.png)")
    with atomic_output(tmp_path / "x.png") as tmp:
        tmp.write_text("done")
    assert set(_listing(tmp_path)) == {".x.png.5.png.99999999.abcdefgh.tmp", f".x.png.{os.getpid()}.abcdefgh.tmp",
                                       "x.png"}


def test_row04_sigkill_while_saving_leaves_no_png(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "synthbos", "show-density", "-o", str(tmp_path / "x.png")],
                            env=env, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    saving = []
    while not saving and proc.poll() is None and time.monotonic() < deadline:
        saving = list(tmp_path.glob(".x.png.*.tmp"))  # the save has begun
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    if not saving:
        pytest.skip("the figure was saved before the test saw it being written")
    assert not (tmp_path / "x.png").exists()  # never a truncated image under the final name
    # The next run removes what the killed one left, and writes the complete image.
    assert main(["show-density", "-o", str(tmp_path / "x.png")]) == 0
    assert _listing(tmp_path) == ["x.png"]  # only the file named


def test_row04_show_density_png_is_complete(tmp_path, capsys):
    assert main(["show-density", "-o", str(tmp_path / "x.png")]) == 0
    data = (tmp_path / "x.png").read_bytes()
    assert data.startswith(b"\x89PNG") and data[-8:-4] == b"IEND"
    assert _listing(tmp_path) == ["x.png"]


# ---------------------------------------------------------------- row 5: output = input


def test_row05_output_equal_to_input_is_refused(tmp_path, capsys, pair_file):
    cfg = _config_file(tmp_path)
    text = cfg.read_text()
    _error_line(capsys, ["render", cfg, "-o", cfg, "-q"], "is also an input")
    assert cfg.read_text() == text
    stamp = pair_file.stat().st_mtime_ns, pair_file.read_bytes()
    _error_line(capsys, ["process", pair_file, "--method", "correlation", "-o", pair_file], "is also an input")
    assert (pair_file.stat().st_mtime_ns, pair_file.read_bytes()) == stamp
    # The same file through another name (a hard link) is refused too.
    os.link(cfg, tmp_path / "same.toml")
    _error_line(capsys, ["render", cfg, "-o", tmp_path / "same.toml", "-q"], "is also an input")


# ---------------------------------------------------------------- row 6: -o in an unwritable place


def test_row06_output_is_a_folder_or_in_a_missing_folder(tmp_path, capsys, pair_file):
    cfg = _config_file(tmp_path)
    _error_line(capsys, ["render", cfg, "-o", tmp_path, "-q"], "is a folder")
    _error_line(capsys, ["process", pair_file, "--method", "correlation", "-o", tmp_path], "is a folder")
    _error_line(capsys, ["render", cfg, "-o", tmp_path / "no" / "p.h5", "-q"], "does not exist")
    _error_line(capsys, ["render", cfg, "-o", cfg / "p.h5", "-q"], "is a file, not a folder")
    assert _listing(tmp_path) == ["cfg.toml"]


def test_row06_no_write_permission(tmp_path, capsys, monkeypatch):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    cfg = _config_file(tmp_path)
    if os.geteuid() == 0:  # root writes regardless of permissions: let the check see what a user would
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == locked else real(p, mode, **kw))
    _error_line(capsys, ["render", cfg, "-o", locked / "p.h5", "-q"], "cannot write in folder")
    _error_line(capsys, ["paper", "--quick", "--device", "cpu", "--out", locked / "camp", "-q"],
                "(read-only or no permission)")
    _error_line(capsys, ["paper", "--quick", "--device", "cpu", "--out", locked, "-q"],
                "cannot write in this folder")
    assert _listing(locked) == []


def test_row06_and_07_read_only_file_system(tmp_path, capsys, pair_file):
    ro = _tmpfs(tmp_path / "ro", "ro")
    try:
        cfg = _config_file(tmp_path)
        _error_line(capsys, ["render", cfg, "-o", ro / "p.h5", "-q"], "read-only or no permission")
        _error_line(capsys, ["process", pair_file, "--method", "correlation", "-o", ro / "r.h5"], "read-only")
        _error_line(capsys, ["paper", "--quick", "--device", "cpu", "--out", ro / "camp", "-q"], "read-only")
        _error_line(capsys, ["regress", "--out", ro / "camp", "-q"], "read-only")
        _error_line(capsys, ["sweep", "--param", "density=4", "--out", ro / "sw", "-q"], "read-only")
        assert _listing(ro) == []
    finally:
        _umount(ro)


# ---------------------------------------------------------------- row 7: --out naming a file


@pytest.mark.parametrize("command", [
    ["paper", "--quick", "--device", "cpu"],
    ["sweep", "--param", "density=4", "--device", "cpu"],
    ["regress"],
])
def test_row07_out_is_a_file_or_under_one(tmp_path, capsys, command):
    afile = tmp_path / "afile"
    afile.write_text("x")
    _error_line(capsys, [*command, "--out", afile, "-q"], "is a file, not a folder")
    _error_line(capsys, [*command, "--out", afile / "sub", "-q"], "is a file, so no folder can be made under it")
    assert _listing(tmp_path) == ["afile"]


# ---------------------------------------------------------------- row 8: memory


@pytest.mark.parametrize(
    ("tables", "expected"),
    [
        ({"camera": {"pixels": [100000000, 100000000]}}, ["camera.pixels[0]", "<= 65536"]),
        ({"camera": {"pixels": [65536, 65536]}}, ["GB of memory", "limits.memory_gb"]),
        ({"volume": {"grid": [3000, 3000, 3000]}}, ["3000 x 3000 x 3000 volume.grid", "limits.memory_gb"]),
    ],
)
def test_row08_memory_estimate_before_any_work(tmp_path, capsys, tables, expected):
    cfg = _config_file(tmp_path, **tables)
    _error_line(capsys, ["render", cfg, "-o", tmp_path / "p.h5", "-q"], *expected, seconds=10)


def test_row08_files_with_a_huge_declared_shape(tmp_path, capsys):
    with open(tmp_path / "huge.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False,
                                                  "shape": (100000, 100000, 100000)})
    with h5py.File(tmp_path / "huge.h5", "w") as f:
        f.create_dataset("rho", shape=(100000,) * 3, dtype="f8", chunks=(8, 8, 8))
    for name in ("huge.npy", "huge.h5"):
        cfg = _config_file(tmp_path, volume={"source": "file", "path": str(tmp_path / name)})
        _error_line(capsys, ["render", cfg, "-o", tmp_path / "p.h5", "-q"], name,
                    "(100000, 100000, 100000) needs about 1.28e+08 GB", seconds=10)
    # Raising the limit is the documented way round (here it still refuses: the limit is per machine).
    with pytest.raises(SynthbosError, match=r"over the limit of 0\.001 GB"):
        load_config({**BASE, "camera": {"pixels": [512, 512]}, "limits": {"memory_gb": 0.001}})


# ---------------------------------------------------------------- row 9: --device


def test_row09_bad_device(tmp_path, capsys):
    cfg = _config_file(tmp_path)
    _error_line(capsys, ["render", cfg, "--device", "bogus", "-o", tmp_path / "p.h5", "-q"], "'bogus'")
    _error_line(capsys, ["paper", "--device", "bogus", "--out", tmp_path / "camp", "-q"], "'bogus'")
    _error_line(capsys, ["sweep", "--param", "density=4", "--device", "cpu:7", "--out", tmp_path / "sw", "-q"],
                "'cpu:7'")
    import warp as wp

    if not wp.is_cuda_available():
        _error_line(capsys, ["render", cfg, "--device", "cuda:0", "-o", tmp_path / "p.h5", "-q"], "no CUDA GPU")
        _error_line(capsys, ["paper", "--device", "cuda:0", "--out", tmp_path / "camp", "-q"], "no CUDA GPU")
    assert _listing(tmp_path) == ["cfg.toml"]


# ---------------------------------------------------------------- row 10: malformed pair files


@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        (lambda f: f.attrs.__delitem__("config"), "'config' attribute is missing"),
        (lambda f: f.attrs.__setitem__("config", "[camera\npixels = "), "'config' attribute is not valid TOML"),
        (lambda f: (f["dots"].__delitem__("target_xy_m"), f["dots"].create_group("target_xy_m")),
         "/dots/target_xy_m is a group"),
        (lambda f: (f["dots"].__delitem__("target_xy_m"), f["dots"].create_dataset("target_xy_m", data=np.zeros(5))),
         "/dots/target_xy_m must be (N, 2)"),
    ],
)
def test_row10_malformed_pair_file(tmp_path, capsys, pair_file, damage, expected):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(pair_file.read_bytes())
    with h5py.File(bad, "a") as f:
        damage(f)
    for method in ("correlation", "tracking"):
        _error_line(capsys, ["process", bad, "--method", method, "-o", tmp_path / "r.h5"], expected)
    assert _listing(tmp_path) == ["bad.h5"]


# ---------------------------------------------------------------- row 11: not UTF-8


def test_row11_non_utf8_configuration_and_dots(tmp_path, capsys, pair_file):
    cfg = tmp_path / "bad.toml"
    cfg.write_bytes(b"[camera]\npixels = [96, 96]\n# caf\xe9 \xff\n")
    _error_line(capsys, ["render", cfg, "-o", tmp_path / "p.h5", "-q"], "bad.toml is not UTF-8")
    _error_line(capsys, ["sweep", cfg, "--param", "density=4", "--out", tmp_path / "sw", "-q"], "not UTF-8")
    dots = tmp_path / "dots.csv"
    dots.write_bytes(b"x,y\n10,\xff\n")
    _error_line(capsys, ["process", pair_file, "--method", "tracking", "--dots", dots, "-o", tmp_path / "r.h5"],
                "dots.csv is not UTF-8")
    assert _listing(tmp_path) == ["bad.toml", "dots.csv"]


# ---------------------------------------------------------------- rows 12 and 21: sweep values


@pytest.mark.parametrize(
    ("param", "expected"),
    [
        ("window=nan", "finite"),
        ("rays=inf", "finite"),
        ("noise=nan", "finite"),
        ("window=2", "sweep point window=2"),  # row 21: refused before any render
        ("density=4,1e9", "target.dots_per_32px"),  # the second point fails before the first runs
        ("camera.glass_index=1e300", "camera.glass_index"),
    ],
)
def test_row12_and_21_sweep_values_checked_before_any_work(tmp_path, capsys, param, expected):
    _error_line(capsys, ["sweep", "--param", param, "--device", "cpu", "--out", tmp_path / "sw", "-q"], expected,
                seconds=10)
    assert _listing(tmp_path) == []


# ---------------------------------------------------------------- rows 13 to 17 and 21: configuration values


@pytest.mark.parametrize(
    ("tables", "expected"),
    [
        ({"camera": {"wavelength_nm": 1e300}, "target": {"dot_model": "disk"}}, "camera.wavelength_nm"),  # 13
        ({"rays": {"step_mm": 1e-300}}, "rays.step_mm"),
        ({"sensor": {"peak_intensity": 1e30}}, "sensor.peak_intensity"),  # 14
        ({"sensor": {"spot_diameter_px": 1e12}}, "sensor.spot_diameter_px"),
        ({"sensor": {"spot_diameter_px": 1e-300}}, "sensor.spot_diameter_px must be >= 0.1"),
        ({"camera": {"f_number": 1e-300}}, "camera.f_number"),
        ({"camera": {"pixel_pitch_um": 1e300}}, "camera.pixel_pitch_um"),
        ({"target": {"distance_mm": 1e300}}, "target.distance_mm"),
        ({"volume": {"density_kg_m3": 1e300}}, "volume.density_kg_m3"),
        ({"volume": {"source": "slice", "density_scale_kg_m3": 1e300}}, "volume.density_scale_kg_m3"),  # 15
        ({"volume": {"source": "slice", "density_scale_kg_m3": 1e5}}, "refractive index"),
        ({"rays": {"seed": 2**32}}, "rays.seed"),  # 16
        ({"rays": {"aim_iterations": 1e12}}, "rays.aim_iterations"),
        ({"sensor": {"spot_diameter_px": 1e5}}, "sensor.spot_diameter_px"),  # 17
        ({"target": {"dot_diameter_px": 1e5, "min_spacing_px": 0}}, "target.dot_diameter_px"),
        ({"camera": {"f_number": 1000}, "target": {"dot_model": "disk"}}, "diffraction spot"),
        ({"camera": {"glass_index": 1e300, "lens": "thick"}}, "camera.glass_index"),  # 21
    ],
)
def test_rows13_to_17_values_refused_before_rendering(tmp_path, capsys, tables, expected):
    if tables.get("volume", {}).get("source") == "slice":
        cfg = tmp_path / "cfg.toml"
        cfg.write_text(_toml({**{k: v for k, v in BASE.items() if k != "volume"}, **tables}))
    else:
        cfg = _config_file(tmp_path, **tables)
    _error_line(capsys, ["render", cfg, "-o", tmp_path / "p.h5", "-q"], expected, seconds=10)
    assert _listing(tmp_path) == ["cfg.toml"]


def test_row15_non_finite_truth_is_never_valid(pair_file):
    pair = read_pair(pair_file)
    assert pair.valid.all() and np.isfinite(pair.theory_px).all() and np.isfinite(pair.displacement_px).all()


# ---------------------------------------------------------------- row 16: seeds


def test_row16_seeds_honoured_or_refused():
    small = {**BASE, "rays": {"per_dot": 5}}
    r0 = render_pair({**small, "rays": {"per_dot": 5, "seed": 0}}, device="cpu")
    top = render_pair({**small, "rays": {"per_dot": 5, "seed": 2**32 - 1}}, device="cpu")
    assert not np.array_equal(r0.reference, top.reference)  # the largest ray seed is its own
    with pytest.raises(SynthbosError, match=r"rays\.seed must be >= 0 and <= 4294967295, got 4294967296 .*32-bit"):
        load_config({**small, "rays": {"seed": 2**32}})
    # The pattern's seed (NumPy) is honoured up to 2^63 - 1, and refused beyond.
    a = render_pair({**small, "target": {"dots_per_32px": 8.0, "seed": 2**63 - 1}}, device="cpu")
    b = render_pair({**small, "target": {"dots_per_32px": 8.0, "seed": 2**63 - 1 - 2**32}}, device="cpu")
    assert not np.array_equal(a.target_xy_m, b.target_xy_m)
    with pytest.raises(SynthbosError, match=r"target\.seed must be >= 0 and <= 9223372036854775807"):
        load_config({**small, "target": {"seed": 2**63}})
    with pytest.raises(SynthbosError, match=r"rays\.aim_iterations must be >= 0 and <= 100"):
        load_config({**small, "rays": {"aim_iterations": 1e12}})


def test_row16_seed_in_the_pair_file_config_round_trips():
    cfg = load_config({**BASE, "rays": {"seed": 2**32 - 1}, "target": {"seed": 2**63 - 1}})
    import tomllib

    again = load_config(tomllib.loads(config_to_toml(cfg)))
    assert again["rays"]["seed"] == 2**32 - 1 and again["target"]["seed"] == 2**63 - 1


# ---------------------------------------------------------------- row 20: two campaigns, one folder


def test_row20_busy_campaign_folder_is_refused(tmp_path, capsys):
    folder = tmp_path / "camp"
    folder.mkdir()
    with folder_lock(folder):
        line = _error_line(capsys, ["paper", "--quick", "--device", "cpu", "--out", folder, "-q"], "is in use by")
        assert f"process {os.getpid()}" in line and "--wait" in line
        assert _listing(folder) == [".lock"]
    assert _listing(folder) == []  # the lock file goes with the run that held it


def test_lock_taken_on_a_removed_lock_file_is_taken_again(tmp_path):
    """A waiter that opened the lock file before its holder removed it locks the new file, not the old one:
    two runs never hold the folder at once."""
    import threading

    folder = tmp_path / "camp"
    folder.mkdir()
    order = []
    with folder_lock(folder):
        waiter = threading.Thread(target=lambda: order.append(_hold(folder)))
        waiter.start()
        time.sleep(0.3)  # the waiter has opened .lock and polls it
        order.append("first done")
    waiter.join(10)
    assert order == ["first done", "second held"]
    with pytest.raises(SynthbosError, match="is in use"):  # while a lock is held, the folder is refused
        with folder_lock(folder), folder_lock(folder):
            pass
    assert _listing(folder) == []


def _hold(folder):
    with folder_lock(folder, wait=True, poll_s=0.05):
        return "second held"


def test_row03_resume_removes_temporaries_of_a_killed_run(tmp_path):
    from dataclasses import replace

    from synthbos.benchmarks.campaign import run_campaign
    from synthbos.benchmarks.spec import REGRESS

    spec = replace(REGRESS, name="tiny", snapshots=(2,), noise_percent=(0.0,), methods=("correlation",),
                   config={"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 10}})
    folder = tmp_path / "camp"
    run_campaign(spec, folder, device="cpu", workers=1, progress=False, figures=False)
    done = _listing(folder)
    # What a SIGKILL during a write leaves: a hidden temporary beside the final name.
    (folder / "pairs" / ".s2_p00.h5.x1y2.tmp").write_bytes(b"partial")
    (folder / "scores" / ".s2_p00_n0_correlation.npz.abcd.tmp").write_bytes(b"partial")
    run_campaign(spec, folder, device="cpu", workers=1, progress=False, figures=False)
    assert _listing(folder) == done


def test_row20_wait_for_the_lock(tmp_path):
    held, released = threading.Event(), threading.Event()

    def holder():
        with folder_lock(tmp_path):
            held.set()
            time.sleep(0.5)
            released.set()

    t = threading.Thread(target=holder)
    t.start()
    held.wait(5)
    with pytest.raises(SynthbosError, match="in use"):
        with folder_lock(tmp_path):
            pass
    with folder_lock(tmp_path, wait=True, poll_s=0.05):
        assert released.is_set()
    t.join()


# ---------------------------------------------------------------- more classes found by trying the commands


def test_more_bad_inputs_give_one_line(tmp_path, capsys, pair_file):
    # Seeds are set per pair by the campaign: sweeping one would silently change nothing.
    _error_line(capsys, ["sweep", "--param", "rays.seed=1,2", "--out", tmp_path / "sw", "-q"], "rays.seed")
    # A base configuration whose table is a number.
    bad = tmp_path / "bad.toml"
    bad.write_text("camera = 5\n")
    _error_line(capsys, ["sweep", bad, "--param", "density=4", "--out", tmp_path / "sw", "-q"],
                "[camera] must be a table of keys")
    _error_line(capsys, ["render", tmp_path, "-o", tmp_path / "p.h5", "-q"], "is a folder, not a TOML file")
    # An image format matplotlib cannot write.
    _error_line(capsys, ["show-density", "-o", tmp_path / "d.xyz"], "name a figure file ending in one of")
    # A dots file with three columns.
    dots = tmp_path / "dots.csv"
    dots.write_text("x,y\n1,2\n3,4,5\n")
    _error_line(capsys, ["process", pair_file, "--method", "tracking", "--dots", dots, "-o", tmp_path / "r.h5"],
                "line 3: expected two values x,y, got 3")
    assert _listing(tmp_path) == ["bad.toml", "dots.csv"]
