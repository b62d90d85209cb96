"""``synthbos show-result``: the figure is written and the summary states the counts of the result file."""

import numpy as np
import pytest
from figure_checks import assert_journal_figure
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


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A small rendered pair, its tracking and correlation results, and its density file (exact displacements)."""
    d = tmp_path_factory.mktemp("pair")
    (d / "small.toml").write_text("[camera]\npixels = [128, 128]\n[rays]\nper_dot = 10\n")
    assert main(["render", str(d / "small.toml"), "-o", str(d / "pair.h5"), "-q", "--device", "cpu"]) == 0
    for method in ("tracking", "correlation"):
        assert main(["process", str(d / "pair.h5"), "--method", method, "-o", str(d / f"{method}.h5"),
                     "--device", "cpu"]) == 0
    assert main(["integrate", str(d / "pair.h5"), "-o", str(d / "density.h5")]) == 0
    return d


@pytest.fixture
def drawn(monkeypatch):
    """The figures that show-result and show-density save, kept for inspection (and still written)."""
    from synthbos.benchmarks import show_density, show_result

    figs = []
    for module in (show_result, show_density):
        save = module.save_figure

        def keep(fig, path, save=save, **kwargs):
            figs.append(fig)
            return save(fig, path, **kwargs)

        monkeypatch.setattr(module, "save_figure", keep)
    return figs


def _quiver_key(fig):
    from matplotlib.quiver import QuiverKey

    return [a for ax in fig.axes for a in ax.get_children() if isinstance(a, QuiverKey)]


def test_show_result_draws_the_error_against_the_pair(rendered, tmp_path, capsys, drawn):
    from synthbos.raytrace import read_pair

    pair = read_pair(rendered / "pair.h5")
    r = read_result(rendered / "tracking.h5")
    # each tracked dot is its pair dot (the pair's prior): the error at the dot itself, independently of the
    # interpolation show-result uses
    ok = r["measured"] & pair.valid
    err = np.hypot(r["u"] - pair.displacement_px[:, 0], r["v"] - pair.displacement_px[:, 1])[ok]
    out = tmp_path / "t.jpg"
    capsys.readouterr()
    assert main(["show-result", str(rendered / "tracking.h5"), "-o", str(out)]) == 0  # the pair from the result
    printed = capsys.readouterr().out
    assert printed.startswith(f"wrote {out}\n") and out.read_bytes()[:3] == b"\xff\xd8\xff"  # a JPEG, named so
    assert not list(tmp_path.glob("t.jpg.*"))
    median = float(printed.split("error against the pair's truth: median ")[1].split(" px")[0])
    np.testing.assert_allclose(median, np.median(err), rtol=0.05, atol=2e-4)
    fig = drawn[-1]
    assert fig.get_figwidth() == pytest.approx(7.2) and len([a for a in fig.axes if a.get_label() != "<colorbar>"]) == 2
    assert_journal_figure(fig)
    (key,) = _quiver_key(fig)
    assert key.U > 0 and key.text.get_text() == f"{key.U:g} px"
    assert any(a.get_title(loc="left").startswith("error: median") for a in fig.axes)
    # --pair names the pair; one of another image size is refused
    assert main(["show-result", str(rendered / "correlation.h5"), "--pair", str(rendered / "pair.h5"),
                 "-o", str(tmp_path / "c.svg")]) == 0
    assert b"<svg" in (tmp_path / "c.svg").read_bytes()[:2000]
    (rendered / "other.toml").write_text("[camera]\npixels = [96, 96]\n[rays]\nper_dot = 4\n")
    assert main(["render", str(rendered / "other.toml"), "-o", str(tmp_path / "other.h5"), "-q",
                 "--device", "cpu"]) == 0
    capsys.readouterr()
    assert main(["show-result", str(rendered / "tracking.h5"), "--pair", str(tmp_path / "other.h5"),
                 "-o", str(tmp_path / "x.png")]) == 2
    assert "do not belong together" in capsys.readouterr().err and not (tmp_path / "x.png").exists()


def test_show_result_and_show_density_draw_a_density_file(rendered, tmp_path, capsys, drawn):
    import h5py

    with h5py.File(rendered / "density.h5") as f:
        rho, truth = f["density_kg_m3"][()], f["truth_cone_kg_m3"][()]
    rms = np.sqrt(np.nanmean((rho - truth) ** 2))
    capsys.readouterr()
    assert main(["show-result", str(rendered / "density.h5"), "-o", str(tmp_path / "d.pdf")]) == 0
    printed = capsys.readouterr().out
    assert (tmp_path / "d.pdf").read_bytes()[:5] == b"%PDF-"
    np.testing.assert_allclose(float(printed.split("RMS ")[1].split(" kg")[0]), rms, rtol=2e-3)
    assert main(["show-density", str(rendered / "density.h5"), "-o", str(tmp_path / "d.png"), "-q"]) == 0
    for fig in drawn:
        assert_journal_figure(fig)
        images = [a for a in fig.axes if a.get_images()]
        assert [a.get_xlabel() for a in images] == ["x (mm)"] * 3 and images[0].get_ylabel() == "y (mm)"
        labels = {a.get_xlabel() for a in fig.axes if a.get_label() == "<colorbar>"}
        assert labels == {"ρ (kg/m³)", "Δρ (kg/m³)"}
        clims = [im.get_clim() for a in images[:2] for im in a.get_images()]
        assert clims[0] == clims[1]  # reconstructed and true density on one scale


def test_show_result_draws_the_density_of_many_failures(tmp_path, capsys, drawn):
    """50,000 dots, those left of x = 200 px failed: their failed fraction in cells, not 25,000 markers."""
    import h5py
    from synthbos.benchmarks.show_result import FAILED_MARKERS_MAX

    rng = np.random.default_rng(8)
    n = 50_000
    xy = rng.uniform(0, 400, size=(n, 2))
    failed = xy[:, 0] < 200
    uv = np.where(failed[:, None], np.nan, 0.3 * np.sin(xy / 40.0))
    path = tmp_path / "many.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("dots")
        for k, a in (("x", xy[:, 0]), ("y", xy[:, 1]), ("u", uv[:, 0]), ("v", uv[:, 1]), ("valid", ~failed)):
            g.create_dataset(k, data=a)
        f.attrs["method"], f.attrs["kind"] = "tracking", "dots"
        f.attrs["image_shape"] = np.array([400, 400])
    assert main(["show-result", str(path), "-o", str(tmp_path / "many.png")]) == 0
    assert f"{int(failed.sum())} failed" in capsys.readouterr().out
    fig = drawn[-1]
    assert_journal_figure(fig)
    markers = [c for a in fig.axes for c in a.collections if len(c.get_offsets()) > FAILED_MARKERS_MAX]
    assert not markers  # neither the dots nor the failures one by one
    (panel,) = [a for a in fig.axes if "failed" in a.get_title(loc="left")]
    (im,) = panel.get_images()
    frac = np.asarray(im.get_array())
    left, right = frac[:, : frac.shape[1] // 2 - 1], frac[:, frac.shape[1] // 2 + 1:]
    np.testing.assert_allclose(np.nanmean(left), 1.0)
    np.testing.assert_allclose(np.nanmean(right), 0.0)
    assert (tmp_path / "many.png").stat().st_size > 20_000
