"""Density sources: each analytic field against its formula, the slice and file sources, bad keys."""

import math

import h5py
import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.loaders import DEFAULT_SNAPSHOTS, read_snapshots
from synthbos.raytrace.sources import COMMON_KEYS, SOURCE_KEYS, density_from_config, node_coordinates

from synthbos import SynthbosError

NODES = [(0, 0, 0), (3, 7, 11), (5, 2, 9), (7, 8, 0)]  # (k, j, i)


def _vol(source, **keys):
    v = dict(COMMON_KEYS, source=source, size_mm=[20.0, 16.0, 6.0], grid=[12, 9, 8])
    v.update(keys)
    return v


def _xyz(field, k, j, i):
    x, y, z = node_coordinates(field.rho.shape, field.size_m)
    return x[i], y[j], z[k]


def _check_nodes(field, formula):
    for k, j, i in NODES:
        x, y, z = _xyz(field, k, j, i)
        assert_allclose(field.rho[k, j, i], formula(x, y, z), rtol=1e-13, err_msg=f"node {(k, j, i)}")


def test_grid_and_size():
    f = density_from_config(_vol("uniform", density_kg_m3=1.1))
    assert f.rho.shape == (8, 9, 12) and f.rho.dtype == np.float64
    assert_allclose(f.size_m, (0.020, 0.016, 0.006))
    assert_allclose(f.rho, 1.1)
    assert f.ambient == 1.1
    x, y, z = node_coordinates(f.rho.shape, f.size_m)
    assert_allclose([x[0], x[-1], y[0], z[-1]], [-0.010, 0.010, -0.008, 0.003])


def test_linear_formula():
    f = density_from_config(_vol("linear", density_kg_m3=1.2, gradient_kg_m4=[3.0, -2.0]))
    _check_nodes(f, lambda x, y, z: 1.2 + 3.0 * x - 2.0 * y)
    f3 = density_from_config(_vol("linear", gradient_kg_m4=[0.0, 0.0, 5.0]))
    _check_nodes(f3, lambda x, y, z: 1.225 + 5.0 * z)
    assert f.ambient == 1.2


def test_gaussian_formula():
    f = density_from_config(_vol("gaussian", amplitude_kg_m3=-0.03, sigma_mm=3.0, centre_mm=[1.0, -2.0, 0.5]))
    c = (1e-3, -2e-3, 0.5e-3)
    s = 3e-3
    _check_nodes(
        f,
        lambda x, y, z: (
            1.225 - 0.03 * math.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / (2 * s * s))
        ),
    )


def test_step_formula_and_thickness():
    f = density_from_config(
        _vol(
            "step",
            density_kg_m3=1.0,
            jump_kg_m3=0.2,
            position_mm=[2.0, 1.0],
            normal=[3.0, 4.0],
            thickness_mm=1.5,
        )
    )
    _check_nodes(
        f, lambda x, y, z: 1.0 + 0.1 * (1 + math.tanh(2 * ((x - 2e-3) * 0.6 + (y - 1e-3) * 0.8) / 1.5e-3))
    )
    assert f.ambient == 1.0
    # maximum-slope thickness: a fine 1-D profile across the step has max slope = jump / thickness
    g = density_from_config(
        dict(
            COMMON_KEYS,
            source="step",
            size_mm=[10.0, 1.0, 1.0],
            grid=[2001, 2, 2],
            jump_kg_m3=0.2,
            thickness_mm=0.5,
        )
    )
    x = node_coordinates(g.rho.shape, g.size_m)[0]
    slope = np.gradient(g.rho[0, 0], x).max()
    assert_allclose(slope, 0.2 / 0.5e-3, rtol=1e-3)
    assert_allclose([g.rho[0, 0, 0], g.rho[0, 0, -1]], [1.225, 1.425], atol=1e-12)


def test_sinusoidal_formula():
    f = density_from_config(
        _vol("sinusoidal", amplitude_kg_m3=0.02, wavelength_mm=5.0, direction=[1.0, 1.0], phase_deg=30.0)
    )
    r = 1 / math.sqrt(2)
    _check_nodes(f, lambda x, y, z: 1.225 + 0.02 * math.sin(2 * math.pi * (x + y) * r / 5e-3 + math.pi / 6))


