"""Issue 31: the newer surface (process settings, calibrate, integrate, show-result, sweep, --scheduler) ends
on bad input in one line, exit status 2, nothing written: no traceback, no hang, no silent nonsense.

One fast case of every class of the issue, through the command line as a user types it (``main([...])`` in
this process; a subprocess where a pipe or a signal is involved). The inputs are a 96 x 96 px pair and the
results of processing it.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
from synthbos.benchmarks.cli import main
from synthbos.raytrace import render_pair, write_pair
from test_bad_input import BASE  # the small render set-up of the first round's bad-input tests

from synthbos.values import MAX_LINE, error_line

ROOT = Path(__file__).resolve().parents[2]


def _listing(folder):
    return sorted(str(p.relative_to(folder)) for p in Path(folder).rglob("*"))


def _error_line(capsys, argv, *expected, seconds=20.0):
    """Run ``main(argv)``: exit status 2, one line ``synthbos: error: ...`` of at most 200 characters naming
    ``expected``, quickly."""
    t0 = time.perf_counter()
    rc = main([str(a) for a in argv])
    elapsed = time.perf_counter() - t0
    captured = capsys.readouterr()
    lines = [ln for ln in captured.err.splitlines() if ln.strip() and not ln.startswith("Warp")]
    assert rc == 2, captured.err
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("synthbos: error: ") and len(lines[0]) <= MAX_LINE, lines[0]
    for text in expected:
        assert text in lines[0], lines[0]
    assert elapsed < seconds
    return lines[0]


def _cli(argv, cwd, **kwargs):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "synthbos", *map(str, argv)], cwd=cwd, env=env, text=True,
                            **kwargs)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A pair file, its tracking and correlation results, a mask and a process configuration."""
    folder = tmp_path_factory.mktemp("newer")
    write_pair(folder / "p.h5", render_pair(BASE, device="cpu"))
    for method in ("tracking", "correlation"):
        assert main(["process", str(folder / "p.h5"), "--method", method, "-o", str(folder / f"{method}.h5"),
                     "--device", "cpu"]) == 0
    mask = np.full((96, 96), 255, np.uint8)
    mask[:, :10] = 0
    tifffile.imwrite(folder / "mask.tif", mask)
    return folder


def _process_config(folder, text, name="cfg.toml"):
    path = Path(folder) / name
    path.write_text(text)
    return path


# ---------------------------------------------------------------- every setting range-checked where it is read


@pytest.mark.parametrize(
    ("method", "text", "expected"),
    [
        ("tracking", "diameter = 1e6", "diameter must be > 0 and <= 64, got 1000000.0"),
        ("tracking", "diameter = 1e300", "diameter must be > 0 and <= 64"),
        ("tracking", "max_displacement = nan", "max_displacement must be finite (> 0 and <= 100), got nan"),
        ("tracking", "max_displacement = inf", "max_displacement must be finite"),
        ("tracking", "max_displacement = 1e300", "max_displacement must be > 0 and <= 100"),
        ("tracking", "max_displacement = -2.0", "max_displacement must be > 0 and <= 100, got -2.0"),
        ("tracking", "outlier_neighbours = -3", "outlier_neighbours must be >= 3 and <= 64, got -3"),
        ("tracking", "search_radius = -1.0", "search_radius must be > 0 and <= 128"),
        ("tracking", "n_levels = 0", "n_levels must be >= 1 and <= 64, got 0"),
        ("tracking", "weights = [1.0]", "weights must be a list of 3 numbers, got 1"),
        ("tracking", "fit_iterations = 1000000000", "fit_iterations must be >= 1 and <= 20"),
        ("tracking", "max_iterations = 1000000000", "max_iterations must be >= 1 and <= 20"),
        ("tracking", 'diameter = "big"', "diameter must be a number (> 0 and <= 64), got 'big'"),
        ("tracking", "predictor_windows = [64, 1e9]", "predictor_windows[1] must be >= 8 and <= 1024"),
        ("tracking", "predictor_windows = [64, 12.5]", "predictor_windows[1] must be a whole number"),
        ("correlation", "iterations = 1000000000", "iterations[0] must be >= 1 and <= 20"),
        ("correlation", "window_sizes = [99999999999]", "window_sizes[0] must be >= 4 and <= 1024"),
        ("correlation", "median_epsilon = 1e300", "median_epsilon must be >= 0 and <= 100"),
    ],
)
def test_process_settings_out_of_range_are_named_with_their_range(files, tmp_path, capsys, method, text, expected):
    cfg = _process_config(tmp_path, f"[{method}]\n{text}\n")
    _error_line(capsys, ["process", files / "p.h5", "--method", method, "--config", cfg, "-o", tmp_path / "r.h5"],
                f"{method} settings: ", expected, seconds=5)
    assert _listing(tmp_path) == ["cfg.toml"]


