"""Pair and result files explain themselves: units and description on every dataset, flag bits as an
attribute, the user's umask on every output."""

import json
import os

import h5py
import numpy as np
import pytest
from numpy.testing import assert_allclose
from synthbos.benchmarks.process import FLAG_BITS, write_result
from synthbos.benchmarks.registry import GRID, MethodResult, get_method, method_names
from synthbos.correlation import VectorFlag
from synthbos.raytrace import render_pair, write_pair
from synthbos.tracking import TRACK_DTYPE, DotStatus

from synthbos import atomic_output


def _datasets(f):
    found = []
    f.visititems(lambda name, obj: found.append((name, obj)) if isinstance(obj, h5py.Dataset) else None)
    return found


def _assert_described(path):
    with h5py.File(path, "r") as f:
        sets = _datasets(f)
        assert sets
        for name, ds in sets:
            assert "units" in ds.attrs, name
            assert len(str(ds.attrs["description"])) > 10, name


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield 0o022
    os.umask(old)


def test_atomic_output_gives_the_users_umask(tmp_path, umask_022):
    with atomic_output(tmp_path / "a.txt") as tmp:
        tmp.write_text("x")
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o644
    os.umask(0o027)
    with atomic_output(tmp_path / "b.txt") as tmp:
        tmp.write_text("x")
    assert (tmp_path / "b.txt").stat().st_mode & 0o777 == 0o640


def test_pair_file_datasets_carry_units_and_description(tmp_path, umask_022):
    cfg = {"camera": {"pixels": [64, 64]}, "target": {"dots_per_32px": 8.0}, "rays": {"per_dot": 10}}
    write_pair(tmp_path / "p.h5", render_pair(cfg, device="cpu"))
    _assert_described(tmp_path / "p.h5")
    assert (tmp_path / "p.h5").stat().st_mode & 0o777 == 0o644
    with h5py.File(tmp_path / "p.h5") as f:
        assert f["dots/displacement_px"].attrs["units"] == "px"
        assert f["dots/target_xy_m"].attrs["units"] == "m"


def _fake_result(name):
    m = get_method(name)
    if m.kind == GRID:
        x, y = np.meshgrid(np.arange(3.0), np.arange(2.0))
        table = {"x": x, "y": y, "u": x * 0, "v": y * 0, "flags": np.zeros((2, 3), np.int32),
                 "peak_ratio": np.ones((2, 3))}
        xy = np.stack([x.ravel(), y.ravel()], axis=1)
        return MethodResult(name, xy, xy * 0, (2, 3), table, {})
    tab = np.zeros(4, dtype=TRACK_DTYPE)
    xy = np.zeros((4, 2))
    return MethodResult(name, xy, xy, None, {c: tab[c] for c in tab.dtype.names}, {})


@pytest.mark.parametrize("method", method_names())
def test_result_file_datasets_carry_units_description_and_flag_bits(tmp_path, method):
    write_result(tmp_path / "r.h5", _fake_result(method))
    _assert_described(tmp_path / "r.h5")
    with h5py.File(tmp_path / "r.h5") as f:
        flagged = [(name, ds) for name, ds in _datasets(f) if name.rpartition("/")[2] in FLAG_BITS]
        assert len(flagged) == 1
        for name, ds in flagged:
            bits = json.loads(ds.attrs["flag_bits"])
            assert bits, name
            assert all(int(b) & (int(b) - 1) == 0 and v["name"] and v["description"] for b, v in bits.items())


def test_flag_bits_cover_every_documented_flag():
    corr = {b: n for b, (n, _) in FLAG_BITS["flags"].items()}
    assert corr == {int(b): b.name for b in VectorFlag}
    assert all(d for _, d in FLAG_BITS["flags"].values())
    status = FLAG_BITS["status"]
    assert {b: n for b, (n, _) in status.items()} == {int(m.value): n for n, m in DotStatus.__members__.items()}
    assert "valid" in status[int(DotStatus.MATCHED)][1]
    assert all(d for _, d in status.values())


# ---------------------------------------------------------------- files that explain themselves (issue 29)

BLOB = {"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 20},
        "volume": {"source": "gaussian", "amplitude_kg_m3": 0.3, "sigma_mm": 1.5, "grid": [32, 32, 8]}}
