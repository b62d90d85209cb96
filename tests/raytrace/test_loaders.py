"""Loaders: every format on small files written here, and every kind of bad input."""

import h5py
import nrrd
import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.checks import check_density as validate_density
from synthbos.raytrace.loaders import infer_format, load_density, read_snapshots

from synthbos import SynthbosError


def _volume(shape=(4, 5, 6), seed=0):
    rng = np.random.default_rng(seed)
    return 1.0 + 0.05 * rng.standard_normal(shape)


def _write_jhtdb(path, data, *, netcdf, step=2 * np.pi / 1024, name="Density_0001", trailing=True):
    """A fake JHTDB cutout: netCDF4-style (dimension scales) or the legacy plain h5py layout."""
    nz, ny, nx = data.shape
    with h5py.File(path, "w") as h5:
        coords = {}
        for ax, n, start in (("zcoor", nz, 7), ("ycoor", ny, 3), ("xcoor", nx, 5)):
            c = h5.create_dataset(ax, data=(start + np.arange(n)) * step)
            coords[ax] = c
        d = h5.create_dataset(name, data=(data[..., None] if trailing else data).astype(np.float32))
        if netcdf:
            h5.attrs["_NCProperties"] = "version=2,netcdf=4.9.2,hdf5=1.14.1"
            comp = h5.create_dataset("values", data=np.zeros(1))
            for i, ax in enumerate(("zcoor", "ycoor", "xcoor")):
                coords[ax].make_scale(ax)
                d.dims[i].attach_scale(coords[ax])
            comp.make_scale("values")
            if trailing:
                d.dims[3].attach_scale(comp)
        h5.attrs["dataset"] = "mixing"
        h5.attrs["x_start"] = 6
        h5.attrs["x_step"] = 1
        h5.attrs["t_start"] = 1


@pytest.mark.parametrize("netcdf", [True, False], ids=["netcdf4", "legacy"])
def test_jhtdb_both_layouts(tmp_path, netcdf):
    data = _volume((4, 5, 6))
    path = tmp_path / ("cut.nc" if netcdf else "cut.h5")
    _write_jhtdb(path, data, netcdf=netcdf)
    assert infer_format(path) == ("jhtdb" if netcdf else "hdf5")
    got = load_density(path)  # legacy .h5 is recognised as a JHTDB cutout from its contents
    assert got.dataset == "Density_0001"
    assert got.data.shape == (4, 5, 6)
    assert_allclose(got.data, data.astype(np.float32), rtol=0, atol=0)
    assert_allclose(got.spacing, [2 * np.pi / 1024] * 3, rtol=1e-12)
    assert got.attrs["dataset"] == "mixing"
    got = load_density(path, format="jhtdb", slice_index=2, axis="z")
    assert_array_equal(got.data, data[2].astype(np.float32))
    assert len(got.spacing) == 2


def test_jhtdb_without_trailing_axis_and_time_step_choice(tmp_path):
    path = tmp_path / "two.nc"
    a, b = _volume(seed=1), _volume(seed=2)
    _write_jhtdb(path, a, netcdf=False, trailing=False)
    with h5py.File(path, "a") as h5:
        h5.create_dataset("Density_0002", data=b[..., None])
    with pytest.raises(SynthbosError, match="several time steps"):
        load_density(path)
    assert_allclose(load_density(path, dataset="Density_0002").data, b)
    assert_allclose(load_density(path, dataset="Density_0001").data, a.astype(np.float32))


def test_jhtdb_errors(tmp_path):
    path = tmp_path / "vel.nc"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("Density_0001", data=np.ones((3, 3, 3, 3)))
        for ax in ("xcoor", "ycoor", "zcoor"):
            h5.create_dataset(ax, data=np.arange(3.0))
    with pytest.raises(SynthbosError, match=r"vel\.nc.*3 components"):
        load_density(path)
    with h5py.File(path, "a") as h5:
        del h5["zcoor"]
    with pytest.raises(SynthbosError, match="zcoor"):
        load_density(path)
    path2 = tmp_path / "uneven.nc"
    _write_jhtdb(path2, _volume(), netcdf=True)
    with h5py.File(path2, "a") as h5:
        del h5["xcoor"]
        h5.create_dataset("xcoor", data=np.array([0, 1, 2, 4, 5, 6.0]))
    with pytest.raises(SynthbosError, match="not uniformly"):
        load_density(path2)