def test_process_flags_and_mask_path_checked(files, tmp_path, capsys):
    out = tmp_path / "r.h5"
    for flag, value, expected in [("--diameter", "1e6", "diameter must be > 0 and <= 64"),
                                  ("--max-displacement", "nan", "max_displacement must be finite"),
                                  ("--max-displacement", "-1", "max_displacement must be > 0")]:
        _error_line(capsys, ["process", files / "p.h5", "--method", "tracking", flag, value, "-o", out], expected)
    long_mask = "m" * 100_000  # (the case is 100 MB; the check is the same)
    cfg = _process_config(tmp_path, f'[image]\nmask = "{long_mask}"\n')
    line = _error_line(capsys, ["process", files / "p.h5", "--method", "tracking", "--config", cfg, "-o", out],
                       "image option mask must be a path of 1 to 4096 characters", "characters)")
    assert "m" * 100 not in line
    assert _listing(tmp_path) == ["cfg.toml"]


def test_calibrate_mapping_order_and_spacing_bounded(files, tmp_path, capsys):
    terms = [[i, j] for i in range(2) for j in range(2 - i)]
    mapping = {"format": "synthbos-soloff-mapping", "version": 1, "order": 1_000_000, "terms": terms,
               "coef_x": [0.0, 1.0, 0.0], "coef_y": [0.0, 0.0, 1.0], "centre": [0, 0], "scale": [1, 1],
               "image_shape": [96, 96]}
    (tmp_path / "map.json").write_text(json.dumps(mapping))
    (tmp_path / "target.csv").write_text("x_mm,y_mm\n1,2\n3,4\n")
    out = tmp_path / "dots.csv"
    t0 = time.perf_counter()
    _error_line(capsys, ["calibrate", "--mapping", tmp_path / "map.json", "--target", tmp_path / "target.csv",
                         "-o", out], "mapping order must be 1 to 5, got 1000000", seconds=2)
    assert time.perf_counter() - t0 < 2
    mapping["order"] = float("inf")
    (tmp_path / "map.json").write_text(json.dumps(mapping))
    _error_line(capsys, ["calibrate", "--mapping", tmp_path / "map.json", "--target", tmp_path / "target.csv",
                         "-o", out], "calibration mapping is malformed")
    tifffile.imwrite(tmp_path / "grid.tif", np.zeros((32, 32), np.uint8))
    for args, expected in [(["--grid", "nan"], "--grid (the grid spacing, mm) must be finite"),
                           (["--grid", "2", "--order", "1000000"], "--order (the mapping's polynomial degree) must "
                                                                    "be >= 1 and <= 5")]:
        _error_line(capsys, ["calibrate", "--reference", tmp_path / "grid.tif", *args, "-o", out], expected)
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--spacing", "nan"], "--spacing (px) must be finite (>= 1 and <= 10000), got nan"),
        (["--spacing", "1e-6"], "--spacing (px) must be >= 1 and <= 10000, got 1e-06"),
        (["--reference-density", "-1.2"], "--reference-density (kg/m^3) must be > 0 and <= 100000, got -1.2"),
        (["--reference-density", "1e300"], "--reference-density (kg/m^3) must be > 0"),
        (["--reference-region=nan,1,2,3"], "--reference-region (mm)[0] must be finite"),
        (["--mask-region=0,1,2,1e300"], "--mask-region (mm)[3] must be >= -1e+06 and <= 1e+06"),
    ],
)
def test_integrate_options_checked_before_reading(files, tmp_path, capsys, args, expected):
    _error_line(capsys, ["integrate", files / "correlation.h5", "--pair", files / "p.h5", *args,
                         "-o", tmp_path / "d.h5"], expected, seconds=2)
    assert _listing(tmp_path) == []


# ---------------------------------------------------------------- file shapes checked before allocation