# Words that mark a description written for no dataset in particular.
PLACEHOLDERS = ("see its documentation", "column '", "todo", "placeholder", "unknown")


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A pair file, its tracking-cc and correlation results, and their density files."""
    from synthbos.benchmarks.cli import main

    folder = tmp_path_factory.mktemp("explained")
    write_pair(folder / "pair.h5", render_pair(BLOB, device="cpu"))
    for method in ("tracking-cc", "correlation"):
        assert main(["process", str(folder / "pair.h5"), "--method", method, "-o", str(folder / f"{method}.h5"),
                     "--device", "cpu"]) == 0
        assert main(["integrate", str(folder / f"{method}.h5"), "--pair", str(folder / "pair.h5"),
                     "-o", str(folder / f"density-{method}.h5")]) == 0
    return folder


FILES = ("pair.h5", "tracking-cc.h5", "correlation.h5", "density-tracking-cc.h5", "density-correlation.h5")


@pytest.mark.parametrize("name", FILES)
def test_every_dataset_has_real_units_and_description(made, name):
    with h5py.File(made / name) as f:
        sets = _datasets(f)
        assert len(sets) >= 6
        for path, ds in sets:
            units, description = ds.attrs.get("units"), ds.attrs.get("description")
            assert isinstance(units, str) and units.strip() and units != "unknown", (path, units)
            assert isinstance(description, str) and len(description) > 20, (path, description)
            assert not any(p in description.lower() for p in PLACEHOLDERS), (path, description)


def test_the_schema_names_every_column_of_the_built_in_methods(made):
    from synthbos.benchmarks.process import RESULT_DATASETS

    assert {f"dots/{n}" for n in TRACK_DTYPE.names} <= set(RESULT_DATASETS)
    with h5py.File(made / "correlation.h5") as f:
        assert {n for n, _ in _datasets(f)} <= set(RESULT_DATASETS)
    assert RESULT_DATASETS["dots/u_pred"][0] == "px" and RESULT_DATASETS["dots/pred_correlation"][0] == "1"


def test_files_open_in_xarray_with_named_dimensions(made):
    import xarray as xr  # with h5netcdf, in the test extra

    def open_(name, group=None):
        return xr.open_dataset(made / name, engine="h5netcdf", group=group, phony_dims="access")

    with open_("pair.h5", "images") as ds, h5py.File(made / "pair.h5") as f:
        assert ds["reference"].dims == ("y", "x") and ds.sizes == {"y": 96, "x": 96}
        assert_allclose(ds["x"].values, np.arange(96.0))
        n = len(f["dots/valid"])
    with open_("pair.h5", "dots") as ds:
        assert ds["displacement_px"].dims == ("dot", "component") and list(ds["component"].values) == ["x", "y"]
        assert ds["ray_covariance_px2"].dims == ("dot", "covariance")
        assert ds["ray_third_moment_px3"].dims == ("dot", "moment")
        assert ds["valid"].dims == ("dot",) and ds.sizes["dot"] == n
    with open_("tracking-cc.h5", "dots") as ds:
        assert {v.dims for v in ds.data_vars.values()} == {("dot",)}
        assert ds["u"].attrs["units"] == "px"
    with open_("correlation.h5") as ds, h5py.File(made / "correlation.h5") as f:
        assert ds["u"].dims == ("grid_y", "grid_x") and ds["flags"].dims == ("grid_y", "grid_x")
        assert_allclose(ds["grid_x"].values, f["x"][0])
        assert_allclose(ds["grid_y"].values, f["y"][:, 0])
    for name in ("density-tracking-cc.h5", "density-correlation.h5"):
        with open_(name) as ds, h5py.File(made / name) as f:
            assert ds["density_kg_m3"].dims == ("y_mm", "x_mm")
            assert ds["truth_cone_kg_m3"].dims == ("y_mm", "x_mm") and ds["x_px"].dims == ("x_mm",)
            assert_allclose(ds["x_mm"].values, f["x_mm"][()])


def test_the_result_readers_skip_the_dimension_scales(made):
    from synthbos.benchmarks.process import read_result

    dots, _ = read_result(made / "tracking-cc.h5")
    grid, _ = read_result(made / "correlation.h5")
    assert "dot" not in dots.table and not {"grid_x", "grid_y"} & set(grid.table)


def _tiffs(pair, folder):
    import tifffile

    tifffile.imwrite(folder / "ref.tif", np.asarray(pair.reference, np.float32))
    tifffile.imwrite(folder / "grad.tif", np.asarray(pair.gradient, np.float32))
    return ["--reference", str(folder / "ref.tif"), "--gradient", str(folder / "grad.tif")]


def test_dot_id_names_the_priors_row(made, tmp_path):
    from synthbos.benchmarks.cli import main
    from synthbos.raytrace import read_pair

    pair = read_pair(made / "pair.h5")
    # A pair prior: the pair's dot index.
    with h5py.File(made / "tracking-cc.h5") as f:
        dot_id, x, y, ok = (f[f"dots/{k}"][()] for k in ("dot_id", "x", "y", "valid"))
    assert_allclose(dot_id, np.arange(pair.n_dots))
    ok = ok.astype(bool)
    assert ok.sum() > 0.9 * pair.n_dots
    assert np.hypot(x[ok] - pair.reference_px[ok, 0], y[ok] - pair.reference_px[ok, 1]).max() < 0.1
    # A --dots CSV: its data rows, here 40 of the pair's dots in another order.
    rows = np.random.default_rng(4).permutation(np.flatnonzero(ok))[:40]
    csv = tmp_path / "dots.csv"
    csv.write_text("x,y\n" + "".join(f"{a:.17g},{b:.17g}\n" for a, b in pair.reference_px[rows]))
    assert main(["process", str(made / "pair.h5"), "--method", "tracking-cc", "--dots", str(csv),
                 "-o", str(tmp_path / "csv.h5"), "--device", "cpu"]) == 0
    with h5py.File(tmp_path / "csv.h5") as f:
        dot_id, x, ok = f["dots/dot_id"][()], f["dots/x"][()], f["dots/valid"][()].astype(bool)
    assert_allclose(dot_id, np.arange(40))
    assert ok.sum() >= 36 and np.abs(x[ok] - pair.reference_px[rows[ok], 0]).max() < 0.1
    # No prior (camera images without --dots): -1 everywhere.
    assert main(["process", *_tiffs(pair, tmp_path), "--method", "tracking-cc", "-o", str(tmp_path / "none.h5"),
                 "--device", "cpu"]) == 0
    with h5py.File(tmp_path / "none.h5") as f:
        assert len(f["dots/dot_id"]) > 0.5 * pair.n_dots and (f["dots/dot_id"][()] == -1).all()
