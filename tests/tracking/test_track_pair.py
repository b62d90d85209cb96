"""The whole tracker on synthetic pairs: yield, accuracy against the Cramer-Rao bound, hard cases,
bad input."""

import numpy as np
import pytest
from _steps import assert_steps_agree, record_steps
from _synth import dot_pattern, jittered_grid, smooth_displacement
from numpy.testing import assert_allclose
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import TRACK_DTYPE, DotStatus, TrackingSettings, fit_soloff, is_valid, track_pair

from synthbos import SynthbosError

SHAPE = (256, 256)
D = 3.0
FLOATS = ("x", "y", "u", "v", "u_cc", "v_cc", "x_gradient", "y_gradient", "diameter", "peak")


def _pair(rng, xy, disp, *, noise=0.0, shape=SHAPE, gradient_xy=None, background=None):
    ref = draw_dots(shape, xy, D)
    grad = draw_dots(shape, xy + disp if gradient_xy is None else gradient_xy, D)
    if background is not None:
        ref, grad = ref + background, grad + background
    ref = ref + noise * rng.standard_normal(shape)
    grad = grad + noise * rng.standard_normal(shape)
    return ref, grad


def _check_no_nan_in_valid(res):
    ok = is_valid(res["status"])
    for name in FLOATS:
        assert np.isfinite(res[name][ok]).all(), f"NaN in field {name} of a valid row"
    assert (res["status"][ok] & DotStatus.FOUND_REFERENCE).all()
    assert (res["status"][ok] & DotStatus.FOUND_GRADIENT).all()
    for name in ("u", "v", "u_cc", "v_cc"):
        assert np.isnan(res[name][~ok]).all()
    return ok


def _rms(res, disp, ok, key="cc"):
    if key == "cc":
        e = np.r_[res["u_cc"] - disp[:, 0], res["v_cc"] - disp[:, 1]]
    else:
        e = np.r_[res["u"] - disp[:, 0], res["v"] - disp[:, 1]]
    return float(np.sqrt(np.mean(e[np.r_[ok, ok]] ** 2)))


@pytest.mark.parametrize("noise", [0.0, 0.01, 0.03, 0.05])
def test_yield_at_20_dots_per_32px_with_prior(noise):
    rng = np.random.default_rng(10)
    xy = dot_pattern(rng, SHAPE, per_32x32=20, min_distance=D)
    disp = smooth_displacement(xy, SHAPE, 1.5)
    ref, grad = _pair(rng, xy, disp, noise=noise)
    res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=D))
    assert res.dtype == TRACK_DTYPE and len(res) == len(xy)
    ok = _check_no_nan_in_valid(res)
    rms = _rms(res, disp, ok)
    bound = np.sqrt(2) * 0.8 * noise
    print(
        f"dense, noise {noise:.0%}: yield {ok.mean():.4f} of {len(xy)} dots, u_cc rms {rms:.4f} px "
        f"(isolated-dot CRLB {bound:.4f})"
    )
    assert ok.mean() >= 0.995, f"yield {ok.mean():.4f}"
    assert_allclose(res["x"][ok], xy[ok, 0], atol=0.5)
    # Dots 3 px apart overlap in their tails, so this is looser than the isolated-dot bound.
    assert rms < 2.0 * bound + 0.03, f"u_cc rms {rms:.4f} px"


@pytest.mark.parametrize("noise", [0.0, 0.01, 0.03, 0.05])
def test_correlation_correction_within_1p5_crlb(noise):
    """Isolated dots: RMS of u_cc, v_cc against 1.5 x sqrt(2) x 0.8 sigma_n / I0."""
    rng = np.random.default_rng(11)
    xy = jittered_grid(rng, (320, 320), spacing=10.0)
    disp = smooth_displacement(xy, (320, 320), 1.5)
    ref, grad = _pair(rng, xy, disp, noise=noise, shape=(320, 320))
    res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=D))
    ok = _check_no_nan_in_valid(res)
    rms_cc, rms_c = _rms(res, disp, ok, "cc"), _rms(res, disp, ok, "centroid")
    bound = np.sqrt(2) * 0.8 * noise  # per component, peak intensity I0 = 1
    msg = (
        f"noise {noise:.0%} of I0: u_cc rms {rms_cc:.4f} px, centroid-difference rms {rms_c:.4f} px, "
        f"displacement CRLB {bound:.4f} px, 1.5 x CRLB {1.5 * bound:.4f} px ({2 * ok.sum()} components)"
    )
    print(msg)
    assert ok.all(), msg
    if noise == 0:
        assert rms_cc < 0.006, msg  # the correlation peak fit's own systematic error
    else:
        assert rms_cc <= 1.5 * bound, msg
        assert rms_cc < rms_c, msg