def test_nrrd_with_spacing(tmp_path):
    data = _volume((3, 4, 5))
    path = tmp_path / "vol.nrrd"
    nrrd.write(str(path), data, {"spacings": [0.1, 0.2, 0.3]}, index_order="C")
    got = load_density(path)
    assert_array_equal(got.data, data)
    assert_allclose(got.spacing, [0.1, 0.2, 0.3])
    path2 = tmp_path / "dirs.nrrd"
    nrrd.write(
        str(path2),
        data,
        {"space": "left-posterior-superior", "space directions": np.diag([0.5, 0.25, 2.0])},
        index_order="C",
    )
    got = load_density(path2, slice_index=1, axis="x")
    assert_array_equal(got.data, data[:, :, 1])
    assert_allclose(got.spacing, [0.25, 2.0])  # (dy, dz) of an x-slice
    assert got.spacing_units == "file"
    mm = load_density(path2, slice_index=1, axis="y", spacing_mm=[1.0, 2.0, 3.0])
    assert mm.spacing == (1.0, 3.0) and mm.spacing_units == "mm"  # (dx, dz) of a y-slice
    with pytest.raises(SynthbosError, match=r"dirs\.nrrd: spacing_mm needs 1 or 3 values"):
        load_density(path2, spacing_mm=[1.0, 2.0])
    with pytest.raises(SynthbosError, match="spacing_mm must be finite and > 0"):
        load_density(path2, spacing_mm=0.0)


def test_npy_npz_hdf5(tmp_path):
    vol = _volume((3, 4, 5))
    np.save(tmp_path / "v.npy", vol)
    np.save(tmp_path / "s.npy", vol[0])
    np.savez(tmp_path / "v.npz", rho=vol, other=vol + 1)
    with h5py.File(tmp_path / "v.h5", "w") as h5:
        h5.create_dataset("group/rho", data=vol)
        h5.create_dataset("group/t", data=1.0)
    assert_array_equal(load_density(tmp_path / "v.npy").data, vol)
    s = load_density(tmp_path / "s.npy")
    assert s.data.shape == (4, 5) and s.spacing is None
    assert_array_equal(load_density(tmp_path / "v.npz", dataset="other").data, vol + 1)
    assert_array_equal(load_density(tmp_path / "v.h5", dataset="group/rho").data, vol)
    with pytest.raises(SynthbosError, match="choose one with dataset"):
        load_density(tmp_path / "v.npz")
    with pytest.raises(SynthbosError, match="choose one with dataset"):
        load_density(tmp_path / "v.h5")
    with pytest.raises(SynthbosError, match=r"v\.h5.*no dataset 'group/nope'"):
        load_density(tmp_path / "v.h5", dataset="group/nope")
    with pytest.raises(SynthbosError, match=r"v\.npz.*no array 'nope'"):
        load_density(tmp_path / "v.npz", dataset="nope")


def test_slices_and_subvolume(tmp_path):
    vol = _volume((4, 5, 6))
    np.save(tmp_path / "v.npy", vol)
    p = tmp_path / "v.npy"
    assert_array_equal(load_density(p, slice_index=1, axis="y").data, vol[:, 1, :])
    assert_array_equal(load_density(p, slice_index=-1, axis="x").data, vol[:, :, -1])
    sub = load_density(p, index_range=[[1, 5], [0, 3], None])
    assert_array_equal(sub.data, vol[:, 0:3, 1:5])
    both = load_density(p, slice_index=2, axis="z", index_range=[[1, 5], [2, 4], [0, 1]])
    assert_array_equal(both.data, vol[2, 2:4, 1:5])  # the z pair is ignored for a z slice
    with pytest.raises(SynthbosError, match="slice_index 9 outside"):
        load_density(p, slice_index=9, axis="z")
    with pytest.raises(SynthbosError, match=r"outside 0\.\.6 along x"):
        load_density(p, index_range=[[0, 7], None, None])
    with pytest.raises(SynthbosError, match="slice_index needs 3-D"):
        np.save(tmp_path / "s.npy", vol[0])
        load_density(tmp_path / "s.npy", slice_index=0)


def test_truncated_and_garbage_files(tmp_path):
    path = tmp_path / "big.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("rho", data=_volume((32, 32, 32)))
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(SynthbosError, match=r"big\.h5.*(not a readable HDF5|truncated)"):
        load_density(path, dataset="rho")
    junk = tmp_path / "junk.nc"
    junk.write_bytes(b"not an hdf5 file at all" * 10)
    with pytest.raises(SynthbosError, match=r"junk\.nc: not a readable HDF5"):
        load_density(junk)
    bad_npy = tmp_path / "bad.npy"
    np.save(bad_npy, _volume())
    bad_npy.write_bytes(bad_npy.read_bytes()[:100])
    with pytest.raises(SynthbosError, match=r"bad\.npy"):
        load_density(bad_npy)
    bad_nrrd = tmp_path / "bad.nrrd"
    bad_nrrd.write_text("NRRD0004\ntype: garbage\n\n")
    with pytest.raises(SynthbosError, match=r"bad\.nrrd: not a readable NRRD"):
        load_density(bad_nrrd)


