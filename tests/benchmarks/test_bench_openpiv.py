"""benchmarks/bench_openpiv.py on a drawn PIV triple (images and a Middlebury .flo truth) and a BOS pair."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from synthbos.benchmarks import bench_openpiv
from synthbos.raytrace.dots import draw_dots

from synthbos import SynthbosError

SHIFT = (1.3, -0.7)


def write_triple(folder, name, shape=(128, 160)):
    import tifffile

    rng = np.random.default_rng(3)
    h, w = shape
    xy = rng.uniform(-8, [w + 8, h + 8], size=(int(20 / 32**2 * (h + 16) * (w + 16)), 2))
    for tag, d in (("img1", 0.0), ("img2", 1.0)):
        img = draw_dots(shape, xy + d * np.asarray(SHIFT), 3.0)
        tifffile.imwrite(folder / f"{name}_{tag}.tif", (img / img.max() * 250).astype(np.uint8))
    flow = np.empty((h, w, 2), dtype="<f4")
    flow[..., 0], flow[..., 1] = SHIFT
    with open(folder / f"{name}_flow.flo", "wb") as f:
        np.array([bench_openpiv.FLO_MAGIC], "<f4").tofile(f)
        np.array([w, h], "<i4").tofile(f)
        flow.tofile(f)
    return flow


def test_flo_reader_and_truth_sampling(tmp_path):
    flow = write_triple(tmp_path, "uniform_00001")
    assert_allclose(bench_openpiv.read_flo(tmp_path / "uniform_00001_flow.flo"), flow)
    ramp = np.stack(np.meshgrid(np.arange(8.0), np.arange(6.0)), axis=-1)  # u = x, v = y
    u, v = bench_openpiv.truth_at(ramp, np.array([[2.25, 6.5]]), np.array([[1.5, 3.0]]))
    assert_allclose(u, [[2.25, 6.5]]) and assert_allclose(v, [[1.5, 3.0]])
    (tmp_path / "bad.flo").write_bytes(b"nope")
    with pytest.raises(SynthbosError, match="not a Middlebury"):
        bench_openpiv.read_flo(tmp_path / "bad.flo")


def test_rows_of_a_drawn_pair(tmp_path, capsys):
    pytest.importorskip("openpiv")
    write_triple(tmp_path, "SQG_00009")
    (name, img1, img2, flo), = bench_openpiv.piv_pairs(tmp_path)
    row = bench_openpiv.piv_row(name, img1, img2, flo, 1)
    assert row["turbulent"]
    for key in ("synthbos", "openpiv"):
        assert row[key]["all"] < 0.1 and row[key]["fraction"] > 0.9 and row[key]["seconds"] > 0
    bos = bench_openpiv.bos_row(img1, img2, 1)
    assert bos["pattern"] == "random" and bos["compared"] > 20 and bos["rms"] < 0.1
    assert bench_openpiv.main(["--piv", str(tmp_path), "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "| SQG_00009 |" in out and "<= OpenPIV's on" in out
