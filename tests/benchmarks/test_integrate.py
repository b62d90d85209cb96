"""``synthbos integrate``: rendered pairs processed by every method and integrated by every solver, scored
against the renderer's cone truth; and the bad inputs, refused in one line with nothing written."""

import h5py
import numpy as np
import pytest
from numpy.testing import assert_allclose
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.integrate import (
    geometry_from_pair,
    gradient_grid,
    solve_density,
    truth_on_grid,
)
from synthbos.benchmarks.process import read_result, run_method, write_result
from synthbos.benchmarks.registry import get_method, method_names, missing_modules
from synthbos.integration import border_region
from synthbos.raytrace import read_pair, render_pair, write_pair

BLOB = {"camera": {"pixels": [256, 256]}, "rays": {"per_dot": 200},
        "volume": {"source": "gaussian", "amplitude_kg_m3": 0.05, "sigma_mm": 3.0, "centre_mm": [1.0, -1.0, 0.0],
                   "grid": [64, 64, 16]}}

# Every method whose modules are installed (optical-flow and openpiv need the `methods` extra).
METHODS_HERE = [m for m in method_names() if not missing_modules(get_method(m))]
# Density RMS against the cone truth, in parts of its range. TV-L1 optical flow has an error floor of
# about 0.006 px (median; the others' is 0.0002 px or less on this noise-free blob, whose median
# displacement is 0.015 px), which integrates to 6.0 %.
LIMIT = {"optical-flow": 0.07}


@pytest.fixture(scope="module")
def blob(tmp_path_factory):
    folder = tmp_path_factory.mktemp("blob")
    write_pair(folder / "pair.h5", render_pair(BLOB, device="cpu"))
    for m in METHODS_HERE:
        assert main(["process", str(folder / "pair.h5"), "--method", m, "-o", str(folder / f"{m}.h5")]) == 0
    return folder


@pytest.mark.parametrize("solver", ["dct", "lsq", "wlsq"])
@pytest.mark.parametrize("method", METHODS_HERE)
def test_rendered_blob_density_within_3_percent_of_the_cone_truth(blob, method, solver):
    pair = read_pair(blob / "pair.h5")
    result, _ = read_result(blob / f"{method}.h5")
    geometry = geometry_from_pair(pair)
    grid = gradient_grid(result, geometry)
    cone, chief = truth_on_grid(pair, grid)
    region = border_region(grid.measured & np.isfinite(cone))
    # The constant of integration from the known density on the border (the truth there).
    dmap = solve_density(grid, solver=solver, reference_value=np.where(region, cone, np.nan), reference_region=region)
    ok = np.isfinite(dmap.density) & np.isfinite(cone)
    rng = np.ptp(cone[ok])
    rel = np.sqrt(np.mean((dmap.density - cone)[ok] ** 2)) / rng
    rel_chief = np.sqrt(np.mean((dmap.density - chief)[ok] ** 2)) / np.ptp(chief[ok])
    print(f"\nblob {method:12s} {solver:5s}: rms vs cone {rel * 100:.2f} % of the range ({rng:.4f} kg/m^3), "
          f"vs chief ray {rel_chief * 100:.2f} %, {int(ok.sum())} nodes")
    assert ok.sum() > 100
    assert rel < LIMIT.get(method, 0.03)


