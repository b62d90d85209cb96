"""Named set-ups (``raytrace.SETUPS``): each loads, changes only what its file says, and renders a pair."""

import tomllib
from importlib import resources

import numpy as np
import pytest
from _small import small_config
from numpy.testing import assert_allclose
from synthbos.raytrace import SETUPS, load_config, render_pair, setup_tables
from synthbos.raytrace.config import merge_tables
from synthbos.raytrace.pairfile import in_cone_spread_px

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


def test_narrow_setup_is_the_default_at_f32():
    assert setup_tables("narrow") == {"camera": {"f_number": 32.0}}


def test_unknown_setup_is_one_clear_error():
    with pytest.raises(SynthbosError, match=r"unknown set-up 'paper2'; named set-ups: default, narrow"):
        load_config(setup="paper2")


def test_merge_tables_later_layers_win_and_inputs_stay():
    a = {"camera": {"f_number": 32.0, "lens": "thin"}}
    b = {"camera": {"f_number": 8.0}, "rays": {"per_dot": 3}}
    assert merge_tables(a, b) == {"camera": {"f_number": 8.0, "lens": "thin"}, "rays": {"per_dot": 3}}
    assert a == {"camera": {"f_number": 32.0, "lens": "thin"}}


def test_narrow_setup_renders_a_narrower_cone():
    """The same dots and rays through the default and the narrow set-up: the narrow cone averages the flow over
    less of itself, so the displacement is stronger and closer to the chief ray's Eq. 4, the dots less spread."""
    tiny = small_config(camera={"pixels": [64, 64]}, rays={"per_dot": 100})
    wide, narrow = render_pair(tiny, device="cpu"), render_pair(load_config(tiny, setup="narrow"), device="cpu")
    assert narrow.valid.sum() > 0.9 * narrow.n_dots
    assert "f_number = 32.0" in narrow.attrs["config"]
    assert_allclose(narrow.target_xy_m, wide.target_xy_m)
    assert_allclose(narrow.reference_px, wide.reference_px, atol=1e-4)  # the ideal lens images a dot alike
    ok = narrow.valid & wide.valid

    def rms(a):
        return float(np.sqrt(np.mean(np.sum(a[ok] ** 2, axis=1))))

    strength = rms(narrow.displacement_px) / rms(wide.displacement_px)
    assert 1.5 < strength < 3.0
    gap_narrow = rms(narrow.displacement_px - narrow.theory_px) / rms(narrow.theory_px)
    gap_wide = rms(wide.displacement_px - wide.theory_px) / rms(wide.theory_px)
    assert gap_narrow < 0.7 * gap_wide
    spread_narrow, spread_wide = in_cone_spread_px(narrow)[ok], in_cone_spread_px(wide)[ok]
    assert np.median(spread_narrow) < 0.7 * np.median(spread_wide)
    # both truths stay the renderer's: the traced displacement equals the cone-averaged Eq. 4
    assert rms(narrow.displacement_px - narrow.theory_cone_px) < 0.01 * rms(narrow.displacement_px)