# (separation range in px, position rms bound, u_cc rms bound): overlap biases both dots towards each other.
OVERLAP_CASES = [((2.0, 2.5), 0.35, 0.6), ((2.5, 3.0), 0.12, 0.2), ((3.0, 3.5), 0.05, 0.08)]


@pytest.mark.parametrize(("sep_range", "pos_bound", "cc_bound"), OVERLAP_CASES)
def test_overlapping_dots_are_separated(sep_range, pos_bound, cc_bound):
    rng = np.random.default_rng(12)
    centres = jittered_grid(rng, SHAPE, spacing=16.0, margin=8)
    angle = rng.uniform(0, 2 * np.pi, len(centres))
    sep = rng.uniform(*sep_range, len(centres))
    off = 0.5 * sep[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    xy = np.vstack([centres - off, centres + off])
    disp = smooth_displacement(xy, SHAPE, 1.0)
    ref, grad = _pair(rng, xy, disp, noise=0.01)
    res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=D))
    ok = _check_no_nan_in_valid(res)
    err = np.hypot(res["x"] - xy[:, 0], res["y"] - xy[:, 1])[ok]
    pos = float(np.sqrt(np.mean(err**2)))
    rms = _rms(res, disp, ok)
    over = (res["status"] & DotStatus.OVERLAPPED) != 0
    later = res["iteration"] > 1
    msg = (
        f"pairs {sep_range[0]}-{sep_range[1]} px apart (d = {D}): yield {ok.mean():.4f}, "
        f"position rms {pos:.4f} px (bound {pos_bound}), u_cc rms {rms:.4f} px (bound {cc_bound}), "
        f"overlapped flag {over.mean():.3f}, "
        f"found after iteration 1: {later.mean():.3f}"
    )
    print(msg)
    assert ok.mean() >= 0.99, msg
    assert pos < pos_bound, msg
    assert rms < cc_bound, msg
    assert over.mean() > 0.9, msg


def test_missing_dots_are_flagged_not_nan():
    rng = np.random.default_rng(13)
    xy = dot_pattern(rng, SHAPE, per_32x32=20, min_distance=D)
    disp = smooth_displacement(xy, SHAPE, 1.0)
    gone = rng.random(len(xy)) < 0.05
    ref, grad = _pair(rng, xy, disp, noise=0.02, gradient_xy=(xy + disp)[~gone])
    res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=D))
    ok = _check_no_nan_in_valid(res)
    lost = ~ok
    print(f"{gone.sum()} dots vanished: {(gone & ~ok).sum()} reported unmatched, {(~gone & ~ok).sum()} others lost")
    assert (gone & ok).sum() <= 0.02 * gone.sum(), "vanished dots reported as matched"
    assert (~gone & lost).mean() < 0.005
    assert (res["status"][gone] & DotStatus.FOUND_REFERENCE).all()
    assert np.isnan(res["x_gradient"][gone & lost]).all()
    assert _rms(res, disp, ok) < 0.05


def test_background_illumination_gradient():
    rng = np.random.default_rng(14)
    xy = dot_pattern(rng, SHAPE, per_32x32=20, min_distance=D)
    disp = smooth_displacement(xy, SHAPE, 1.5)
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    background = 0.2 + 1.5 * xx / SHAPE[1] + 0.5 * yy / SHAPE[0]  # up to twice the dot peak
    ref, grad = _pair(rng, xy, disp, noise=0.02, background=background)
    res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=D))
    ok = _check_no_nan_in_valid(res)
    rms = _rms(res, disp, ok)
    print(f"illumination ramp 0.2..2.2 I0: yield {ok.mean():.4f}, u_cc rms {rms:.4f} px")
    assert ok.mean() >= 0.995
    assert rms < 0.06


