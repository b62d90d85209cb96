"""Issue 28/29: ``synthbos calibrate --grid`` on drawn real-like grid TIFFs (12-bit, PackBits): dark dots found
without ``--invert``, a WhiteIsZero TIFF read the right way up, one clear line (exit 2, nothing written) when
the image holds no grid, naming ``--invert`` and what was found."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
from scipy.spatial import cKDTree
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.process import read_dots_csv
from synthbos.raytrace.dots import draw_dots

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tracking"))
from _gridimage import real_like_grid

SHAPE = (384, 448)


def _calibrate(path, out, *extra):
    return main(["calibrate", "--reference", str(path), "--grid", "1.5", "-o", str(out), *extra])


def _check_dots(out, xy):
    """Every drawn dot away from the edge has a predicted dot within 0.05 px."""
    got = read_dots_csv(out)
    dist, _ = cKDTree(got).query(xy)
    inner = (xy[:, 0] > 3) & (xy[:, 0] < SHAPE[1] - 4) & (xy[:, 1] > 3) & (xy[:, 1] < SHAPE[0] - 4)
    assert dist[inner].max() < 0.05, dist[inner].max()
    return got


@pytest.mark.parametrize("dark", [False, True])
def test_grid_of_either_polarity_found_without_invert(tmp_path, capsys, dark):
    img, xy, _ = real_like_grid(SHAPE, 8.0, seed=11, dark=dark, n_missing=10, n_spurious=10)
    tifffile.imwrite(tmp_path / "grid.tif", img, compression="packbits")
    out, mapping = tmp_path / "dots.csv", tmp_path / "map.json"
    assert _calibrate(tmp_path / "grid.tif", out, "--mapping-out", str(mapping)) == 0
    printed = capsys.readouterr().out
    assert f"{'dark' if dark else 'bright'} blobs on the grid fitted" in printed, printed
    _check_dots(out, xy)
    assert json.loads(mapping.read_text())["dots"] == ("dark on bright" if dark else "bright on dark")
    if dark:  # --invert asks for what the image shows: the same result
        out2 = tmp_path / "dots2.csv"
        assert _calibrate(tmp_path / "grid.tif", out2, "--invert") == 0
        np.testing.assert_allclose(read_dots_csv(out2), read_dots_csv(out))


def test_white_is_zero_grid_read_the_right_way_up(tmp_path, capsys):
    img, xy, _ = real_like_grid(SHAPE, 8.0, seed=12, n_missing=10, n_spurious=10)
    # stored WhiteIsZero: the file holds 65535 - counts; a reader that ignores the tag sees dark dots
    tifffile.imwrite(tmp_path / "grid.tif", (65535 - img).astype(np.uint16), photometric="miniswhite")
    out = tmp_path / "dots.csv"
    assert _calibrate(tmp_path / "grid.tif", out) == 0
    printed = capsys.readouterr().out
    assert "WhiteIsZero" in printed and "bright blobs" in printed, printed
    _check_dots(out, xy)


def test_no_grid_one_line_naming_invert_unless_blank_nothing_written(tmp_path, capsys):
    rng = np.random.default_rng(13)
    random_dots = 100 + 3000 * draw_dots(SHAPE, rng.uniform(0, 448, (1200, 2)), 4.0) + rng.normal(0, 5, SHAPE)
    bright_grid, _, _ = real_like_grid(SHAPE, 8.0, seed=14, n_missing=0, n_spurious=0)
    images = {
        "random.tif": (random_dots, [], r"no regular dot grid .*\d+ bright blobs, \d on one lattice"),
        "blank.tif": (np.full(SHAPE, 800.0), [], "the calibration image is blank \\(every pixel 800\\): no dot grid"),
        "bright.tif": (bright_grid, ["--invert"], "dark blobs?, .* --invert was given: leave it out"),
    }
    for name, (image, extra, message) in images.items():
        tifffile.imwrite(tmp_path / name, np.clip(image, 0, 4095).astype(np.uint16), compression="packbits")
        out, mapping = tmp_path / "dots.csv", tmp_path / "map.json"
        assert _calibrate(tmp_path / name, out, "--mapping-out", str(mapping), *extra) == 2
        err = capsys.readouterr().err.strip()
        print(err)
        assert "\n" not in err and len(err) <= 200 and ("--invert" in err) == (name != "blank.tif"), err
        assert __import__("re").search(message, err), err
        assert not out.exists() and not mapping.exists()
