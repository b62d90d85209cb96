"""``synthbos process`` on camera images drawn here: configuration, flags, masks, inversion, image formats."""

import json

import h5py
import numpy as np
import pytest
from numpy.testing import assert_allclose
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.process import decide_invert, load_image, load_mask, process_settings
from synthbos.correlation import CorrelationSettings
from synthbos.raytrace.dots import draw_dots

SHIFT = (1.3, -0.7)
SHAPE = (128, 128)


def _xy(seed=0, shape=SHAPE, spacing=7.0):
    """Dots on a jittered lattice (well separated, so tracking finds every one)."""
    rng = np.random.default_rng(seed)
    g = np.arange(-spacing, shape[1] + spacing, spacing)
    x, y = np.meshgrid(g, np.arange(-spacing, shape[0] + spacing, spacing))
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    return xy + rng.uniform(-1.5, 1.5, xy.shape)


def _pair(seed=0, shift=SHIFT, shape=SHAPE):
    xy = _xy(seed, shape)
    return draw_dots(shape, xy, 3.0), draw_dots(shape, xy + np.asarray(shift), 3.0)


@pytest.fixture
def images(tmp_path):
    import tifffile

    a, b = _pair()
    s = 4000 / max(a.max(), b.max())
    tifffile.imwrite(tmp_path / "a.tif", (a * s + 100).astype(np.uint16))
    tifffile.imwrite(tmp_path / "b.tif", (b * s + 100).astype(np.uint16))
    return tmp_path / "a.tif", tmp_path / "b.tif"


def _run(images, out, *extra, method="correlation"):
    return main(["process", "--reference", str(images[0]), "--gradient", str(images[1]),
                 "--method", method, "-o", str(out), *extra])


def test_config_keys_take_effect_and_are_written(tmp_path, images, capsys):
    cfg = tmp_path / "process.toml"
    cfg.write_text("[correlation]\nwindow_sizes = [64, 32]\noverlaps = 0.5\nmin_correlation = 0.4\n"
                   "[tracking]\ndiameter = 3.0\n[image]\ninvert = false\n")
    out = tmp_path / "r.h5"
    assert _run(images, out, "--config", str(cfg)) == 0
    printed = capsys.readouterr().out
    assert "49 vectors: 49 measured, 0 replaced, 0 failed, 0 masked" in printed
    with h5py.File(out) as f:
        assert f["u"].shape == (7, 7)  # 32 px windows every 16 px in 128 px
        s = json.loads(f.attrs["settings"])
        assert s["window_sizes"] == [64, 32] and s["overlaps"] == [0.5, 0.5] and s["min_correlation"] == 0.4
        assert json.loads(f.attrs["image"])["invert"] is False
        assert "window_sizes = [64, 32]" in f.attrs["config"]
        assert json.loads(f.attrs["counts"])["measured"] == 49
        bits = json.loads(f["flags"].attrs["flag_bits"])
        assert bits["1"]["name"] == "MEDIAN" and "median test" in bits["1"]["description"]
        assert bits["32"]["name"] == "ISOLATED" and f["u"].attrs["units"] == "px"
        assert f["correlation"].attrs["units"] == "1"
        assert_allclose(f["u"][()], SHIFT[0], atol=0.05)
        assert_allclose(f["v"][()], SHIFT[1], atol=0.05)
    # flags override the file
    assert _run(images, out, "--config", str(cfg), "--windows", "32,16", "--overlap", "0") == 0
    with h5py.File(out) as f:
        assert f["u"].shape == (8, 8)
        assert json.loads(f.attrs["settings"])["window_sizes"] == [32, 16]


def test_tracking_flags_take_effect(tmp_path, images):
    out = tmp_path / "t.h5"
    assert _run(images, out, "--diameter", "3.0", "--max-displacement", "4", method="tracking-cc") == 0
    with h5py.File(out) as f:
        s = json.loads(f.attrs["settings"])
        assert s["diameter"] == 3.0 and s["max_displacement"] == 4.0
        ok = np.isfinite(f["dots/u"][()])
        assert ok.mean() > 0.7
        assert np.median(np.abs(f["dots/u"][()][ok] - SHIFT[0])) < 0.05