def test_saturated_dots_are_flagged():
    rng = np.random.default_rng(15)
    xy = jittered_grid(rng, SHAPE, spacing=10.0)
    disp = smooth_displacement(xy, SHAPE, 1.0)
    ref, grad = _pair(rng, xy, disp, noise=0.0)
    ref, grad = np.minimum(ref, 0.5), np.minimum(grad, 0.5)
    res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=D))
    ok = _check_no_nan_in_valid(res)
    sat = (res["status"] & DotStatus.SATURATED) != 0
    paper = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings.paper(diameter=D))
    ok_p = _check_no_nan_in_valid(paper)
    print(
        f"clipped at half the peak: yield {ok.mean():.4f}, saturated flag on {sat.mean():.3f}, "
        f"u rms {_rms(res, disp, ok, 'centroid'):.4f} "
        f"(paper's procedure {_rms(paper, disp, ok_p, 'centroid'):.4f})"
    )
    assert ok.mean() > 0.99
    assert sat.mean() > 0.9
    # The model fit leaves the saturated pixels out and fits the flanks: still accurate.
    assert _rms(res, disp, ok, "centroid") < 0.02
    # Flat tops defeat the three-point fit (equal samples give no offset): flagged, finite, but coarse.
    assert _rms(paper, disp, ok_p, "centroid") < 0.3


def test_prior_partly_outside_image():
    rng = np.random.default_rng(16)
    xy = jittered_grid(rng, SHAPE, spacing=12.0)
    disp = smooth_displacement(xy, SHAPE, 1.0)
    ref, grad = _pair(rng, xy, disp, noise=0.01)
    prior = np.vstack([xy, [[-5.0, 10.0], [300.0, 40.0], [np.nan, 3.0]]])
    res = track_pair(ref, grad, prior_xy=prior, settings=TrackingSettings(diameter=D))
    ok = _check_no_nan_in_valid(res)
    outside = (res["status"] & DotStatus.OUTSIDE_IMAGE) != 0
    assert_allclose(outside, np.r_[np.zeros(len(xy), bool), np.ones(3, bool)])
    assert not ok[-3:].any()
    assert np.isnan(res["x"][-3:]).all()
    assert ok[:-3].mean() == 1.0


def test_prior_through_soloff_mapping():
    rng = np.random.default_rng(17)
    target = jittered_grid(rng, (100, 100), spacing=5.0, margin=3) / 10.0  # target units: cm
    truth = np.stack(
        [
            20 + 21.0 * target[:, 0] + 0.05 * target[:, 0] ** 2,
            15 + 22.0 * target[:, 1] - 0.03 * target[:, 0] * target[:, 1],
        ],
        axis=1,
    )
    m = fit_soloff(target, truth + rng.normal(0, 0.01, truth.shape))
    disp = smooth_displacement(truth, SHAPE, 1.0)
    ref, grad = _pair(rng, truth, disp, noise=0.01)
    res = track_pair(ref, grad, prior_xy=target, mapping=m, settings=TrackingSettings(diameter=D))
    ok = _check_no_nan_in_valid(res)
    assert ok.mean() == 1.0
    assert _rms(res, disp, ok) < 0.03


@pytest.mark.parametrize("matching", ["nearest", "multiparametric"])
@pytest.mark.parametrize("identification", ["dynamic", "static"])
def test_standard_tracking_without_prior(matching, identification):
    rng = np.random.default_rng(18)
    xy = dot_pattern(rng, SHAPE, per_32x32=6, min_distance=6.0)
    disp = smooth_displacement(xy, SHAPE, 1.0)
    ref, grad = _pair(rng, xy, disp, noise=0.02)
    s = TrackingSettings(diameter=D, matching=matching, identification=identification)
    res = track_pair(ref, grad, settings=s)
    ok = _check_no_nan_in_valid(res)
    # Rows are reference dots in identification order: pair them with the truth by position.
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(xy).query(np.stack([res["x"], res["y"]], axis=1))
    assert (dist < 0.3).mean() > 0.99
    e = np.hypot(res["u_cc"] - disp[idx, 0], res["v_cc"] - disp[idx, 1])[ok]
    print(
        f"standard tracking ({identification}, {matching}): {len(res)} of {len(xy)} dots identified, "
        f"{ok.sum()} matched, u_cc rms {np.sqrt(np.mean(e**2)):.4f}"
    )
    assert ok.sum() >= 0.98 * len(xy)
    assert np.sqrt(np.mean(e**2)) < 0.05


def test_estimated_diameter_gives_same_result():
    rng = np.random.default_rng(19)
    xy = dot_pattern(rng, SHAPE, per_32x32=20, min_distance=D)
    disp = smooth_displacement(xy, SHAPE, 1.0)
    ref, grad = _pair(rng, xy, disp, noise=0.02)
    res = track_pair(ref, grad, prior_xy=xy)
    ok = _check_no_nan_in_valid(res)
    assert ok.mean() >= 0.995
    assert _rms(res, disp, ok) < 0.06


