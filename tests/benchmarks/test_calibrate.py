"""``synthbos calibrate``: grid image -> dots file (+ mapping), mapping + target -> dots file, bad input."""

import json
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
from numpy.testing import assert_allclose
from scipy.spatial import cKDTree
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.process import read_dots_csv
from synthbos.raytrace.dots import draw_dots

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tracking"))
from _synth import smooth_displacement

SHAPE = (192, 224)
SPACING = 2.5  # mm


def to_image(t):
    """mm -> px: 6.1 px/mm, a 4 degree rotation, quadratic distortion."""
    c, s = np.cos(np.radians(4.0)), np.sin(np.radians(4.0))
    x, y = t[:, 0], t[:, 1]
    return np.stack(
        [112.2 + 6.1 * (c * x - s * y) + 0.012 * x**2, 95.4 + 6.0 * (s * x + c * y) - 0.01 * x * y + 0.008 * y**2],
        axis=1,
    )


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    folder = tmp_path_factory.mktemp("calib")
    rng = np.random.default_rng(50)
    gi, gj = np.meshgrid(np.arange(-20, 21), np.arange(-20, 21), indexing="ij")
    px = to_image(np.stack([gi.ravel(), gj.ravel()], axis=1) * SPACING)
    px = px[(px[:, 0] > -6) & (px[:, 0] < SHAPE[1] + 6) & (px[:, 1] > -6) & (px[:, 1] < SHAPE[0] + 6)]
    img = draw_dots(SHAPE, px, 3.0) + 0.01 * rng.standard_normal(SHAPE)
    path = folder / "grid.tif"
    tifffile.imwrite(path, img.astype(np.float32))
    return path, px


