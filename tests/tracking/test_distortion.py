"""Distorted dots: the first-moment and elliptical moment steps measure the mean landing position of a
dot's rays.

Ground truth by synthesis (``_synth.distorted_dots``): each gradient-image dot is the spot drawn at the
landing points of rays through a unit aperture, displaced across a sharp interface, so its image is
skewed and its mean landing position (the truth a renderer records) is not where a symmetric model
centres it.
"""

import numpy as np
import pytest
from _synth import distorted_dots, dot_pattern, fitted_pair, smooth_displacement
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import DotStatus, TrackingSettings, is_valid, track_pair
from synthbos.tracking.dotfit import fit_window_half, moment_shifts
from synthbos.tracking.reference import moment_shifts_numpy
from synthbos.tracking.stack import track_pairs

SHAPE = (128, 128)


def _pair(seed, *, per_32x32=8.0, min_distance=4.0, strength=0.4, margin=3.0):
    rng = np.random.default_rng(seed)
    xy = dot_pattern(rng, SHAPE, per_32x32=per_32x32, min_distance=min_distance, margin=margin)
    reference = draw_dots(SHAPE, xy, 3.0)
    gradient, mean = distorted_dots(rng, SHAPE, xy + smooth_displacement(xy, SHAPE, 1.0), strength=strength)
    return reference, gradient, xy, mean - xy


def _errors(table, truth, *, cc=False):
    u, v = ("u_cc", "v_cc") if cc else ("u", "v")
    ok = is_valid(table["status"])
    return np.hypot(table[u] - truth[:, 0], table[v] - truth[:, 1])[ok], ok


@pytest.mark.parametrize("ellipse", [False, True])
def test_moment_shifts_device_equals_numpy(device, ellipse):
    """Crowded dots (14 per 32x32 px, >= 3 px apart), some whose stamps cross the image edge."""
    reference, gradient, xy, truth = _pair(1, per_32x32=14.0, min_distance=3.0, margin=1.0)
    n = len(xy)
    params, kw = fitted_pair(reference, gradient, xy, truth, device)
    _, render_half = fit_window_half(0.75)
    crossing = ((np.rint(params[n:, :2]) < render_half) | (np.rint(params[n:, :2]) > 127 - render_half)).any(axis=1)
    d_ref, a_ref = moment_shifts_numpy([reference, gradient], params, ellipse=ellipse, **kw)
    d, a = moment_shifts([reference, gradient], params, device=device, ellipse=ellipse, **kw)
    assert_array_equal(a, a_ref)
    assert_allclose(d, d_ref, atol=1e-10)
    assert a[n:].mean() > 0.95  # the skewed gradient dots move
    assert crossing.sum() >= 3 and a[n:][crossing].all()  # those at the border too (their stamps filled)
    assert_array_equal(a[:n], a[n:])  # with their reference partners: a pair is measured alike
    assert np.abs(d[:n]).max() < 2e-3  # whose first moments are their (exact) centres


def test_ellipse_step_measures_crowded_distorted_dots():
    """Crowded distorted dots (14 per 32x32 px, >= 3 px apart): the symmetric models' shares hand part of
    each dot's spread light to its neighbours; the elliptical shares follow it. Gradient-image centres
    against the mean landing positions, the fit started at the truth: p90 0.012 px with the first-moment
    step, 0.004 px with the elliptical one."""
    reference, gradient, xy, truth = _pair(1, per_32x32=14.0, min_distance=3.0)
    n = len(xy)
    params, kw = fitted_pair(reference, gradient, xy, truth, "cpu")
    errors = {}
    for ellipse in (False, True):
        d, _ = moment_shifts([reference, gradient], params, device="cpu", ellipse=ellipse, **kw)
        errors[ellipse] = np.hypot(*(params[n:, :2] + d[n:] - (xy + truth)).T)
    assert np.percentile(errors[False], 90) > 0.010, np.percentile(errors[False], 90)
    assert np.percentile(errors[True], 90) < 0.006, np.percentile(errors[True], 90)
    assert np.percentile(errors[True], 99) < 0.014, np.percentile(errors[True], 99)


@pytest.mark.parametrize(
    ("seed", "distortion", "p90", "p99"),
    [(3, "ellipse", 0.0065, 0.018), (11, "ellipse", 0.0065, 0.018), (3, "kernel", 0.009, 0.022),
     (11, "kernel", 0.009, 0.022)],
)  # fmt: skip
def test_distortion_steps_in_track_pair(seed, distortion, p90, p99):
    """The tracker end to end on crowded dots, each distorted by its own random elliptical spread: the
    elliptical and the shared-kernel (default) steps against the first-moment step, both estimators
    (first-moment p90 0.010-0.012 px; elliptical 0.004-0.005 px; shared kernels 0.006-0.007 px, p99
    0.013-0.019 px: a kernel shared by neighbours that are distorted unlike each other fits neither as well
    as each dot's own ellipse does; on rendered flows, whose neighbours share their distortion, the kernel
    step is the better one, ``tests/benchmarks/test_distortion_bench.py``)."""
    reference, gradient, xy, truth = _pair(seed, per_32x32=14.0, min_distance=3.0)
    table = track_pair(reference, gradient, prior_xy=xy, settings=TrackingSettings(distortion=distortion))
    moment = track_pair(reference, gradient, prior_xy=xy, settings=TrackingSettings(distortion="moment"))
    for cc in (False, True):
        e, ok = _errors(table, truth, cc=cc)
        e_m, _ = _errors(moment, truth, cc=cc)
        assert ok.all()
        assert np.percentile(e, 90) < p90, np.percentile(e, 90)
        assert np.percentile(e, 99) < p99, np.percentile(e, 99)
        assert np.percentile(e, 90) < 0.75 * np.percentile(e_m, 90)


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


@pytest.mark.parametrize("distortion", ["ellipse", "moment"])
def test_undistorted_noisy_dots_keep_the_fit(distortion):
    """Exact dots under 2 % noise: the shift is significant for (almost) none, so the fit's Cramer-Rao
    precision stays; the rows it leaves alone are those of the symmetric fit, bit for bit."""
    rng = np.random.default_rng(5)
    xy = dot_pattern(rng, (192, 192), per_32x32=20, min_distance=3.0)
    disp = smooth_displacement(xy, (192, 192), 1.5)
    reference = draw_dots((192, 192), xy, 3.0) + 0.02 * rng.standard_normal((192, 192))
    gradient = draw_dots((192, 192), xy + disp, 3.0) + 0.02 * rng.standard_normal((192, 192))
    moment = track_pair(reference, gradient, prior_xy=xy, settings=TrackingSettings(distortion=distortion))
    symmetric = track_pair(reference, gradient, prior_xy=xy, settings=TrackingSettings(distortion="none"))
    moved = (moment["status"] & DotStatus.DISTORTED) != 0
    assert moved.sum() <= 0.002 * len(xy), moved.sum()
    same = ~moved
    assert_array_equal(moment["u"][same], symmetric["u"][same])
    assert_array_equal(moment["status"][same], symmetric["status"][same])


def test_track_pairs_equals_track_pair_on_distorted_dots(device):
    """With the default (elliptical) step, which moves nearly every dot here."""
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
