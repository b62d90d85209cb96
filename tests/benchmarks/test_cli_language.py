"""One command-line language: every option helped with its default, -o on every writing command, -q on every
command, one meaning per option name; options a method ignores refused; advice that fits what failed; a
prompt Ctrl-C on render."""

import argparse
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from synthbos.benchmarks.advice import failure_advice
from synthbos.benchmarks.cli import EXAMPLES, build_parser, in_worker_thread, main, work_abandoned
from synthbos.benchmarks.process import process_pair
from synthbos.benchmarks.registry import DOTS, GRID, MethodResult, get_method
from synthbos.correlation import CorrelationSettings
from synthbos.correlation.multigrid import VectorFlag, count_vectors
from synthbos.tracking import DotStatus

ROOT = Path(__file__).resolve().parents[2]
#: The commands that write files or folders.
WRITERS = {"render", "process", "integrate", "calibrate", "paper", "regress", "sweep", "show-density", "show-result"}


def _commands():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def _options(p):
    return [a for a in p._actions if not isinstance(a, argparse._HelpAction)]


def test_every_option_has_help_and_every_command_its_examples():
    commands = _commands()
    assert set(commands) == set(EXAMPLES)
    for name, p in commands.items():
        for action in _options(p):
            if action.help == argparse.SUPPRESS:  # an alias: the option it spells names it in its help
                twin = [a for a in _options(p) if a.dest == action.dest and a is not action]
                assert twin and all(o in twin[0].help for o in action.option_strings), (name, action.option_strings)
                continue
            assert action.help and action.help.strip(), (name, action.option_strings or action.dest)
        text = p.format_help()
        assert "examples:\n  synthbos " + name in text, name


def test_every_writing_command_has_o_and_every_command_q():
    for name, p in _commands().items():
        strings = {s for a in _options(p) for s in a.option_strings}
        assert {"-q", "--quiet"} <= strings, name
        if name in WRITERS:
            assert {"-o", "--output"} <= strings, name
            dest = next(a for a in _options(p) if "-o" in a.option_strings).dest
            assert dest in ("output", "out"), name  # the campaign commands keep the name of their older --out


def test_defaults_are_shown():
    commands = _commands()
    assert "campaign size per point (default: regress)" in " ".join(commands["sweep"].format_help().split())
    integrate = " ".join(commands["integrate"].format_help().split())
    assert "uncertainty-weighted (default: lsq)" in integrate
    # no "(default: None)" or "(default: False)" anywhere
    for name, p in commands.items():
        text = p.format_help()
        assert "default: None" not in text and "default: False" not in text, name


def test_old_spellings_and_both_forms_of_invert_parse():
    parser = build_parser()
    args = parser.parse_args(["process", "p.h5", "--method", "tracking", "-o", "r.h5", "--config", "s.toml"])
    assert args.settings == "s.toml"  # process's --config is now --settings
    args = parser.parse_args(["process", "p.h5", "--method", "tracking", "-o", "r.h5", "--settings", "s.toml",
                              "--invert"])
    assert (args.settings, args.invert) == ("s.toml", "true")
    assert parser.parse_args(["calibrate", "--invert", "false", "-o", "d.csv"]).invert == "false"
    assert parser.parse_args(["calibrate", "--invert", "-o", "d.csv"]).invert == "true"
    assert parser.parse_args(["calibrate", "-o", "d.csv"]).invert is None
    for cmd in (["paper"], ["regress"], ["sweep", "--param", "noise=0"]):
        assert parser.parse_args([*cmd, "--out", "f"]).out == "f"
        assert parser.parse_args([*cmd, "-o", "f"]).out == "f"
        assert parser.parse_args([*cmd, "--output", "f"]).out == "f"
    # integrate's --config is a render configuration, as render's and sweep's CONFIG.toml
    helps = {name: " ".join(p.format_help().split()) for name, p in _commands().items()}
    assert "--config CONFIG.toml render configuration" in helps["integrate"]
    assert all("CONFIG.toml render configuration" in helps[c] for c in ("render", "sweep"))