@pytest.mark.parametrize(
    ("value", "message"),
    [(np.nan, "NaN/inf"), (np.inf, "NaN/inf"), (-0.1, "must be > 0"), (0.0, "must be > 0")],
)
def test_bad_values_are_named(tmp_path, value, message):
    vol = _volume()
    vol[1, 2, 3] = value
    np.save(tmp_path / "v.npy", vol)
    with pytest.raises(
        SynthbosError, match=rf"v\.npy: density .*{message}.*\(1, 2, 3\)|v\.npy: density.*{message}"
    ):
        load_density(tmp_path / "v.npy")
    _write_jhtdb(tmp_path / "c.nc", vol, netcdf=True)
    with pytest.raises(SynthbosError, match=rf"c\.nc \[Density_0001\]: density.*{message}"):
        load_density(tmp_path / "c.nc")


def test_wrong_dimensionality_missing_file_and_format(tmp_path):
    np.save(tmp_path / "line.npy", np.ones(5))
    np.save(tmp_path / "four.npy", np.ones((2, 2, 2, 2)))
    np.save(tmp_path / "thin.npy", np.ones((1, 5)))
    with pytest.raises(SynthbosError, match=r"line\.npy: density must be 2-D .* shape \(5,\)"):
        load_density(tmp_path / "line.npy")
    with pytest.raises(SynthbosError, match=r"four\.npy: density must be 2-D"):
        load_density(tmp_path / "four.npy")
    with pytest.raises(SynthbosError, match="at least 2 nodes"):
        load_density(tmp_path / "thin.npy")
    with pytest.raises(SynthbosError, match=r"nowhere\.h5: density file not found"):
        load_density(tmp_path / "nowhere.h5")
    (tmp_path / "x.dat").write_text("1")
    with pytest.raises(SynthbosError, match="cannot infer the format"):
        load_density(tmp_path / "x.dat")
    with pytest.raises(SynthbosError, match="unknown format"):
        load_density(tmp_path / "line.npy", format="tiff")
    with pytest.raises(SynthbosError, match="must be real numbers"):
        validate_density(np.array(["a", "b"]), where="x")


def test_snapshot_file_errors(tmp_path):
    with pytest.raises(SynthbosError, match="snapshot file not found"):
        read_snapshots(tmp_path / "none.h5")
    with h5py.File(tmp_path / "s.h5", "w") as h5:
        h5.create_dataset("density", data=np.ones((4, 4)))
    with pytest.raises(SynthbosError, match=r"s\.h5: /density must be \(snapshots, ny, nx\)"):
        read_snapshots(tmp_path / "s.h5")


def test_axis_order_reads_fortran_ordered_arrays(tmp_path):
    vol = _volume((4, 5, 6))  # (nz, ny, nx)
    np.save(tmp_path / "xyz.npy", vol.transpose(2, 1, 0))  # stored (nx, ny, nz), as Fortran output
    got = load_density(tmp_path / "xyz.npy", axis_order="xyz")
    assert_array_equal(got.data, vol)
    # slices, ranges and spacing name physical axes after the reordering
    s = load_density(tmp_path / "xyz.npy", axis_order="xyz", slice_index=2, axis="y", spacing_mm=[0.1, 0.2, 0.3])
    assert_array_equal(s.data, vol[:, 2, :])
    assert s.spacing == (0.1, 0.3)
    r = load_density(tmp_path / "xyz.npy", axis_order="XYZ", index_range=[[1, 4], None, [0, 2]])
    assert_array_equal(r.data, vol[0:2, :, 1:4])
    plane = vol[0]  # (ny, nx)
    np.save(tmp_path / "xy.npy", plane.T)
    assert_array_equal(load_density(tmp_path / "xy.npy", axis_order="xy").data, plane)
    assert_array_equal(load_density(tmp_path / "xy.npy", axis_order="yx").data, plane.T)
    # a file's own spacing follows the axes: NRRD spacings are listed x first for a C-ordered (z, y, x) array
    nrrd.write(str(tmp_path / "v.nrrd"), vol.transpose(2, 1, 0).copy(order="C"), {"spacings": [3.0, 2.0, 1.0]},
               index_order="C")
    n = load_density(tmp_path / "v.nrrd", axis_order="xyz")
    assert_array_equal(n.data, vol)
    assert n.spacing == (1.0, 2.0, 3.0)
    for bad in ("xy", "xxz", "abc", "zyxw"):
        with pytest.raises(SynthbosError, match="axis_order must name each"):
            load_density(tmp_path / "xyz.npy", axis_order=bad)
