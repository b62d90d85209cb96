"""``synthbos integrate PAIR.h5``: the floor of the density from a pair's exact displacements; and the plane
a constant displacement bias integrates to.

The pair files are synthesised: dots at random image positions, displacements from Eq. 4 applied to a
known depth-averaged density (a Gaussian blob), its density at each dot as the truths.
"""

import h5py
import numpy as np
import pytest
from numpy.testing import assert_allclose
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.integrate import exact_grid, geometry_from_config, input_kind, solve_density
from synthbos.raytrace import write_pair
from synthbos.raytrace.config import config_to_toml, load_config
from synthbos.raytrace.pairfile import Pair

from synthbos import SynthbosError

CONFIG = {"camera": {"pixels": [128, 128]}}
AMBIENT, AMPLITUDE, SIGMA_MM, CENTRE_MM = 1.225, 0.05, 1.5, (0.4, -0.3)


def blob(x_mm, y_mm):
    """The depth-averaged density (kg/m^3) and its gradient (kg/m^4) in the volume's frame."""
    dx, dy = x_mm - CENTRE_MM[0], y_mm - CENTRE_MM[1]
    bump = AMPLITUDE * np.exp(-(dx**2 + dy**2) / (2 * SIGMA_MM**2))
    return AMBIENT + bump, -dx / SIGMA_MM**2 * bump * 1e3, -dy / SIGMA_MM**2 * bump * 1e3


def synthetic_pair(*, bias_px=(0.0, 0.0), n_dots=400, seed=0) -> Pair:
    """Dots at random positions whose exact displacements are Eq. 4 of ``blob`` (plus ``bias_px``)."""
    geometry = geometry_from_config(CONFIG)
    rng = np.random.default_rng(seed)
    ref = rng.uniform(2.0, 125.0, (n_dots, 2))
    x_mm, y_mm = geometry.to_mm(ref[:, 0], ref[:, 1])
    rho, gx, gy = blob(x_mm, y_mm)
    per_px = geometry.gradient(1.0, 1.0)  # grad rho (kg/m^4) per px of displacement, each axis
    disp = np.stack([gx / per_px[0], gy / per_px[1]], axis=1) + np.asarray(bias_px)
    valid = np.ones(n_dots, bool)
    valid[:3] = False  # left out by the integration
    disp[:3] = 50.0
    return Pair(reference=np.zeros((128, 128), np.float32), gradient=np.zeros((128, 128), np.float32),
                target_xy_m=np.zeros((n_dots, 2)), reference_px=ref, gradient_px=ref + disp, displacement_px=disp,
                theory_px=disp, valid=valid, theory_cone_px=disp, density_cone_kg_m3=rho, density_chief_kg_m3=rho,
                attrs={"config": config_to_toml(load_config(CONFIG)), "magnification": geometry.magnification})


@pytest.fixture
def pair_file(tmp_path):
    return write_pair(tmp_path / "pair.h5", synthetic_pair())


