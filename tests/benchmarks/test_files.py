"""Pair and result files explain themselves: units and description on every dataset, flag bits as an
attribute, the user's umask on every output."""

import json
import os

import h5py
import numpy as np
import pytest
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