def _huge_copy(src, dst, replace):
    """Copy an HDF5 file and replace datasets by chunked ones of huge declared shape (nearly empty on disk)."""
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        for name, shape in replace.items():
            dtype = f[name].dtype
            del f[name]
            f.create_dataset(name, shape=shape, dtype=dtype, chunks=tuple(min(64, n) for n in shape))
    assert os.path.getsize(dst) < 10e6
    return dst


def test_pair_and_result_files_declaring_huge_shapes(files, tmp_path, capsys):
    big = (10**6, 10**6)
    pair_big = _huge_copy(files / "p.h5", tmp_path / "big_images.h5",
                          {"images/reference": big, "images/gradient": big})
    with h5py.File(files / "p.h5") as f:
        dots = {f"dots/{n}": (10**12, f[f"dots/{n}"].shape[1]) for n in f["dots"] if f[f"dots/{n}"].ndim == 2}
        dots.update({f"dots/{n}": (10**12,) for n in f["dots"] if f[f"dots/{n}"].ndim == 1})
    pair_dots = _huge_copy(files / "p.h5", tmp_path / "big_dots.h5", dots)
    out = tmp_path / "r.h5"
    for pair in (pair_big, pair_dots):
        _error_line(capsys, ["process", pair, "--method", "correlation", "-o", out], pair.name,
                    "GB of memory, over the limit of", seconds=5)
        _error_line(capsys, ["integrate", files / "tracking.h5", "--pair", pair, "-o", tmp_path / "d.h5"],
                    "GB of memory, over the limit of", seconds=5)
    with h5py.File(files / "tracking.h5") as f:
        columns = {f"dots/{n}": (10**12,) for n in f["dots"]}
    result_big = _huge_copy(files / "tracking.h5", tmp_path / "big_result.h5", columns)
    _error_line(capsys, ["show-result", result_big, "-o", tmp_path / "f.png"], "declares shape (1000000000000,)",
                seconds=5)
    _error_line(capsys, ["integrate", result_big, "--pair", files / "p.h5", "-o", tmp_path / "d.h5"],
                "GB of memory, over the limit of", seconds=5)
    assert sorted(_listing(tmp_path)) == ["big_dots.h5", "big_images.h5", "big_result.h5"]


# ---------------------------------------------------------------- images of no size, a folder as output


def test_empty_image_and_folder_output(files, tmp_path, capsys):
    empty = tmp_path / "empty.tif"
    with pytest.warns(UserWarning):
        tifffile.imwrite(empty, np.zeros((0, 0), np.uint16))
    for method in ("correlation", "tracking"):
        _error_line(capsys, ["process", "--reference", empty, "--gradient", empty, "--method", method,
                             "-o", tmp_path / "r.h5"], "the images are 0 x 0 px; processing needs at least 8 x 8 px")
    cfg = tmp_path / "cfg.toml"
    cfg.write_text('[camera]\npixels = [96, 96]\n[volume]\nsource = "gaussian"\n')
    _error_line(capsys, ["render", cfg, "-o", f"{tmp_path / 'out'}/", "-q"], "names a folder; name a file")
    assert _listing(tmp_path) == ["cfg.toml", "empty.tif"]


# ---------------------------------------------------------------- --scheduler inputs


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (b"\x00\xff garbage", "is not JSON"),
        (b"", "is not JSON"),
        (b'["tcp://127.0.0.1:8786"]', "holds a JSON list, not an object"),
        (b'{"id": "Scheduler-1", "services": {}}', "names no address (its keys: ['id', 'services'])"),
        (b'{"address": "carrier-pigeon://127.0.0.1:8786"}', "unknown protocol 'carrier-pigeon'"),
        (b'{"address": "tcp://127.0.0.1:99999"}', "the port must be a number 1 to 65535"),
        (b'{"address": 8786}', "the scheduler address must be text"),
    ],
)
def test_scheduler_file_checked_before_any_work(tmp_path, capsys, content, expected):
    path = tmp_path / "scheduler.json"
    path.write_bytes(content)
    _error_line(capsys, ["paper", "--quick", "--device", "cpu", "--scheduler", path, "--out", tmp_path / "camp",
                         "-q"], expected, seconds=10)
    assert _listing(tmp_path) == ["scheduler.json"]


