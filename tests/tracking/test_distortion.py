"""Distorted dots: the first-moment step measures the mean landing position of a dot's rays.

Ground truth by synthesis (``_synth.distorted_dots``): each gradient-image dot is the spot drawn at the
landing points of rays through a unit aperture, displaced across a sharp interface, so its image is
skewed and its mean landing position (the truth a renderer records) is not where a symmetric model
centres it.
"""

import numpy as np
import pytest
from _synth import distorted_dots, dot_pattern, smooth_displacement
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import DotStatus, TrackingSettings, is_valid, track_pair
from synthbos.tracking.batch import track_pairs
from synthbos.tracking.dotfit import fit_dots, fit_window_half, moment_shifts
from synthbos.tracking.reference import moment_shifts_numpy

SHAPE = (128, 128)


def _pair(seed, *, per_32x32=8.0, min_distance=4.0, strength=0.4):
    rng = np.random.default_rng(seed)
    xy = dot_pattern(rng, SHAPE, per_32x32=per_32x32, min_distance=min_distance)
    reference = draw_dots(SHAPE, xy, 3.0)
    gradient, mean = distorted_dots(rng, SHAPE, xy + smooth_displacement(xy, SHAPE, 1.0), strength=strength)
    return reference, gradient, xy, mean - xy


def _errors(table, truth, *, cc=False):
    u, v = ("u_cc", "v_cc") if cc else ("u", "v")
    ok = is_valid(table["status"])
    return np.hypot(table[u] - truth[:, 0], table[v] - truth[:, 1])[ok], ok


def test_moment_shifts_device_equals_numpy(device):
    reference, gradient, xy, truth = _pair(1)
    n = len(xy)
    half, render_half = fit_window_half(0.75)
    start = np.column_stack([np.r_[xy, xy + truth], np.ones(2 * n), np.full(2 * n, 0.75), np.zeros(2 * n)])
    frame = np.r_[np.zeros(n, int), np.ones(n, int)]
    partner = np.r_[np.arange(n) + n, np.arange(n)]
    params, _, _ = fit_dots([reference, gradient], start, half=half, render_half=render_half, frame=frame,
                            partner=partner, iterations=3, device=device)  # fmt: skip
    kw = {"half": render_half, "frame": frame, "partner": partner, "noise": (0.0, 0.0)}
    d_ref, a_ref = moment_shifts_numpy([reference, gradient], params, **kw)
    d, a = moment_shifts([reference, gradient], params, device=device, **kw)
    assert_array_equal(a, a_ref)
    assert_allclose(d, d_ref, atol=1e-10)
    assert a[n:].mean() > 0.9  # the skewed gradient dots move
    assert_array_equal(a[:n], a[n:])  # with their reference partners: a pair is measured alike
    assert np.abs(d[:n]).max() < 2e-3  # whose first moments are their (exact) centres


def test_moment_step_measures_the_mean_landing_position():
    """Isolated enough dots (8 per 32x32 px, >= 4 px apart) with a bias of ~0.01 px p50 for the symmetric
    fit: the first moment removes it to the 1e-3 px level, in both estimators."""
    reference, gradient, xy, truth = _pair(3)
    moment = track_pair(reference, gradient, prior_xy=xy)
    symmetric = track_pair(reference, gradient, prior_xy=xy, settings=TrackingSettings(distortion="none"))
    for cc in (False, True):
        e_m, ok_m = _errors(moment, truth, cc=cc)
        e_s, _ = _errors(symmetric, truth, cc=cc)
        assert ok_m.all()
        assert np.percentile(e_s, 90) > 0.010, np.percentile(e_s, 90)
        assert np.percentile(e_m, 90) < 0.004, np.percentile(e_m, 90)
        assert np.percentile(e_m, 99) < 0.008, np.percentile(e_m, 99)
    flagged = (moment["status"] & DotStatus.DISTORTED) != 0
    assert flagged.mean() > 0.95
    assert not ((symmetric["status"] & DotStatus.DISTORTED) != 0).any()


def test_undistorted_noisy_dots_keep_the_fit():
    """Exact dots under 2 % noise: the shift is significant for (almost) none, so the fit's Cramer-Rao
    precision stays; the rows it leaves alone are those of the symmetric fit, bit for bit."""
    rng = np.random.default_rng(5)
    xy = dot_pattern(rng, (192, 192), per_32x32=20, min_distance=3.0)
    disp = smooth_displacement(xy, (192, 192), 1.5)
    reference = draw_dots((192, 192), xy, 3.0) + 0.02 * rng.standard_normal((192, 192))
    gradient = draw_dots((192, 192), xy + disp, 3.0) + 0.02 * rng.standard_normal((192, 192))
    moment = track_pair(reference, gradient, prior_xy=xy)
    symmetric = track_pair(reference, gradient, prior_xy=xy, settings=TrackingSettings(distortion="none"))
    moved = (moment["status"] & DotStatus.DISTORTED) != 0
    assert moved.sum() <= 0.002 * len(xy), moved.sum()
    same = ~moved
    assert_array_equal(moment["u"][same], symmetric["u"][same])
    assert_array_equal(moment["status"][same], symmetric["status"][same])


def test_track_pairs_equals_track_pair_on_distorted_dots(device):
    pairs = [_pair(seed, per_32x32=14.0, min_distance=3.0) for seed in (7, 8)]
    refs = np.array([p[0] for p in pairs])
    grads = np.array([p[1] for p in pairs])
    prior = np.array([p[2][: min(len(q[2]) for q in pairs)] for p in pairs])
    tables = track_pairs(refs, grads, prior_xy=prior, device=device)
    for b in range(len(pairs)):
        single = track_pair(refs[b], grads[b], prior_xy=prior[b], device=device)
        assert_array_equal(tables[b]["status"], single["status"])
        assert ((single["status"] & DotStatus.DISTORTED) != 0).mean() > 0.9
        for name in ("x", "y", "u", "v", "u_cc", "v_cc", "x_gradient", "y_gradient"):
            assert_allclose(tables[b][name], single[name], rtol=0, atol=1e-9, err_msg=name)


@pytest.mark.parametrize("distortion", ["sideways", "bad"])
def test_settings_are_checked(distortion):
    from synthbos import SynthbosError

    with pytest.raises(SynthbosError, match="distortion"):
        TrackingSettings(distortion=distortion)
    with pytest.raises(SynthbosError, match="distortion_chi2"):
        TrackingSettings(distortion_chi2=-1.0)