@pytest.mark.parametrize("paper", [False, True])
def test_each_step_of_a_run_matches_its_reference(device, monkeypatch, paper):
    """A run with a prior (a stack of one), its steps checked against their NumPy references on the run's
    own inputs (every identification round's windows, the model fit and first-moment step, the neighbour
    tests; the paper's procedure fits no model), and the run's result against the displacement it was
    drawn with."""
    rng = np.random.default_rng(20)
    xy = dot_pattern(rng, (128, 128), per_32x32=20, min_distance=D)
    disp = smooth_displacement(xy, (128, 128), 1.5)
    ref, grad = _pair(rng, xy, disp, noise=0.03, shape=(128, 128))
    calls = record_steps(monkeypatch)
    settings = TrackingSettings.paper(diameter=D) if paper else TrackingSettings(diameter=D)
    res = track_pair(ref, grad, prior_xy=xy, settings=settings, device=device)
    ran = {name for name, c in calls.items() if c}
    # identification's host engine measures windows on the CPU and for the paper's estimators; a GPU's
    # kernels for the default (measure_stack, against the same reference in test_pieces)
    host = device == "cpu" or paper
    tests = {"stack.neighbour_outliers_stack", "stack.confirmed_by_neighbours_stack"}
    assert ran == {*tests, *(["measure_windows"] if host else []), *([] if paper else ["stack.fit_stack"])}
    if host:
        assert len(calls["measure_windows"]) >= 2  # the residual rounds too
    assert_steps_agree(calls)
    ok = _check_no_nan_in_valid(res)
    assert ok.mean() >= 0.97
    assert _rms(res, disp, ok) < (0.06 if paper else 0.05)


def test_settings_as_dict():
    d = TrackingSettings(diameter=3.0).as_dict()
    assert d["centroid"] == "model" and d["correction"] == "model"
    assert d["cc_threshold"] == 0.5 and d["threshold"] == "auto"
    p = TrackingSettings.paper(diameter=3.0)
    assert (p.centroid, p.correction, p.diameter) == ("gaussian3", "paper", 3.0)
    assert_allclose(d["weights"], [1 / 3] * 3)
    with pytest.raises(SynthbosError):
        TrackingSettings(centroid="median")
    with pytest.raises(SynthbosError):
        TrackingSettings(correction="fft")


@pytest.mark.parametrize("centroid", ["centroid", "gaussian4", "lsq"])
def test_other_centroid_methods_run_the_pipeline(centroid):
    rng = np.random.default_rng(21)
    xy = jittered_grid(rng, (128, 128), spacing=10.0)
    disp = smooth_displacement(xy, (128, 128), 1.0)
    ref, grad = _pair(rng, xy, disp, noise=0.01, shape=(128, 128))
    res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=D, centroid=centroid))
    ok = _check_no_nan_in_valid(res)
    assert ok.all()
    assert _rms(res, disp, ok, "centroid") < 0.05


def test_bad_input_raises_one_clear_error():
    rng = np.random.default_rng(22)
    xy = jittered_grid(rng, (64, 64), spacing=10.0)
    ref, grad = _pair(rng, xy, 0.0 * xy, shape=(64, 64))
    s = TrackingSettings(diameter=D)
    cases = [
        ((ref, grad[:-1]), {}, "differ in shape"),
        ((np.zeros_like(ref), grad), {}, "all zero"),
        ((ref, np.where(np.arange(64) == 3, np.nan, grad)), {}, "non-finite"),
        ((ref, grad), {"prior_xy": xy[:, :1]}, "Nx2"),
        ((ref, grad), {"prior_xy": xy + 500.0}, "no prior dot lies inside"),
        ((ref[0], grad[0]), {}, "2-D"),
        ((ref, grad), {"prior_xy": xy, "mapping": lambda p: p[:, :1]}, r"mapping must give .* shape \(\d+, 1\)"),
        ((ref.astype(complex), grad), {}, "real numbers"),
        ((np.full((64, 64), 1.0), np.full((64, 64), 1.0)), {"settings": TrackingSettings()}, "diameter"),
    ]
    for args, kw, text in cases:
        kw = {"settings": s, **kw}
        with pytest.raises(SynthbosError, match=text) as info:
            track_pair(*args, **kw)
        assert "\n" not in str(info.value)