def test_calibrate_grid_writes_every_dot_and_the_mapping(tmp_path, grid, capsys):
    path, every = grid
    dots, mapping = tmp_path / "dots.csv", tmp_path / "map.json"
    assert (
        main(
            [
                "calibrate",
                "--reference",
                str(path),
                "--grid",
                str(SPACING),
                "-o",
                str(dots),
                "--mapping-out",
                str(mapping),
            ]
        )
        == 0
    )
    print(capsys.readouterr().out)
    xy = read_dots_csv(dots)
    assert dots.read_text().startswith("x,y\n")
    dist, idx = cKDTree(every).query(xy)
    truth = every[idx]
    print(f"calibrate --grid: {len(xy)} dots, prediction error max {dist.max():.4f} px")
    assert dist.max() < 0.05 and len(np.unique(idx)) == len(xy)
    # every dot inside the image is predicted (the edge is ambiguous within the prediction error)
    m = 0.05
    x, y = every[:, 0], every[:, 1]
    inside = (x >= m) & (x <= SHAPE[1] - 1 - m) & (y >= m) & (y <= SHAPE[0] - 1 - m)
    assert np.isin(np.flatnonzero(inside), idx).all()
    data = json.loads(mapping.read_text(encoding="utf-8"))
    assert data["format"] == "synthbos-soloff-mapping" and data["target_unit"] == "mm"
    assert data["residual_rms_px"] < 0.05 and data["image_shape"] == list(SHAPE)

    # the dots file drives tracking (synthbos process) to full yield
    rng = np.random.default_rng(51)
    disp = smooth_displacement(truth, SHAPE, 1.0)
    ref = draw_dots(SHAPE, truth, 3.0) + 0.01 * rng.standard_normal(SHAPE)
    grad = draw_dots(SHAPE, truth + disp, 3.0) + 0.01 * rng.standard_normal(SHAPE)
    tifffile.imwrite(tmp_path / "ref.tif", ref.astype(np.float32))
    tifffile.imwrite(tmp_path / "grad.tif", grad.astype(np.float32))
    out = tmp_path / "res.h5"
    assert (
        main(
            [
                "process",
                "--method",
                "tracking-cc",
                "--reference",
                str(tmp_path / "ref.tif"),
                "--gradient",
                str(tmp_path / "grad.tif"),
                "--dots",
                str(dots),
                "-o",
                str(out),
            ]
        )
        == 0
    )
    with h5py.File(out) as f:
        u, v = f["dots/u"][()], f["dots/v"][()]
    ok = np.isfinite(u)
    e = np.hypot(u - disp[:, 0], v - disp[:, 1])[ok]
    # full yield, but for dots cut by the image edge (DotStatus.EDGE_CUT: e^-2 disks past the edge by amounts
    # that differ by over 0.25 px, or a centre within d / 4 of the edge)
    def overshoot(p):
        lo, hi = 1.5 - (p + 0.5), p + 1.5 - (np.array(SHAPE[::-1]) - 0.5)
        return np.maximum(np.maximum(lo, hi), 0.0)

    o1, o2 = overshoot(truth), overshoot(truth + disp)
    edge = ((np.abs(o1 - o2) > 0.2) | (np.maximum(o1, o2) > 0.7)).any(axis=1)
    rms = np.sqrt(np.mean(e**2))
    print(f"tracking with it: {ok.sum()} of {len(ok)} dots ({edge.sum()} cut by the edge), rms {rms:.4f} px")
    assert ok[~edge].all()
    assert np.sqrt(np.mean(e**2)) < 0.03

    # a pattern known in mm, through the saved mapping
    target = tmp_path / "target.csv"
    pattern = np.random.default_rng(52).uniform([-12, -10], [12, 10], (50, 2))
    target.write_text("x_mm,y_mm\n" + "".join(f"{a},{b}\n" for a, b in pattern), encoding="utf-8")
    dots2 = tmp_path / "pattern_dots.csv"
    assert main(["calibrate", "--mapping", str(mapping), "--target", str(target), "-o", str(dots2)]) == 0
    # node (0, 0) of the grid frame is the dot nearest the image centre
    centre = np.array([(SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2])
    gi, gj = np.meshgrid(np.arange(-20, 21), np.arange(-20, 21), indexing="ij")
    nodes = np.stack([gi.ravel(), gj.ravel()], axis=1) * SPACING
    origin = nodes[np.argmin(np.hypot(*(to_image(nodes) - centre).T))]
    assert_allclose(read_dots_csv(dots2), to_image(pattern + origin), atol=0.05)


def test_calibrate_bad_input_one_line_exit_2(tmp_path, grid, capsys):
    path, _ = grid
    noise = tmp_path / "noise.tif"
    tifffile.imwrite(noise, np.random.default_rng(53).random((64, 64)).astype(np.float32))
    latin = tmp_path / "latin.csv"
    latin.write_bytes("x_mm,y_mm\n1,2 \xb0\n".encode("latin-1"))
    header = tmp_path / "header.csv"
    header.write_text("x,y\n1,2\n")
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    good_map = tmp_path / "map.json"
    assert (
        main(
            [
                "calibrate",
                "--reference",
                str(path),
                "--grid",
                "2",
                "-o",
                str(tmp_path / "d.csv"),
                "--mapping-out",
                str(good_map),
            ]
        )
        == 0
    )
    capsys.readouterr()
    out = tmp_path / "out.csv"
    cases = [
        (["--reference", str(noise), "--grid", "2"], "no regular dot grid"),
        (["--reference", str(tmp_path / "missing.tif"), "--grid", "2"], "does not exist"),
        (["--reference", str(path), "--grid", "-1"], "--grid (the grid spacing, mm) must be > 0"),
        (["--mapping", str(good_map), "--target", str(latin)], "not UTF-8"),
        (["--mapping", str(good_map), "--target", str(header)], "x_mm,y_mm"),
        (["--mapping", str(bad_json), "--target", str(header)], "not valid JSON"),
        (["--mapping", str(header), "--target", str(header)], "not valid JSON"),
        (["--mapping", str(good_map)], "--target"),
        (["--grid", "2"], "--reference"),
    ]
    for args, text in cases:
        assert main(["calibrate", *args, "-o", str(out)]) == 2, args
        err = capsys.readouterr().err.strip()
        assert text in err and "\n" not in err, (args, err)
        assert not out.exists()
    assert not list(tmp_path.glob(".*tmp"))
