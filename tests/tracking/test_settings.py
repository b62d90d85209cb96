"""The vocabulary's one home (tracking.settings): the kernels' constants come from its values, and the
names that lived in tracking.pipeline still reach the same objects."""

import numpy as np
import pytest
import warp as wp
from numpy.testing import assert_array_equal
from synthbos.tracking import identify_kernels, pipeline, predict_kernels, settings
from synthbos.tracking import kernel_constants as kc

from synthbos import SynthbosError


def test_kernel_constants_are_the_settings_values():
    pairs = [
        (kc.EDGE_CUT_MAX, settings.EDGE_CUT_PX),
        (kc.PIXEL_EDGE, settings.PIXEL_EDGE_PX),
        ((kc.WIDTH_LO, kc.WIDTH_HI), settings.THREE_POINT_WIDTH_RANGE),
        ((kc.CLIP_LO, kc.CLIP_HI), settings.RESIDUAL_WIDTH_CLIP),
        (kc.STAMP_WIDTHS, settings.RESIDUAL_STAMP_WIDTHS),
        (kc.DIAMETER_WIDTHS, settings.DIAMETER_PER_WIDTH),
        (predict_kernels.RESOLVED, settings.PREDICTOR_RESOLVED_PX),
        (predict_kernels.MIN_VALID_FRACTION, settings.PREDICTOR_MIN_VALID_FRACTION),
        (identify_kernels.SMALL_W, settings.SMALL_WINDOW),
    ]
    for constant, value in pairs:
        assert_array_equal(np.asarray(constant, dtype=np.float64), np.asarray(value, dtype=np.float64))
    # float64 constants, not Python floats that a kernel would read as float32
    assert all(type(c) is wp.float64 for c in (kc.EDGE_CUT_MAX, kc.WIDTH_LO, predict_kernels.RESOLVED))
    for bit in settings.DotStatus:
        if hasattr(kc, bit.name):
            assert getattr(kc, bit.name) == int(bit), bit.name


def test_the_pipeline_names_are_the_settings_objects():
    for name in ("TrackingSettings", "DotStatus", "TRACK_DTYPE", "is_valid", "window_sizes", "prior_inside"):
        assert getattr(pipeline, name) is getattr(settings, name), name


def test_window_geometry_of_a_3px_dot():
    eta0, half_r, half_g, map_half = settings.window_sizes(3.0, settings.TrackingSettings())
    assert (eta0, half_r, half_g, map_half) == (0.75, 3, 5, 2)  # ceil(1.5 + 1), ceil(1.5 + 1 + 2), ceil(2)
    inside = settings.prior_inside(np.array([[-0.49, 0.0], [-0.5, 0.0], [9.49, 4.49], [np.nan, 1.0]]), (5, 10))
    assert_array_equal(inside, [True, False, True, False])


def test_the_removed_backend_setting_is_refused_in_one_line():
    """The NumPy path is gone (its references live in tracking/reference.py, for the tests): a settings
    table that still names ``backend`` is refused with one line naming the key."""
    from synthbos.benchmarks.registry import METHODS

    assert "backend" not in settings.TrackingSettings.__dataclass_fields__
    with pytest.raises(SynthbosError, match=r"^unknown tracking setting\(s\) backend; known: ") as err:
        METHODS["tracking"].settings({"backend": "warp"})
    assert "\n" not in str(err.value)