def test_sweep_without_a_folder_is_one_line(capsys):
    assert main(["sweep", "--param", "noise=0,1", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "-o FOLDER" in err[0]


def test_dots_with_a_method_that_ignores_them_is_refused(tmp_path, capsys):
    dots = tmp_path / "dots.csv"
    dots.write_text("x,y\n10,10\n")
    out = tmp_path / "r.h5"
    status = main(["process", "--reference", "a.tif", "--gradient", "b.tif", "--method", "correlation",
                   "--dots", str(dots), "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1
    assert "--dots" in err[0] and "correlation" in err[0] and "tracking" in err[0]
    assert not out.exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["process", "--reference", "a.tif", "--gradient", "b.tif", "--method", "tracking", "--mask-excludes", "dark",
          "-o", "r.h5"], "--mask-excludes: there is no mask"),
        (["paper", "--quick", "--device", "cpu", "--worker-device", "cpu", "-o", "camp"],
         "--worker-device cpu: it applies when processing on a GPU"),
        (["sweep", "--param", "noise=0", "--device", "cpu", "--worker-device", "cpu", "-o", "camp"],
         "--worker-device cpu: it applies when processing on a GPU"),
        (["sweep", "--param", "window=16,32", "--methods", "tracking,tracking-cc", "--device", "cpu", "-o", "sw"],
         "sweep parameter window sets the correlation windows; none of the methods (tracking, tracking-cc)"),
    ],
)
def test_options_the_run_would_ignore_are_refused(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_methods_quiet_lists_the_names(capsys):
    assert main(["methods", "-q"]) == 0
    names = capsys.readouterr().out.split()
    assert names[:3] == ["correlation", "tracking", "tracking-cc"]


# ---------------------------------------------------------------- advice that fits what failed


def _dots_image(shape, spacing, shift, *, jitter=0.0, seed=0, diameter=3.0):
    """Integrated-free Gaussian dots on a grid of ``spacing`` px (jittered by ``jitter`` px), moved by ``shift``."""
    h, w = shape
    rng = np.random.default_rng(seed)
    cx, cy = np.meshgrid(np.arange(-spacing, w + spacing, spacing), np.arange(-spacing, h + spacing, spacing))
    cx = cx.ravel() + rng.normal(0, jitter, cx.size) + shift[0]
    cy = cy.ravel() + rng.normal(0, jitter, cy.size) + shift[1]
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    s2 = 2 * (diameter / 4) ** 2
    img = np.zeros(shape)
    for x0, y0 in zip(cx, cy, strict=True):
        x_lo, x_hi = max(int(x0) - 4, 0), min(int(x0) + 6, w)
        y_lo, y_hi = max(int(y0) - 4, 0), min(int(y0) + 6, h)
        if x_lo < x_hi and y_lo < y_hi:
            img[y_lo:y_hi, x_lo:x_hi] += np.exp(-((xs[y_lo:y_hi, x_lo:x_hi] - x0) ** 2
                                                  + (ys[y_lo:y_hi, x_lo:x_hi] - y0) ** 2) / s2)
    return img + np.random.default_rng(seed + 100).normal(0, 0.02, shape)


def _correlate(a, b, **settings):
    res, _ = process_pair("correlation", a, b, settings=get_method("correlation").settings(settings), device="cpu")
    return res


@pytest.mark.skipif("pattern" in CorrelationSettings.__dataclass_fields__,
                    reason="the correlation judges periodic patterns itself; the advice is tested on drawn flags below")
def test_regular_pattern_advice_names_peak_ratio_min():
    """A regular grid whose period divides the window: every window has two equal peaks (ratio ~1.0001)."""
    a = _dots_image((128, 128), 8.0, (0, 0))
    b = _dots_image((128, 128), 8.0, (1.3, 0.4))
    res = _correlate(a, b)
    assert res.counts["failed"] > 0.5 * res.counts["total"]
    note = failure_advice(res, kind=GRID, where="r.h5")
    assert note.startswith(f"note: most points failed ({res.counts['failed']} of {res.counts['total']}")
    assert "peak_ratio_min = 1.0" in note and "show-result r.h5" in note
    assert "--windows" not in note


def _grid_result(flags, *, peak_ratio, correlation, **settings):
    """A correlation result with these flags (``VectorFlag`` bits), peak ratios and peak correlations."""
    flags = np.asarray(flags)
    n = flags.size
    counts = count_vectors(flags)
    table = {"flags": flags, "peak_ratio": np.full(n, peak_ratio), "correlation": np.full(n, correlation)}
    return MethodResult("correlation", np.zeros((n, 2)), np.zeros((n, 2)), (1, n), table,
                        {"window_sizes": [32, 16], "peak_ratio_min": 1.05, "min_correlation": 0.5, **settings},
                        flags == 0, counts=counts)


def test_equal_peaks_advice_names_the_setting_the_correlation_has():
    peak, ok = int(VectorFlag.PEAK), 0
    flags = [peak] * 40 + [peak | int(VectorFlag.DISAGREE)] * 20 + [ok] * 4
    note = failure_advice(_grid_result(flags, peak_ratio=1.0004, correlation=0.85), kind=GRID)
    assert "in 60 windows the second correlation peak is as high as the first (median peak ratio 1.0004" in note
    assert "peak_ratio_min = 1.0 in the [correlation] table" in note
    note = failure_advice(_grid_result(flags, peak_ratio=1.0004, correlation=0.85, pattern="random"), kind=GRID)
    assert 'set pattern = "periodic" in the [correlation] table' in note  # a correlation that judges patterns
    note = failure_advice(_grid_result(flags, peak_ratio=1.0004, correlation=0.85, pattern="periodic"), kind=GRID)
    assert "taken as periodic" in note and "half its pitch" in note
    note = failure_advice(_grid_result(flags, peak_ratio=1.0004, correlation=0.3), kind=GRID)
    assert "do not correlate in 60 windows (median peak correlation 0.30, below min_correlation 0.5)" in note
    note = failure_advice(_grid_result([int(VectorFlag.BORDER)] * 50 + [ok] * 14, peak_ratio=2.0, correlation=0.9),
                          kind=GRID)
    assert "edge of the correlation plane" in note and "--windows 64,32,16" in note
    assert failure_advice(_grid_result([peak] * 30 + [ok] * 34, peak_ratio=1.0, correlation=0.9), kind=GRID) is None


def test_unrelated_images_advice_says_they_do_not_correlate():
    a = _dots_image((128, 128), 5.0, (0, 0), jitter=1.5, seed=3)
    b = _dots_image((128, 128), 5.0, (0, 0), jitter=1.5, seed=4)
    note = failure_advice(_correlate(a, b), kind=GRID)
    assert "do not correlate" in note and "peak_ratio_min = 1.0" not in note


def test_large_displacement_advice_asks_for_larger_first_windows():
    """A random pattern moved 7 px with 16 px first windows: the peaks sit on the plane's edge."""
    a = _dots_image((128, 128), 5.0, (0, 0), jitter=1.5, seed=3)
    b = _dots_image((128, 128), 5.0, (7.0, 0.0), jitter=1.5, seed=3)
    res = _correlate(a, b, window_sizes=(16, 8))
    note = failure_advice(res, kind=GRID)
    assert note is not None, res.counts
    assert "--windows 32,16,8" in note and "peak_ratio_min" not in note


def test_no_advice_when_most_points_were_measured():
    a = _dots_image((128, 128), 5.0, (0, 0), jitter=1.5, seed=3)
    b = _dots_image((128, 128), 5.0, (1.2, 0.3), jitter=1.5, seed=3)
    res = _correlate(a, b)
    assert res.counts["measured"] == res.counts["total"]
    assert failure_advice(res, kind=GRID) is None


def test_tracking_advice_fits_its_failures():
    a = _dots_image((96, 96), 8.0, (0, 0), jitter=1.0, seed=5)
    method = get_method("tracking")
    res, _ = process_pair("tracking", a, a, settings=method.settings({}), device="cpu")
    assert failure_advice(res, kind=DOTS) is None  # the same image twice: all measured
    other = _dots_image((96, 96), 8.0, (0, 0), jitter=1.0, seed=6)
    res, _ = process_pair("tracking", a, other, settings=method.settings({}), device="cpu")
    assert res.counts["measured"] == 0
    assert "the images do not correlate around 156 dots" in failure_advice(res, kind=DOTS)
    xy = np.stack(np.meshgrid(np.arange(4.0, 92, 8), np.arange(4.0, 92, 8)), axis=-1).reshape(-1, 2)
    xy[: 2 * len(xy) // 3] += 500.0  # two thirds of the prior outside the image
    res, _ = process_pair("tracking", a, a, settings=method.settings({}), prior_xy=xy, device="cpu")
    note = failure_advice(res, kind=DOTS)
    assert note is not None and f"puts {2 * len(xy) // 3} dots outside the image" in note, res.counts


def test_unpaired_dots_advice_names_max_displacement():
    """Dots found in the reference image and not paired in the gradient image (status bits as tracking sets
    them): the advice names --max-displacement with its value."""
    found = int(DotStatus.FOUND_REFERENCE)
    status = np.array([found] * 7 + [found | int(DotStatus.FOUND_GRADIENT) | int(DotStatus.MATCHED)] * 3)
    res = MethodResult("tracking", np.zeros((10, 2)), np.full((10, 2), np.nan), None, {"status": status},
                       {"max_displacement": 1.5, "diameter": None}, status == status.max(),
                       counts={"measured": 3, "replaced": 0, "failed": 7, "masked": 0, "total": 10})
    note = failure_advice(res, kind=DOTS, where="r.h5")
    assert note.startswith("note: most points failed (7 of 10; synthbos show-result r.h5 -o FIG.png shows where)")
    assert "7 dots found in the reference image were not paired" in note
    assert "--max-displacement (now 1.5 px)" in note and "--diameter, now measured from the images" in note


# ---------------------------------------------------------------- Ctrl-C on render


def test_in_worker_thread_returns_raises_and_forgets_nothing():
    assert in_worker_thread(np.add, 2, 3) == 5
    with pytest.raises(ZeroDivisionError):
        in_worker_thread(lambda: 1 / 0)
    assert not work_abandoned()


@pytest.mark.slow
def test_ctrl_c_on_render_stops_at_once_and_says_nothing_was_written(tmp_path):
    """A render's Warp launch on the CPU takes tens of seconds; a Ctrl-C in it ends the command in < 2 s."""
    out = tmp_path / "pair.h5"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-u", "-m", "synthbos", "render", "-o", str(out), "-q", "--device",
                             "cpu"], cwd=tmp_path, env=env, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)
    assert proc.stdout.readline().startswith("device: cpu")  # the render starts after this line
    time.sleep(1.5)
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    seconds = time.monotonic() - t0
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("Warp")]
    assert proc.returncode == 130, err
    assert seconds < 2.0, seconds
    assert lines == ["synthbos: interrupted; nothing was written (the pair file is written whole at the end); "
                     "re-run to render it again"], err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_process_prints_the_advice_and_show_result_writes_the_name_asked_for(tmp_path, capsys):
    import tifffile

    for name, seed in (("a.tif", 3), ("b.tif", 4)):  # two unrelated random patterns
        img = _dots_image((128, 128), 5.0, (0, 0), jitter=1.5, seed=seed)
        tifffile.imwrite(tmp_path / name, (img * 20000 + 1000).astype(np.uint16))
    argv = ["process", "--reference", str(tmp_path / "a.tif"), "--gradient", str(tmp_path / "b.tif"), "--method",
            "correlation", "--device", "cpu"]
    assert main([*argv, "-o", str(tmp_path / "r.h5")]) == 1  # nothing measured: a warning that says why
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("synthbos: warning: nothing was measured in")
    # all (or all but a chance one) of the 64 final windows
    assert re.search(r"; the two images do not correlate in 6[34] windows", err[0]), err[0]
    # some windows measured: a note on standard output, left out with -q
    for name, seed in (("a.tif", 3), ("b.tif", 3)):
        img = _dots_image((128, 128), 5.0, (0, 0), jitter=1.5, seed=seed)
        img[:, :80] = _dots_image((128, 80), 5.0, (0, 0), jitter=1.5, seed=seed + (name == "b.tif"))
        tifffile.imwrite(tmp_path / name, (img * 20000 + 1000).astype(np.uint16))
    assert main([*argv, "-o", str(tmp_path / "s.h5")]) == 0
    out = capsys.readouterr().out
    assert "note: most points failed" in out and "the two images do not correlate" in out
    assert main([*argv, "-o", str(tmp_path / "q.h5"), "-q"]) == 0
    assert "note:" not in capsys.readouterr().out
    fig = tmp_path / "x.jpg"
    assert main(["show-result", str(tmp_path / "r.h5"), "-o", str(fig)]) == 0
    assert capsys.readouterr().out.splitlines()[0] == f"wrote {fig}"
    assert fig.read_bytes()[:2] == b"\xff\xd8"  # a JPEG, under the name asked for
    assert not (tmp_path / "x.jpg.png").exists() and not (tmp_path / "x.png").exists()