@pytest.mark.parametrize(
    ("address", "expected"),
    [
        ("udp://127.0.0.1:8786", "unknown protocol 'udp'"),
        ("tcp://127.0.0.1:port", "the port must be a number 1 to 65535, got 'port'"),
        ("tcp://:8786", "expected tcp://HOST:PORT"),
        ("nonsense", "--scheduler must be 'local', PROTOCOL://HOST:PORT"),
    ],
)
def test_scheduler_address_checked(tmp_path, capsys, address, expected):
    _error_line(capsys, ["sweep", "--param", "noise=0,1", "--device", "cpu", "--scheduler", address,
                         "--out", tmp_path / "sw", "-q"], expected, seconds=10)
    assert _listing(tmp_path) == []


# ---------------------------------------------------------------- a closed output pipe


@pytest.mark.parametrize("command", ["show-result", "process"])
def test_closed_output_pipe_ends_quietly(files, tmp_path, command):
    """``synthbos ... | head`` with the reader gone: no BrokenPipeError, no message; the output is written."""
    out = tmp_path / ("f.png" if command == "show-result" else "r.h5")
    argv = ([command, files / "tracking.h5", "-o", out] if command == "show-result"
            else [command, files / "p.h5", "--method", "tracking", "--device", "cpu", "-o", out])
    proc = _cli(argv, tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader is gone before the first line
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 128 + signal.SIGPIPE, err
    assert [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("Warp")] == [], err
    # It ends where the closed pipe showed (as a Unix tool does on SIGPIPE): a whole output or none.
    assert _listing(tmp_path) in ([], [out.name])


# ---------------------------------------------------------------- outputs that are inputs, figures


def test_process_output_naming_its_config_or_mask_is_refused(files, tmp_path, capsys):
    shutil.copy(files / "mask.tif", tmp_path / "mask.tif")
    cfg = _process_config(tmp_path, '[image]\nmask = "mask.tif"\n')
    before = {p: p.read_bytes() for p in (cfg, tmp_path / "mask.tif")}
    base = ["process", files / "p.h5", "--method", "correlation"]
    _error_line(capsys, [*base, "--config", cfg, "-o", cfg], "-o", "is also an input")
    _error_line(capsys, [*base, "--mask", tmp_path / "mask.tif", "-o", tmp_path / "mask.tif"], "is also an input")
    _error_line(capsys, [*base, "--config", cfg, "-o", tmp_path / "mask.tif"], "is also an input")
    assert {p: p.read_bytes() for p in before} == before


def test_show_result_writes_only_the_named_figure(files, tmp_path, capsys):
    unrelated = tmp_path / "x.png"
    unrelated.write_bytes(b"someone else's picture")
    assert main(["show-result", str(files / "correlation.h5"), "-o", str(tmp_path / "x.pdf")]) == 0
    assert (tmp_path / "x.pdf").read_bytes()[:4] == b"%PDF"
    assert unrelated.read_bytes() == b"someone else's picture"
    assert main(["show-result", str(files / "correlation.h5"), "-o", str(tmp_path / "y.svg")]) == 0
    assert _listing(tmp_path) == ["x.pdf", "x.png", "y.svg"]
    capsys.readouterr()
    for name in ("fig.xyz", "fig"):
        _error_line(capsys, ["show-result", files / "correlation.h5", "-o", tmp_path / name],
                    "name a figure file ending in one of", ".png")
    assert _listing(tmp_path) == ["x.pdf", "x.png", "y.svg"]


def test_show_result_on_other_or_broken_files(files, tmp_path, capsys):
    density = tmp_path / "d.h5"
    assert main(["integrate", str(files / "tracking.h5"), "--pair", str(files / "p.h5"), "-o", str(density)]) == 0
    capsys.readouterr()
    fig = tmp_path / "f.png"
    assert main(["show-result", str(density), "-o", str(tmp_path / "d.png")]) == 0  # a density file is drawn
    assert (tmp_path / "d.png").read_bytes()[:4] == b"\x89PNG"
    capsys.readouterr()
    _error_line(capsys, ["show-result", files / "p.h5", "-o", fig], "is a pair file of 'synthbos render'")
    no_flags = tmp_path / "no_flags.h5"
    shutil.copy(files / "correlation.h5", no_flags)
    with h5py.File(no_flags, "r+") as f:
        del f["flags"]
    _error_line(capsys, ["show-result", no_flags, "-o", fig], "missing /flags")
    broken = tmp_path / "broken.h5"
    shutil.copy(files / "tracking.h5", broken)
    with h5py.File(broken, "r+") as f:
        f.attrs["settings"] = "{not json"
    _error_line(capsys, ["show-result", broken, "-o", fig], "its settings attribute is not JSON text")
    assert not fig.exists()


# ---------------------------------------------------------------- input that can only give nonsense


def test_prior_with_duplicates_or_outside_the_image_is_refused(files, tmp_path, capsys):
    from synthbos.benchmarks.items import nominal_positions
    from synthbos.raytrace import read_pair

    xy = nominal_positions(read_pair(files / "p.h5"))
    dup = np.concatenate([xy, xy[:5] + 0.01])
    (tmp_path / "dup.csv").write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in dup))
    out = tmp_path / "r.h5"
    _error_line(capsys, ["process", files / "p.h5", "--method", "tracking-cc", "--dots", tmp_path / "dup.csv",
                         "-o", out], "10 positions that are another's within 0.5 px", "each dot must be listed once")
    (tmp_path / "far.csv").write_text("x,y\n" + "".join(f"{x * 1e3},{y * 1e3 + 1e5}\n" for x, y in xy))
    _error_line(capsys, ["process", files / "p.h5", "--method", "tracking-cc", "--dots", tmp_path / "far.csv",
                         "-o", out], "no dot of the prior lies in the 96 x 96 px image")
    assert not out.exists()