@pytest.mark.parametrize(
    ("text", "extra", "message"),
    [
        ("[correlation]\nwindow_size = [32]\n", [], "unknown correlation setting"),
        ("[correlation]\noverlaps = 1.5\n", [], "overlap"),
        ("[tracking]\ndiameters = 3\n", [], "unknown tracking"),
        ("[imag]\n", [], "unknown table"),
        ("[image]\ninvert = 'maybe'\n", [], "invert"),
        ("[image]\nmask_excludes = 'white'\n", [], "mask_excludes"),
        ("", ["--diameter", "3"], "--diameter is a tracking setting"),
        ("", ["--windows", "32,x"], "--windows"),
        ("", ["--mask", "nope.png"], "does not exist"),
    ],
)
def test_bad_settings_exit_2_without_output(tmp_path, images, capsys, text, extra, message):
    cfg = tmp_path / "p.toml"
    cfg.write_text(text)
    out = tmp_path / "r.h5"
    assert _run(images, out, "--config", str(cfg), *extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()


def _mask_png(path, *, left_excluded_px, polarity):
    import imageio.v3 as iio

    m = np.full(SHAPE, 255, np.uint8)  # white: measured
    m[:, :left_excluded_px] = 0
    if polarity == "bright":
        m = 255 - m
    iio.imwrite(path, m)


@pytest.mark.parametrize("polarity", ["dark", "bright"])
def test_mask_is_honoured_by_correlation(tmp_path, images, polarity):
    _mask_png(tmp_path / "m.png", left_excluded_px=48, polarity=polarity)
    out = tmp_path / "r.h5"
    assert _run(images, out, "--mask", str(tmp_path / "m.png"), "--mask-excludes", polarity) == 0
    with h5py.File(out) as f:
        x, u, flags = f["x"][()], f["u"][()], f["flags"][()]
        counts = json.loads(f.attrs["counts"])
        assert json.loads(f.attrs["image"])["mask_excludes"] == polarity
    masked = (flags & 8) != 0
    assert_allclose(masked, np.broadcast_to(x < 48 - 8, x.shape))  # windows more than half masked
    assert np.isnan(u[masked]).all() and counts["masked"] == masked.sum() == 24
    assert_allclose(u[~masked], SHIFT[0], atol=0.05)


def test_mask_is_honoured_by_tracking(tmp_path, images):
    _mask_png(tmp_path / "m.png", left_excluded_px=48, polarity="dark")
    out = tmp_path / "t.h5"
    assert _run(images, out, "--mask", str(tmp_path / "m.png"), method="tracking") == 0
    with h5py.File(out) as f:
        x, u, masked = f["dots/x"][()], f["dots/u"][()], f["dots/masked"][()]
        counts = json.loads(f.attrs["counts"])
    # Without a prior, dots inside the excluded area are never found; those that touch its edge are
    # flagged and not measured (track_pair's MASKED bit); no measured dot lies in the excluded area.
    measured = np.isfinite(u)
    assert not (measured & (x < 48)).any()
    assert np.isnan(u[masked]).all() and counts["masked"] == int(masked.sum()) > 0
    assert (np.abs(x[masked] - 48) < 4).all()
    assert measured[x > 52].mean() > 0.7


def test_load_mask_polarity_and_errors(tmp_path):
    _mask_png(tmp_path / "m.png", left_excluded_px=10, polarity="dark")
    dark = load_mask(tmp_path / "m.png", SHAPE, excludes="dark")
    assert dark[:, :10].all() and not dark[:, 10:].any()
    assert_allclose(load_mask(tmp_path / "m.png", SHAPE, excludes="bright"), ~dark)
    from synthbos import SynthbosError

    with pytest.raises(SynthbosError, match="shape"):
        load_mask(tmp_path / "m.png", (64, 64))


@pytest.mark.parametrize("method", ["correlation", "tracking-cc"])
def test_dark_dots_give_the_result_of_bright_dots(tmp_path, method):
    import tifffile

    a, b = _pair(seed=3)
    s = 3000 / max(a.max(), b.max())
    bright = [(x * s + 200).astype(np.uint16) for x in (a, b)]
    dark = [(3500 - x * s).astype(np.uint16) for x in (a, b)]
    res = {}
    for name, (ra, rb) in (("bright", bright), ("dark", dark)):
        tifffile.imwrite(tmp_path / f"{name}_a.tif", ra)
        tifffile.imwrite(tmp_path / f"{name}_b.tif", rb)
        out = tmp_path / f"{name}.h5"
        assert _run((tmp_path / f"{name}_a.tif", tmp_path / f"{name}_b.tif"), out, method=method) == 0
        with h5py.File(out) as f:
            key = "u" if method == "correlation" else "dots/u"
            res[name] = f[key][()]
            res[name + "_image"] = json.loads(f.attrs["image"])
    assert res["dark_image"]["inverted"] and not res["bright_image"]["inverted"]
    assert res["bright"].shape == res["dark"].shape
    assert_allclose(res["dark"], res["bright"], atol=1e-3, equal_nan=True)
    assert np.isfinite(res["bright"]).mean() > 0.7


def test_decide_invert():
    a, _ = _pair()
    assert decide_invert(a)[0] is False
    assert decide_invert(a.max() - a)[0] is True
    assert decide_invert(a, invert=True) == (True, "set by the user")


@pytest.mark.parametrize(
    ("kind", "compression"),
    [("uint8", None), ("uint12", "lzw"), ("uint16", "lzw"), ("uint16", "zlib"), ("float32", None),
     ("float64", "lzw")],
)
def test_tiff_formats_read(tmp_path, kind, compression):
    import tifffile

    a, _ = _pair()
    full = {"uint8": 255, "uint12": 4095, "uint16": 65535}.get(kind, 1.0)
    dtype = np.uint16 if kind == "uint12" else np.dtype(kind)
    img = (a / a.max() * full).astype(dtype)
    tifffile.imwrite(tmp_path / "i.tif", img, compression=compression)
    back = load_image(tmp_path / "i.tif")
    assert back.dtype == np.float64 and back.shape == SHAPE
    assert_allclose(back, img.astype(np.float64))


def test_colour_image_becomes_luminance_with_a_note(tmp_path):
    import tifffile

    a, _ = _pair()
    rgb = np.stack([a, a, a], axis=-1).astype(np.float32)
    tifffile.imwrite(tmp_path / "c.tif", rgb, photometric="rgb")
    notes = []
    back = load_image(tmp_path / "c.tif", notes=notes)
    assert_allclose(back, a, rtol=1e-5, atol=1e-6)
    assert len(notes) == 1 and "luminance" in notes[0]


def test_process_settings_defaults():
    settings, options = process_settings("correlation")
    assert settings == CorrelationSettings() and options.invert == "auto" and options.mask is None


def test_nothing_measured_exits_1_and_says_so(tmp_path, capsys):
    import tifffile

    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        tifffile.imwrite(tmp_path / f"{name}.tif", (rng.random(SHAPE) * 4000).astype(np.uint16))
    out = tmp_path / "r.h5"
    assert _run((tmp_path / "a.tif", tmp_path / "b.tif"), out) == 1
    captured = capsys.readouterr()
    assert "64 vectors: 0 measured, 0 replaced, 64 failed, 0 masked" in captured.out
    assert "nothing was measured" in captured.err
    with h5py.File(out) as f:  # the result is kept: its flags say why
        assert json.loads(f.attrs["counts"])["failed"] == 64


def test_regular_grid_judged_random_names_the_pattern_setting(tmp_path, capsys):
    """A regular dot grid (pitch 8 px) forced to pattern = "random" fails everywhere; the warning names
    the setting that measures it, and that setting (the default, auto, finds it too) does."""
    import tifffile
    from synthbos.raytrace.dots import draw_dots

    g = np.arange(-8.0, 80.0, 8.0) + 0.3
    xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    for name, shift in (("a", 0.0), ("b", 1.3)):
        tifffile.imwrite(tmp_path / f"{name}.tif", (draw_dots((64, 64), xy + shift, 3.0) * 4000).astype(np.uint16))
    cfg = tmp_path / "random.toml"
    cfg.write_text('[correlation]\npattern = "random"\n')
    images = (tmp_path / "a.tif", tmp_path / "b.tif")
    assert _run(images, tmp_path / "r.h5", "--config", str(cfg)) == 1
    assert 'pattern = "periodic"' in capsys.readouterr().err
    assert _run(images, tmp_path / "d.h5") == 0
    with h5py.File(tmp_path / "d.h5") as f:
        assert np.all(f["flags"][()] == 0)
        assert_allclose(f["u"][()], 1.3, atol=0.02)


def test_mostly_failed_gives_a_hint(tmp_path, capsys):
    import tifffile

    a, b = _pair(shift=(20.0, 0.0))
    for name, img in (("a", a), ("b", b)):
        tifffile.imwrite(tmp_path / f"{name}.tif", (img * 1000).astype(np.uint16))
    out = tmp_path / "r.h5"
    code = _run((tmp_path / "a.tif", tmp_path / "b.tif"), out)
    printed = capsys.readouterr().out
    assert code in (0, 1)
    assert code == 1 or "--windows 64,32,16" in printed
    assert _run((tmp_path / "a.tif", tmp_path / "b.tif"), out, "--windows", "64,32,16") == 0
    with h5py.File(out) as f:
        ok = f["flags"][()] == 0
        assert ok.mean() > 0.9
        assert_allclose(f["u"][()][ok], 20.0, atol=0.1)  # edge windows lose 20 px of their dots