def test_calibrate_finds_dark_dots_by_itself_and_invert_false_keeps_them_dark(tmp_path, capsys):
    """A grid of dark dots on a bright background (paper printed with black dots): --invert auto (the default)
    makes them bright, as process does, and finds the grid the bright image gives; --invert false leaves them
    dark, and no grid is found."""
    import tifffile
    from synthbos.raytrace.dots import draw_dots

    xy = np.stack(np.meshgrid(np.arange(7.5, 128, 15), np.arange(7.5, 128, 15)), axis=-1).reshape(-1, 2)
    bright = draw_dots((128, 128), xy, 3.0) + 0.01 * np.random.default_rng(2).standard_normal((128, 128))
    for name, img in (("bright", bright), ("dark", 1.0 - bright)):
        tifffile.imwrite(tmp_path / f"{name}.tif", img.astype(np.float32))
        assert main(["calibrate", "--reference", str(tmp_path / f"{name}.tif"), "--grid", "2.0", "-o",
                     str(tmp_path / f"{name}.csv")]) == 0
    dark, bright = (np.loadtxt(tmp_path / f"{n}.csv", delimiter=",", skiprows=1) for n in ("dark", "bright"))
    assert len(dark) > 50
    # the same grid: the dark dots' contrast is the bright image's negated, so only the noise's part differs
    np.testing.assert_allclose(dark, bright, atol=0.05)
    assert main(["calibrate", "--reference", str(tmp_path / "dark.tif"), "--grid", "2.0", "--invert", "false",
                 "-o", str(tmp_path / "kept.csv")]) == 2
    assert not (tmp_path / "kept.csv").exists()