def test_floor_command_scores_exact_displacements(pair_file, tmp_path, capsys):
    out = tmp_path / "floor.h5"
    assert main(["integrate", str(pair_file), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "cone" in printed and "rms/range" in printed
    with h5py.File(out) as f:
        a = dict(f.attrs)
        rho, x, y = f["density_kg_m3"][()], f["x_mm"][()], f["y_mm"][()]
        assert f["truth_cone_kg_m3"].attrs["units"] == "kg/m^3"
    assert a["method"] == "exact" and a["pair"] == str(pair_file)
    for key in ("cone_rms_rel", "cone_p90_rel", "cone_offset_kg_m3", "chief_rms_rel", "cone_range_kg_m3"):
        assert key in a
    # The constant: the ambient density put on the border of the measured domain, where the blob's truth
    # is still above it: the offset is exactly that difference.
    with h5py.File(out) as f:
        cone, border = f["truth_cone_kg_m3"][()], f["reference_region"][()]
    ok = np.isfinite(rho)
    assert_allclose(a["cone_offset_kg_m3"], AMBIENT - np.mean(cone[border & ok]), atol=1e-8)
    assert_allclose(a["cone_range_kg_m3"], np.ptp(cone[ok]), rtol=1e-12)
    assert_allclose(np.ptp(blob(*np.meshgrid(x, y))[0][ok]), np.ptp(cone[ok]), rtol=0.02)
    # Exact gradients sampled at the dots and interpolated linearly onto the grid: beside the offset, the
    # reconstruction is within 1 % of the range of the blob (0.64 % here); with the offset 3 %.
    shape_err = np.sqrt(np.mean((rho - cone - a["cone_offset_kg_m3"])[ok] ** 2)) / a["cone_range_kg_m3"]
    assert 1e-3 < shape_err < 0.01
    assert_allclose(a["cone_rms_rel"], np.sqrt(np.mean((rho - cone)[ok] ** 2)) / np.ptp(cone[ok]), rtol=1e-9)
    assert 0.02 < a["cone_rms_rel"] < 0.04


def test_a_constant_displacement_bias_integrates_to_a_plane():
    geometry = geometry_from_config(CONFIG)
    bias = np.array([0.004, -0.003])  # px
    exact = solve_density(exact_grid(synthetic_pair(), geometry), ambient=AMBIENT)
    biased_grid = exact_grid(synthetic_pair(bias_px=bias), geometry)
    biased = solve_density(biased_grid, ambient=AMBIENT)
    diff = biased.density - exact.density
    X, Y = np.meshgrid(biased_grid.x_mm, biased_grid.y_mm)
    ok = np.isfinite(diff)
    a = np.stack([np.ones(ok.sum()), X[ok], Y[ok]], axis=1)
    coef, *_ = np.linalg.lstsq(a, diff[ok], rcond=None)
    slope = np.asarray(geometry.gradient(*bias)) * 1e-3  # kg/m^4 -> kg/m^3 per mm
    assert_allclose(coef[1:], slope, rtol=1e-6)
    assert_allclose(diff[ok], a @ coef, atol=1e-9 * np.abs(diff[ok]).max() + 1e-12)  # a plane, nothing else
    assert abs(np.mean(diff[biased.reference_region & ok])) < 1e-12  # level on the reference border


def test_integrate_input_errors_one_line_nothing_written(pair_file, tmp_path, capsys):
    out = tmp_path / "d.h5"

    def refused(args, words):
        assert main([*args, "-o", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("synthbos: error:") and "\n" not in err and words in err, err
        assert not out.exists()

    refused(["integrate", str(pair_file), "--pair", str(pair_file)], "leave out --pair and --config")
    cfg = tmp_path / "c.toml"
    cfg.write_text("[camera]\npixels = [128, 128]\n")
    refused(["integrate", str(pair_file), "--config", str(cfg)], "is a pair file")
    refused(["integrate", str(cfg)], "is not an HDF5 file")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.create_dataset("x", data=np.zeros(3))
    refused(["integrate", str(tmp_path / "other.h5")], "neither a result file")
    assert main(["integrate", str(pair_file), "-o", str(tmp_path / "floor.h5")]) == 0
    refused(["integrate", str(tmp_path / "floor.h5")], "is a density file")
    refused(["integrate", str(tmp_path / "nowhere.h5")], "does not exist")
    few = synthetic_pair(n_dots=5)
    few.valid[:] = False
    refused(["integrate", str(write_pair(tmp_path / "few.h5", few))], "0 valid dot(s)")
    with pytest.raises(SynthbosError, match="not an HDF5 file"):
        input_kind(cfg)


def test_a_campaign_keeps_each_pairs_floor(tmp_path, monkeypatch):
    """``pair_floor`` writes a pair's floor beside its scores, reads it back after, and makes it again once the
    pair file is newer (a pair rendered again)."""
    import os

    from synthbos.benchmarks import integrate

    path = tmp_path / "pairs" / "s2_p00.h5"
    path.parent.mkdir()
    write_pair(path, synthetic_pair())
    first = integrate.pair_floor(path)
    kept = tmp_path / "floors" / "s2_p00.npz"
    assert integrate.floor_file(path) == kept and kept.exists() and integrate.floor_current(path)
    want = integrate.density_floor_errors(path)
    assert sorted(first) == sorted(want) and all(np.array_equal(first[k], want[k]) for k in want)

    def refuse(_path):
        raise AssertionError("computed again")

    monkeypatch.setattr(integrate, "density_floor_errors", refuse)
    again = integrate.pair_floor(path)
    assert all(np.array_equal(again[k], want[k]) for k in want)
    stamp = kept.stat().st_mtime_ns
    os.utime(path, ns=(stamp + 10**9, stamp + 10**9))  # the pair rendered again, after its floor
    assert not integrate.floor_current(path)
    with pytest.raises(AssertionError, match="computed again"):
        integrate.pair_floor(path)
    path.unlink()  # a pair deleted to be rendered again (a Dask pipeline task asks before it renders)
    assert not integrate.floor_current(path)