@pytest.mark.parametrize(
    ("keys", "message"),
    [
        ({"source": "linear", "gradient": [1, 2]}, r"unknown key volume\.gradient for source 'linear'"),
        ({"source": "warp"}, r"volume\.source must be one of"),
        ({"source": "linear", "gradient_kg_m4": [1.0]}, r"volume\.gradient_kg_m4 must be a list of 2 or 3"),
        (
            {"source": "linear", "gradient_kg_m4": [200.0, 0.0]},
            r"density must be > 0 everywhere; .* reduce the gradient",
        ),
        ({"source": "gaussian", "sigma_mm": 0.0}, r"volume\.sigma_mm must be > 0"),
        (
            {"source": "gaussian", "amplitude_kg_m3": float("nan")},
            r"volume\.amplitude_kg_m3 must be finite",
        ),
        ({"source": "step", "normal": [0.0, 0.0]}, r"volume\.normal must not be the zero vector"),
        ({"source": "step", "jump_kg_m3": -2.0}, r"must be > 0 everywhere"),
        ({"source": "sinusoidal", "wavelength_mm": -1.0}, r"volume\.wavelength_mm must be > 0"),
        ({"source": "uniform", "density_kg_m3": "air"}, r"volume\.density_kg_m3 must be a number"),
        ({"source": "uniform", "grid": [4, 4]}, r"volume\.grid must be a list of 3 numbers"),
        ({"source": "slice", "snapshot": 5}, r"volume\.snapshot must be >= 0 and <= 4, got 5"),
        ({"source": "slice", "grid": [8, 8, 8]}, r"volume\.grid does not apply"),
        ({"source": "file"}, r"volume\.path is required"),
        ({"source": "file", "path": "x.npy", "axis": "w"}, r"volume\.axis must be"),
        ({"source": "file", "path": "x.npy", "normalised": "yes"}, r"volume\.normalised must be"),
        ({"source": "file", "path": "x.npy", "format": "csv"}, r"volume\.format must be"),
        ({"source": "file", "path": "x.npy", "spacing_mm": -1.0}, r"volume\.spacing_mm\[0\] must be > 0"),
    ],
)
def test_bad_keys_name_the_key(keys, message):
    v = dict(COMMON_KEYS)
    v.update(keys)
    with pytest.raises(SynthbosError, match=message):
        density_from_config(v)


def test_source_keys_are_toml_values():
    # every default is a TOML value (None only marks a required key), so the lead's config can fill them in
    for source, keys in SOURCE_KEYS.items():
        for key, default in keys.items():
            assert default is None or isinstance(default, str | int | float | list), (source, key)


def test_slice_default_snapshot():
    dens, _, _ = read_snapshots()
    assert dens.shape[0] == 5
    for k in (0, 4):
        f = density_from_config(dict(COMMON_KEYS, source="slice", snapshot=k))
        assert f.rho.shape == (2, *dens.shape[1:])
        assert_array_equal(f.rho[0], f.rho[1])  # extruded: d rho/dz = 0 exactly
        assert_allclose(f.rho[0], 1.225 * dens[k], rtol=1e-15)
        assert_allclose(f.ambient, 1.225 * dens[k].mean(), rtol=1e-15)
        assert_allclose(f.ambient, 1.225, rtol=1e-6)  # normalised to mean 1
        assert_allclose(f.size_m, (0.032, 0.032, 0.010))
    g = density_from_config(dict(COMMON_KEYS, source="slice", snapshot=2, density_scale_kg_m3=0.5))
    assert_allclose(g.rho[0], 0.5 * dens[2])


def test_slice_from_another_file(tmp_path):
    path = tmp_path / "snaps.h5"
    plane = 1.0 + 0.1 * np.arange(12.0).reshape(3, 4) / 12
    with h5py.File(path, "w") as h5:
        h5.create_dataset("density", data=np.stack([plane, plane * 2]))
    f = density_from_config(dict(COMMON_KEYS, source="slice", snapshot=1, path=str(path)))
    assert_allclose(f.rho[1], 1.225 * 2 * plane)
    with pytest.raises(SynthbosError, match=r"snapshot must be >= 0 and <= 1, got 2"):
        density_from_config(dict(COMMON_KEYS, source="slice", snapshot=2, path=str(path)))
    assert DEFAULT_SNAPSHOTS.name == "buoyancy_snapshots.h5"


def test_file_source_slice_volume_spacing_and_scale(tmp_path):
    rng = np.random.default_rng(3)
    vol = 1.0 + 0.1 * rng.random((4, 5, 6))
    np.save(tmp_path / "v.npy", vol)
    base = dict(COMMON_KEYS, source="file", path=str(tmp_path / "v.npy"))
    # physical data (npy: not normalised by default), mapped onto size_mm
    f = density_from_config(base)
    assert_array_equal(f.rho, vol)
    assert_allclose(f.size_m, (0.032, 0.032, 0.010))
    assert_allclose(f.ambient, vol.mean())
    # a slice, extruded, normalised -> scaled
    g = density_from_config(dict(base, slice_index=1, axis="y", normalised=True, density_scale_kg_m3=2.0))
    assert g.rho.shape == (2, 4, 6)
    assert_allclose(g.rho[0], 2.0 * vol[:, 1, :])
    assert_array_equal(g.rho[0], g.rho[1])
    # spacing given: the extent follows from it along the data axes
    h = density_from_config(dict(base, spacing_mm=[0.5, 0.25, 2.0]))
    assert_allclose(h.size_m, (0.5e-3 * 5, 0.25e-3 * 4, 2e-3 * 3))
    ys = density_from_config(dict(base, slice_index=2, axis="y", spacing_mm=[0.5, 0.25, 2.0]))
    assert_allclose(ys.size_m, (0.5e-3 * 5, 2e-3 * 3, 0.010))  # a y-slice spans x by z
    assert_array_equal(ys.rho[0], vol[:, 2, :])
    s = density_from_config(dict(base, slice_index=0, spacing_mm=0.1))
    assert_allclose(s.size_m, (0.1e-3 * 5, 0.1e-3 * 4, 0.010))  # the extruded slice keeps size_mm[2]
    sub = density_from_config(dict(base, index_range=[[1, 4], [0, 2], "all"]))
    assert_array_equal(sub.rho, vol[:, 0:2, 1:4])