def test_prior_with_some_dots_outside_the_image_is_measured_with_a_note(files, tmp_path, capsys):
    """A target larger than the view: the dots of the prior outside the image are named in a note, not refused."""
    from synthbos.benchmarks.cli import main
    from synthbos.benchmarks.items import nominal_positions
    from synthbos.raytrace import read_pair

    xy = np.concatenate([nominal_positions(read_pair(files / "p.h5")), [[500.0, 20.0], [-40.0, 50.0]]])
    (tmp_path / "wide.csv").write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in xy))
    out = tmp_path / "r.h5"
    assert main(["process", str(files / "p.h5"), "--method", "tracking-cc", "--dots", str(tmp_path / "wide.csv"),
                 "-o", str(out)]) == 0
    assert f"note: 2 of the {len(xy)} dots of the prior lie outside the 96 x 96 px image" in capsys.readouterr().out
    assert out.exists()


def test_calibration_target_with_no_dot_in_the_image(tmp_path, capsys):
    terms = [[i, j] for i in range(2) for j in range(2 - i)]
    mapping = {"format": "synthbos-soloff-mapping", "version": 1, "order": 1, "terms": terms,
               "coef_x": [48.0, 0.0, 10.0], "coef_y": [48.0, 10.0, 0.0], "centre": [0, 0], "scale": [1, 1],
               "image_shape": [96, 96]}
    (tmp_path / "map.json").write_text(json.dumps(mapping))
    # 10 px per mm: a target in micrometres lands far outside the image.
    rows = "".join(f"{x * 1000},{y * 1000}\n" for x in range(1, 6) for y in range(1, 6))
    (tmp_path / "target.csv").write_text("x_mm,y_mm\n" + rows)
    _error_line(capsys, ["calibrate", "--mapping", tmp_path / "map.json", "--target", tmp_path / "target.csv",
                         "-o", tmp_path / "dots.csv"], "none of the 25 target dots maps into the calibrated 96 x 96")
    assert not (tmp_path / "dots.csv").exists()


def test_integrate_refuses_absurd_displacements_and_densities(files, tmp_path, capsys):
    absurd = tmp_path / "absurd.h5"
    shutil.copy(files / "correlation.h5", absurd)
    with h5py.File(absurd, "r+") as f:
        f["u"][...] = 1e300
    out = tmp_path / "d.h5"
    _error_line(capsys, ["integrate", absurd, "--pair", files / "p.h5", "-o", out],
                "displacement of 1e+300 px, longer than the 96 x 96 px image's diagonal")
    assert _listing(tmp_path) == ["absurd.h5"]
    # A reference density a million times too small: the reconstruction goes negative, which no fluid is:
    # written, with a one-line warning (issue 28).
    assert main([str(a) for a in ["integrate", files / "correlation.h5", "--pair", files / "p.h5",
                                  "--reference-density", "1e-6", "-o", out]]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip() and not ln.startswith("Warp")]
    assert len(err) == 1 and err[0].startswith("synthbos: warning: the density is negative (unphysical) at "), err
    with h5py.File(out) as f:
        rho = f["density_kg_m3"][()]
        assert np.nanmin(rho) < 0 and f.attrs["negative_nodes"] == np.count_nonzero(rho < 0) > 0


