"""Named set-ups (``raytrace.SETUPS``): each loads, changes only what its file says, and renders a pair."""

import tomllib
from importlib import resources

import numpy as np
import pytest
from _small import small_config
from numpy.testing import assert_allclose
from synthbos.raytrace import DEFAULT_CONFIG, SETUPS, load_config, render_pair, setup_tables
from synthbos.raytrace.config import merge_tables

from synthbos import SynthbosError

NAMED = [name for name in SETUPS if name != "default"]


def _differences(a, b):
    return {(t, k) for t in a for k in a[t] if a[t][k] != b.get(t, {}).get(k)}


def test_default_setup_is_the_default():
    assert setup_tables("default") == {}
    assert load_config(setup="default") == load_config()


@pytest.mark.parametrize("name", NAMED)
def test_named_setup_changes_only_its_own_keys(name):
    text = resources.files("synthbos.raytrace").joinpath(SETUPS[name][0]).read_text()
    tables = tomllib.loads(text)
    assert setup_tables(name) == tables
    cfg, base = load_config(setup=name), load_config()
    assert _differences(cfg, base) == {(t, k) for t in tables for k in tables[t]}
    for table, values in tables.items():
        for key, value in values.items():
            assert cfg[table][key] == value
    # a configuration given with the set-up changes the set-up, not the default
    over = load_config({"camera": {"pixels": [64, 48]}}, setup=name)
    assert over["camera"]["pixels"] == [64, 48]
    assert _differences(over, cfg) == {("camera", "pixels")}


def test_narrow_setup_is_the_default_at_f32_with_four_times_the_contrast():
    cfg = load_config(setup="narrow")
    assert cfg["camera"]["f_number"] == 32.0
    assert_allclose(cfg["volume"]["density_scale_kg_m3"], 4 * DEFAULT_CONFIG["volume"]["density_scale_kg_m3"])


def test_unknown_setup_is_one_clear_error():
    with pytest.raises(SynthbosError, match=r"unknown set-up 'paper2'; named set-ups: default, narrow"):
        load_config(setup="paper2")


def test_merge_tables_later_layers_win_and_inputs_stay():
    a = {"camera": {"f_number": 32.0, "lens": "thin"}}
    b = {"camera": {"f_number": 8.0}, "rays": {"per_dot": 3}}
    assert merge_tables(a, b) == {"camera": {"f_number": 8.0, "lens": "thin"}, "rays": {"per_dot": 3}}
    assert a == {"camera": {"f_number": 32.0, "lens": "thin"}}


@pytest.mark.parametrize("name", NAMED)
def test_named_setup_renders_a_tiny_pair(name):
    """The named set-up renders; its density contrast scales the displacement of the same dots and rays seen
    with the same camera (Eq. 4 is linear in the density gradient; the rays bend by less than 1e-3 rad)."""
    cfg = load_config(setup=name)
    tiny = small_config(camera={"pixels": [64, 64]}, rays={"per_dot": 60})
    pair = render_pair(load_config(tiny, setup=name), device="cpu")
    same_camera = render_pair(merge_tables(tiny, {"camera": setup_tables(name).get("camera", {})}), device="cpu")
    assert pair.valid.sum() > 0.9 * pair.n_dots
    assert_allclose(pair.target_xy_m, same_camera.target_xy_m)
    assert_allclose(pair.reference_px, same_camera.reference_px, atol=1e-5)
    scale = cfg["volume"]["density_scale_kg_m3"] / DEFAULT_CONFIG["volume"]["density_scale_kg_m3"]
    ok = pair.valid & same_camera.valid
    d, d1 = pair.displacement_px[ok], same_camera.displacement_px[ok]
    assert np.abs(d).max() > 0.05
    assert_allclose(d, scale * d1, rtol=0, atol=0.01 * np.abs(d).max())
    assert f"f_number = {cfg['camera']['f_number']!r}" in pair.attrs["config"]
