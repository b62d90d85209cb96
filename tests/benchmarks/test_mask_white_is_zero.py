"""Issue 28: a mask TIFF stored WhiteIsZero (PhotometricInterpretation 0, tifffile's MINISWHITE) is read the
right way up, and ``process`` says what the mask read left out. Before, it was read inverted, silently."""

import json

import h5py
import imageio.v3 as iio
import numpy as np
import pytest
import tifffile
from numpy.testing import assert_array_equal
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.process import load_image, load_mask
from synthbos.raytrace.dots import draw_dots

SHAPE = (128, 128)


def _white_measured(left_excluded_px=40):
    m = np.ones(SHAPE, dtype=bool)  # white (True): measured
    m[:, :left_excluded_px] = False
    return m


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, bool])
def test_white_is_zero_mask_reads_as_its_picture(tmp_path, dtype):
    white = _white_measured()
    iio.imwrite(tmp_path / "mask.png", np.where(white, 255, 0).astype(np.uint8))
    top = 1 if dtype is bool else np.iinfo(dtype).max
    stored = np.where(white, 0, top).astype(dtype)  # WhiteIsZero: white is stored as 0
    tifffile.imwrite(tmp_path / "mask.tif", stored, photometric="miniswhite")
    with tifffile.TiffFile(tmp_path / "mask.tif") as tif:
        assert tif.pages[0].photometric == tifffile.PHOTOMETRIC.MINISWHITE
    for excludes in ("dark", "bright"):
        notes = []
        got = load_mask(tmp_path / "mask.tif", SHAPE, excludes=excludes, notes=notes)
        assert_array_equal(got, load_mask(tmp_path / "mask.png", SHAPE, excludes=excludes))
        assert_array_equal(got, ~white if excludes == "dark" else white)
        assert len(notes) == 2 and "WhiteIsZero" in notes[0], notes
        n = int((~white).sum()) if excludes == "dark" else int(white.sum())
        assert f"{n} of {white.size} pixels" in notes[1], notes


def test_white_is_zero_image_values(tmp_path):
    counts = np.random.default_rng(0).integers(0, 4096, SHAPE).astype(np.uint16)
    tifffile.imwrite(tmp_path / "a.tif", counts, photometric="miniswhite")
    tifffile.imwrite(tmp_path / "b.tif", counts, photometric="minisblack")
    tifffile.imwrite(tmp_path / "c.tif", counts.astype(np.float32) / 4096, photometric="miniswhite")
    notes = []
    assert_array_equal(load_image(tmp_path / "a.tif", notes=notes), 65535.0 - counts)
    assert_array_equal(load_image(tmp_path / "b.tif", notes=notes), counts)
    np.testing.assert_allclose(load_image(tmp_path / "c.tif"), 1.0 - counts / 4096, atol=1e-7)
    assert len(notes) == 1 and "a.tif" in notes[0]


def test_process_honours_a_white_is_zero_mask(tmp_path, capsys):
    rng = np.random.default_rng(1)
    xy = rng.uniform(-4, 132, (500, 2))
    for name, shift in (("a.tif", (0.0, 0.0)), ("b.tif", (1.2, -0.6))):
        img = 100 + 3000 * draw_dots(SHAPE, xy + shift, 3.0)
        tifffile.imwrite(tmp_path / name, img.astype(np.uint16))
    white = _white_measured(48)
    iio.imwrite(tmp_path / "mask.png", np.where(white, 255, 0).astype(np.uint8))
    tifffile.imwrite(tmp_path / "mask.tif", np.where(white, 0, 255).astype(np.uint8), photometric="miniswhite")
    counts = {}
    for mask in ("mask.png", "mask.tif"):
        out = tmp_path / f"{mask}.h5"
        assert main(["process", "--reference", str(tmp_path / "a.tif"), "--gradient", str(tmp_path / "b.tif"),
                     "--method", "correlation", "--mask", str(tmp_path / mask), "-o", str(out)]) == 0
        printed = capsys.readouterr().out
        assert f"mask {tmp_path / mask}: {int((~white).sum())} of {white.size} pixels (37.5%) left out" in printed
        assert ("WhiteIsZero" in printed) == mask.endswith(".tif"), printed
        with h5py.File(out) as f:
            counts[mask] = json.loads(f.attrs["counts"])
            masked = (f["flags"][()] & 8) != 0
            x = f["x"][()]
    print(counts)
    assert counts["mask.tif"] == counts["mask.png"] and counts["mask.tif"]["masked"] > 0
    assert not masked[x > 56].any()  # the measured side (white) is measured
