"""The method registry: names select implementations, settings and the paper's tracking procedure."""

import dataclasses

import numpy as np
import pytest
from numpy.testing import assert_array_equal
from synthbos.benchmarks.registry import METHODS, default_methods, get_method, method_names
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import TrackingSettings, track_pair

from synthbos import SynthbosError


def test_every_entry_is_complete_and_styles_are_distinct():
    for m in METHODS.values():
        assert m.kind in ("grid", "dots", "dense") and callable(m.run) and m.label and m.settings_key
    styles = {(m.color, str(m.linestyle), m.marker) for m in METHODS.values()}
    assert len(styles) == len(METHODS)  # no two methods draw alike
    assert len({m.color for m in METHODS.values()}) == len(METHODS)
    assert set(default_methods()) == {"correlation", "tracking", "tracking-cc"}
    assert set(default_methods()) < set(method_names())


def test_a_method_without_a_settings_key_reads_the_table_of_its_name():
    """A plugin that names no ``settings_key`` (docs/plugins.md: by default the name) holds its name there,
    so the registry's checks hold with a plugin installed."""
    mine = dataclasses.replace(get_method("correlation"), name="phase-correlation", settings_key="")
    assert mine.settings_key == "phase-correlation"
    assert dataclasses.replace(mine, name="other").settings_key == "phase-correlation"  # once set, kept


def test_settings_from_overrides_and_unknown_keys():
    assert get_method("tracking").settings() == TrackingSettings()
    assert get_method("tracking-paper").settings() == TrackingSettings.paper()
    assert get_method("tracking-cc-paper").settings({"max_iterations": 2}) == TrackingSettings.paper(max_iterations=2)
    with pytest.raises(SynthbosError, match="unknown tracking-paper setting"):
        get_method("tracking-paper").settings({"no_such_key": 1})
    with pytest.raises(SynthbosError, match="unknown method"):
        get_method("no-such-method")


def test_paper_entry_runs_the_paper_procedure():
    rng = np.random.default_rng(5)
    shape = (96, 96)
    xy = rng.uniform(8, 88, size=(60, 2))
    xy = xy[np.min(np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(60) * 99, axis=1) > 3.5]
    ref = draw_dots(shape, xy, 3.0)
    grad = draw_dots(shape, xy + np.array([0.3, -0.2]), 3.0)
    m = get_method("tracking-cc-paper")
    res = m.run(ref, grad, prior_xy=xy, settings=m.settings())
    tab = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings.paper())
    assert_array_equal(res.uv, np.stack([tab["u_cc"], tab["v_cc"]], axis=1))
    assert res.settings["centroid"] == "gaussian3" and res.settings["correction"] == "paper"