def test_file_source_jhtdb_normalised_by_default(tmp_path):
    path = tmp_path / "cut.nc"
    vol = (1.0 + 0.05 * np.random.default_rng(0).standard_normal((3, 4, 5))).astype(np.float32)
    with h5py.File(path, "w") as h5:
        h5.create_dataset("Density_0001", data=vol[..., None])
        for ax, n in (("xcoor", 5), ("ycoor", 4), ("zcoor", 3)):
            h5.create_dataset(ax, data=np.arange(n) * 0.1)
    f = density_from_config(dict(COMMON_KEYS, source="file", path=str(path), slice_index=1))
    assert_allclose(f.rho[0], 1.225 * vol[1].astype(np.float64))
    p = density_from_config(dict(COMMON_KEYS, source="file", path=str(path), normalised=False))
    assert_allclose(p.rho, vol.astype(np.float64))


def test_file_source_bad_data_named(tmp_path):
    vol = np.ones((3, 4, 5))
    vol[0, 0, 0] = -1.0
    np.save(tmp_path / "neg.npy", vol)
    with pytest.raises(SynthbosError, match=r"neg\.npy: density must be > 0"):
        density_from_config(dict(COMMON_KEYS, source="file", path=str(tmp_path / "neg.npy")))
    with pytest.raises(SynthbosError, match=r"missing\.npy: density file not found"):
        density_from_config(dict(COMMON_KEYS, source="file", path=str(tmp_path / "missing.npy")))


def test_file_source_axis_order_and_stretch_notice(tmp_path):
    from synthbos.raytrace.config import load_config
    from synthbos.raytrace.sources import DensityNotice

    rng = np.random.default_rng(4)
    plane = 1.0 + 0.1 * rng.random((5, 8))  # (ny, nx): 8 nodes along x
    np.save(tmp_path / "sim.npy", plane.T)  # a simulation writing (nx, ny)
    base = dict(COMMON_KEYS, source="file", path=str(tmp_path / "sim.npy"), size_mm=[32.0, 16.0, 4.0])
    with pytest.warns(DensityNotice, match=r"8x5 nodes \(x, y\) are stretched onto size_mm 32 x 16 mm "
                      r"\(node spacing 4\.571 x 4 mm\)"):
        f = density_from_config(dict(base, axis_order="xy"))
    assert_array_equal(f.rho[0], plane)  # not rotated
    assert len(f.notes) == 1 and "spacing_mm" in f.notes[0]
    with pytest.warns(DensityNotice):
        g = density_from_config(base)
    assert g.rho.shape == (2, 8, 5)  # the old reading: rotated
    # with the spacing given there is nothing to announce
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        h = density_from_config(dict(base, axis_order="xy", spacing_mm=[0.5, 0.5]))
    assert h.notes == ()
    assert_allclose(h.size_m[:2], (3.5e-3, 2e-3))
    # a file with its own spacing: the change of proportions is stated
    path = tmp_path / "cut.nc"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("Density_0001", data=np.ones((3, 4, 5, 1)))
        for ax, n in (("xcoor", 5), ("ycoor", 4), ("zcoor", 3)):
            h5.create_dataset(ax, data=np.arange(n) * 0.1)
    with pytest.warns(DensityNotice, match=r"aspect ratio of 1\.333, this one 2"):
        density_from_config(dict(COMMON_KEYS, source="file", path=str(path), size_mm=[32.0, 16.0, 4.0]))
    # the key is part of the configuration, validated
    cfg = load_config({"volume": {"source": "file", "path": str(tmp_path / "sim.npy"), "axis_order": "xy"}})
    assert cfg["volume"]["axis_order"] == "xy"
    with pytest.raises(SynthbosError, match="axis_order"):
        density_from_config(dict(base, axis_order=3))
    with pytest.raises(SynthbosError, match="axis_order must name each"):
        density_from_config(dict(base, axis_order="xyz"))