def test_cli_writes_density_with_truths_and_summary(blob, tmp_path, capsys):
    out = tmp_path / "d.h5"
    assert main(["integrate", str(blob / "correlation.h5"), "--pair", str(blob / "pair.h5"), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "cone" in printed and "chief" in printed
    with h5py.File(out) as f:
        rho, x, y = f["density_kg_m3"][()], f["x_mm"][()], f["y_mm"][()]
        assert rho.shape == (len(y), len(x))
        for name in ("density_kg_m3", "x_mm", "y_mm", "truth_cone_kg_m3", "truth_chief_kg_m3"):
            assert f[name].attrs["units"] in ("kg/m^3", "mm")
        assert f["truth_cone_kg_m3"].shape == rho.shape
        # The default constant: the ambient density (1.225) on average over the border.
        border = f["reference_region"][()]
        assert_allclose(np.nanmean(rho[border]), 1.225, rtol=1e-12)
        assert f.attrs["cone_rms_rel"] < 0.05
        # The grid is the correlation grid mapped to the mid-plane: 256 px span 0.75 * 256 * 10 um / M.
        m = f.attrs["geometry"]
        assert '"magnification"' in m
        span_px = (read_result(blob / "correlation.h5")[0].xy[:, 0].max()
                   - read_result(blob / "correlation.h5")[0].xy[:, 0].min())
        pair = read_pair(blob / "pair.h5")
        assert_allclose(x[-1] - x[0], span_px * 10e-3 * 0.75 / pair.attrs["magnification"], rtol=1e-9)
        # The blob's peak sits near its centre (1, -1) mm: x and y are the volume's, with y as in the sources.
        j, i = np.unravel_index(np.nanargmax(f["truth_cone_kg_m3"][()]), rho.shape)
        assert abs(x[i] - 1.0) < 1.5 and abs(y[j] + 1.0) < 1.5


def test_cli_without_pair_uses_a_configuration(blob, tmp_path):
    import tomllib

    cfg = tmp_path / "setup.toml"
    pair = read_pair(blob / "pair.h5")
    cfg.write_text(pair.attrs["config"])
    assert tomllib.loads(cfg.read_text())
    for solver in ("dct", "wlsq"):
        out = tmp_path / f"d_{solver}.h5"
        assert main(["integrate", str(blob / "tracking-cc.h5"), "--config", str(cfg), "--solver", solver,
                     "--reference-density", "1.2", "--reference-region=-100,100,-100,100", "-o", str(out)]) == 0
        with h5py.File(out) as f:
            rho = f["density_kg_m3"][()]
            assert_allclose(np.nanmean(rho), 1.2, rtol=1e-12)
            assert "truth_cone_kg_m3" not in f
    # Dirichlet: the border of the measured domain held at the given density.
    out = tmp_path / "d_dirichlet.h5"
    assert main(["integrate", str(blob / "correlation.h5"), "--config", str(cfg), "--dirichlet",
                 "--reference-density", "1.21", "-o", str(out)]) == 0
    with h5py.File(out) as f:
        rho, border = f["density_kg_m3"][()], f["reference_region"][()]
        assert_allclose(rho[border], 1.21, rtol=1e-12)
        assert np.isfinite(rho[f["measured"][()]]).all()
        assert "held fixed" in f.attrs["reference"]


def _error_line(capsys):
    err = capsys.readouterr().err.strip()
    assert err.startswith("synthbos: error:") and "\n" not in err and "Traceback" not in err
    return err


def test_bad_inputs_one_line_and_nothing_written(blob, tmp_path, capsys):
    pair_file = str(blob / "pair.h5")
    out = tmp_path / "d.h5"
    pair = read_pair(pair_file)
    res = run_method("correlation", pair.reference, pair.gradient)

    # An empty result.
    empty = tmp_path / "empty.h5"
    with h5py.File(empty, "w") as f:
        f.attrs["method"] = "tracking"
        g = f.create_group("dots")
        for n in ("x", "y", "u", "v"):
            g.create_dataset(n, data=np.zeros(0))
    assert main(["integrate", str(empty), "-o", str(out)]) == 2
    assert "no vectors" in _error_line(capsys)

    # No valid vector.
    res.uv[:] = np.nan
    res.table["u"] = np.full_like(res.table["u"], np.nan)
    res.table["v"] = np.full_like(res.table["v"], np.nan)
    nan_file = write_result(tmp_path / "nan.h5", res)
    assert main(["integrate", str(nan_file), "--pair", pair_file, "-o", str(out)]) == 2
    assert "no valid vector" in _error_line(capsys)

    # A mask that covers everything.
    assert main(["integrate", str(blob / "correlation.h5"), "--pair", pair_file, "--mask-region=-100,100,-100,100",
                 "-o", str(out)]) == 2
    assert "mask covers every" in _error_line(capsys)

    # A result and a pair that do not belong together: another image size, another magnification.
    small = dict(BLOB, camera={"pixels": [128, 128]}, rays={"per_dot": 10})
    other = tmp_path / "other.h5"
    write_pair(other, render_pair(small, device="cpu"))
    assert main(["integrate", str(blob / "correlation.h5"), "--pair", str(other), "-o", str(out)]) == 2
    assert "do not belong together" in _error_line(capsys)
    with h5py.File(blob / "correlation.h5") as f, h5py.File(tmp_path / "mag.h5", "w") as g:
        for k in f:
            f.copy(k, g)
        for k, v in f.attrs.items():
            g.attrs[k] = v
        g.attrs["magnification"] = 0.2
    assert main(["integrate", str(tmp_path / "mag.h5"), "--pair", pair_file, "-o", str(out)]) == 2
    assert "magnification" in _error_line(capsys)

    # ... or a set-up (configuration) with another image size.
    cfg = tmp_path / "setup.toml"
    cfg.write_text("[camera]\npixels = [128, 128]\n")
    assert main(["integrate", str(blob / "correlation.h5"), "--config", str(cfg), "-o", str(out)]) == 2
    assert "set-up's are 128 x 128 px" in _error_line(capsys)

    # A bad option value and a missing file.
    assert main(["integrate", str(blob / "correlation.h5"), "--reference-region", "1,2", "-o", str(out)]) == 2
    _error_line(capsys)
    assert main(["integrate", str(tmp_path / "missing.h5"), "-o", str(out)]) == 2
    assert "does not exist" in _error_line(capsys)
    assert not out.exists()
    assert not list(tmp_path.glob(".*.tmp"))