# ---------------------------------------------------------------- error messages shortened


def test_error_line_is_cut_to_200_characters():
    line = error_line(ValueError("sweep value list " + ", ".join(str(v) for v in range(1000)) + " is bad"))
    assert len(line) <= MAX_LINE and line.startswith("synthbos: error: sweep value list 0, 1, 2")
    huge = "x" * 100_000_000
    line = error_line(ValueError(f"bad key {huge} (in cfg.toml)"))
    assert len(line) <= MAX_LINE and line.endswith("(in cfg.toml)") and "..." in line
    path = "/very/long/folder/" * 20 + "result.h5"
    line = error_line(ValueError(f"cannot read {path}: no space left on device"))
    assert len(line) <= MAX_LINE and line.endswith("result.h5: no space left on device")


def test_long_values_in_commands_give_short_lines(tmp_path, capsys):
    values = ",".join(str(v) for v in range(1000)) + ",nan"
    _error_line(capsys, ["sweep", "--param", f"noise={values}", "--device", "cpu", "--out", tmp_path / "sw", "-q"],
                "noise", seconds=20)
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(f'[camera]\npixels = [96, 96]\n[volume]\nsource = "{"g" * 10_000_000}"\n')
    line = _error_line(capsys, ["render", cfg, "-o", tmp_path / "p.h5", "-q"], "volume.source", seconds=20)
    assert "characters" in line or "..." in line


# ---------------------------------------------------------------- Ctrl-C on a Dask campaign


@pytest.mark.slow
@pytest.mark.parametrize("delay", [1.0, 2.0, 3.0, 5.0])
def test_ctrl_c_while_a_local_dask_campaign_starts_prints_one_line(tmp_path, delay):
    """Ctrl-C while the command loads, while the cluster starts its workers (which would end with
    tracebacks of their own) or while they import: one line, status 130, the whole run stopped."""
    pytest.importorskip("distributed")
    out = tmp_path / "camp"
    proc = _cli(["paper", "--quick", "--device", "cpu", "--scheduler", "local", "--workers", "2", "-q", "--out", out],
                tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    time.sleep(delay)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("Warp")]
    assert proc.returncode == 130, err
    assert len(lines) == 1 and lines[0].startswith("synthbos: interrupted"), err


@pytest.mark.slow
def test_ctrl_c_on_a_local_dask_campaign_prints_one_line(tmp_path):
    pytest.importorskip("distributed")
    out = tmp_path / "camp"
    proc = _cli(["paper", "--quick", "--device", "cpu", "--scheduler", "local", "--workers", "2", "-q", "--out", out],
                tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    deadline = time.monotonic() + 300
    while not list(out.glob("**/*.npz")) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    os.killpg(proc.pid, signal.SIGINT)  # a terminal's Ctrl-C reaches the whole process group
    _, err = proc.communicate(timeout=120)
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("Warp")]
    assert proc.returncode == 130
    assert lines == ["synthbos: interrupted; finished items are kept, re-run to resume"], err


# ---------------------------------------------------------------- a refractivity of zero


def test_gladstone_dale_of_zero_is_refused(tmp_path, capsys):
    """K = 0 makes every ray straight and every density truth 0/0: refused in one line, nothing written."""
    cfg = tmp_path / "k0.toml"
    cfg.write_text("[volume]\ngladstone_dale_m3_per_kg = 0.0\n")
    _error_line(capsys, ["render", cfg, "-o", tmp_path / "p.h5"], "gladstone_dale_m3_per_kg", "> 0")
    assert _listing(tmp_path) == ["k0.toml"]


def test_ctrl_c_while_the_options_are_read_prints_one_line(monkeypatch, capsys):
    """A Ctrl-C that lands while argparse reads the options (seen at 2 s on a loaded 2-core machine):
    one line and status 130, not argparse's traceback."""
    from synthbos.benchmarks import cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert cli.main(["paper", "--quick"]) == 130
    captured = capsys.readouterr()
    assert captured.err.strip().splitlines() == ["synthbos: interrupted"] and captured.out == ""
