"""``synthbos show-result``: the figure is written and the summary states the counts of the result file."""

import numpy as np
import pytest
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.show_result import read_result


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    import imageio.v3 as iio
    import tifffile
    from synthbos.raytrace.dots import draw_dots

    d = tmp_path_factory.mktemp("img")
    rng = np.random.default_rng(5)
    xy = rng.uniform(-10, 138, size=(330, 2))
    a, b = draw_dots((128, 128), xy, 3.0), draw_dots((128, 128), xy + np.array([0.8, 0.5]), 3.0)
    b[48:80, 64:96] = rng.random((32, 32)) * b.max()  # a patch that fails
    tifffile.imwrite(d / "a.tif", (a * 1000).astype(np.uint16))
    tifffile.imwrite(d / "b.tif", (b * 1000).astype(np.uint16))
    m = np.full((128, 128), 255, np.uint8)
    m[:, :24] = 0
    iio.imwrite(d / "m.png", m)
    return d


@pytest.mark.parametrize("method", ["correlation", "tracking"])
def test_show_result_draws_and_summarises(images, tmp_path, capsys, method):
    res_file, fig = tmp_path / "r.h5", tmp_path / "fig.png"
    assert main(["process", "--reference", str(images / "a.tif"), "--gradient", str(images / "b.tif"),
                 "--method", method, "--mask", str(images / "m.png"), "-o", str(res_file)]) == 0
    capsys.readouterr()
    assert main(["show-result", str(res_file), "-o", str(fig)]) == 0
    printed = capsys.readouterr().out
    assert fig.stat().st_size > 10_000 and fig.read_bytes()[:4] == b"\x89PNG"
    assert not fig.with_suffix(".pdf").exists()  # only the file named
    r = read_result(res_file)
    n = {k: int(r[k].sum()) for k in ("measured", "replaced", "failed", "masked")}
    assert sum(n.values()) == len(r["x"])
    assert n["masked"] > 0 and n["failed"] > 0 and n["measured"] > n["failed"]
    assert f"{n['measured']} measured, {n['replaced']} replaced, {n['failed']} failed, {n['masked']} masked" in printed


def test_show_result_bad_file_exits_2(tmp_path, capsys):
    (tmp_path / "x.h5").write_text("not hdf5")
    assert main(["show-result", str(tmp_path / "x.h5"), "-o", str(tmp_path / "f.png")]) == 2
    assert main(["show-result", str(tmp_path / "none.h5"), "-o", str(tmp_path / "f.png")]) == 2
    assert not (tmp_path / "f.png").exists()
