"""Standard tracking (no prior) on patterns that are not dots: what it counts as measured is right.

Speckle and random squares are drawn and displaced by a known smooth field (``benchmarks.bench_noprior``);
among the dots counted valid (MATCHED) at most 1 % may be more than 0.5 px from the drawn field at the
dot's reference position. The registration check (MISREGISTERED) is what keeps them out: without it
the same pairs give several per cent. On true dots it flags nothing.
"""

import numpy as np
import pytest
from _steps import assert_steps_agree, record_steps
from _synth import dot_pattern, smooth_displacement
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.benchmarks.bench_noprior import field, score, speckle_pair, squares_pair
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import DotStatus, TrackingSettings, is_valid, track_pair
from synthbos.tracking.reference import registration_offsets_numpy
from synthbos.tracking.register import (
    local_gradients,
    registration_offsets,
    spline_coefficients,
)

from synthbos import SynthbosError

SHAPE = (256, 256)
AMPLITUDE = 1.5
OFF = TrackingSettings(registration_tolerance=np.inf)


@pytest.mark.parametrize(
    ("name", "pair", "min_yield"),
    [
        ("speckle", lambda: speckle_pair(SHAPE, seed=3, amplitude=AMPLITUDE, grain=4.0), 0.6),
        ("squares", lambda: squares_pair(SHAPE, seed=3, amplitude=AMPLITUDE), 0.45),
    ],
)
def test_no_dot_more_than_half_a_pixel_off_is_counted_valid(name, pair, min_yield):
    ref, grad = pair()
    before = track_pair(ref, grad, settings=OFF)
    after = track_pair(ref, grad)
    _, valid0, off0, rms0 = score(before, SHAPE, AMPLITUDE)
    n, valid, off, rms = score(after, SHAPE, AMPLITUDE)
    print(
        f"{name}: {n} dots; without the check {valid0} valid, {off0:.2%} > 0.5 px, RMS {rms0:.3f} px; "
        f"with it {valid} valid (yield {valid / n:.3f}), {off:.2%} > 0.5 px, RMS {rms:.3f} px"
    )
    assert off0 > 0.015  # the failure the check is for
    assert off <= 0.01
    assert valid >= min_yield * n
    flagged = (after["status"] & DotStatus.MISREGISTERED) != 0
    assert_array_equal(is_valid(before["status"]) & ~flagged, is_valid(after["status"]))
    assert not (flagged & is_valid(after["status"])).any()
    assert np.isnan(after["u_cc"][flagged]).all()
    assert np.isnan(after["u"][flagged]).all()
    assert np.isfinite(after["x_gradient"][flagged]).all()


def test_true_dots_are_not_flagged():
    """Dots of 3 px at 20 per 32x32 px, 3 % noise: the check changes nothing, row for row."""
    rng = np.random.default_rng(5)
    xy = dot_pattern(rng, SHAPE, per_32x32=20, min_distance=3.0)
    disp = smooth_displacement(xy, SHAPE, 1.5)
    ref = draw_dots(SHAPE, xy, 3.0) + 0.03 * rng.standard_normal(SHAPE)
    grad = draw_dots(SHAPE, xy + disp, 3.0) + 0.03 * rng.standard_normal(SHAPE)
    after = track_pair(ref, grad)
    before = track_pair(ref, grad, settings=OFF)
    assert not ((after["status"] & DotStatus.MISREGISTERED) != 0).any()
    assert is_valid(after["status"]).mean() >= 0.998
    for name in after.dtype.names:
        assert_array_equal(after[name], before[name], err_msg=name)


def _speckle_case():
    ref, grad = speckle_pair((128, 128), seed=1, amplitude=0.8, grain=3.0, noise=0.0)
    rng = np.random.default_rng(2)
    xy = rng.uniform(10, 118, (60, 2))
    return ref, grad, xy, field(xy, (128, 128), 0.8)


def test_registration_finds_a_known_error():
    """A speckle pattern moved by (0.7, -1.3) px: started 0.3 px off, the correction brings each dot's
    displacement back to the shift; started on it, it stays."""
    from scipy import ndimage

    ref, _ = speckle_pair((128, 128), seed=1, amplitude=0.0, grain=3.0, noise=0.0)
    shift = np.array([0.7, -1.3])
    grad = ndimage.shift(ref, shift[::-1], order=5, mode="nearest")
    rng = np.random.default_rng(2)
    xy = rng.uniform(12, 116, (60, 2))
    coef = spline_coefficients(grad)
    wrong = shift + np.array([0.3, -0.2])
    c, ok = registration_offsets_numpy(ref, coef, xy, np.tile(wrong, (len(xy), 1)), half=4)
    assert ok.all()
    assert_allclose(wrong + c, np.tile(shift, (len(xy), 1)), atol=0.03)
    c0, _ = registration_offsets_numpy(ref, coef, xy, np.tile(shift, (len(xy), 1)), half=4)
    assert np.abs(c0).max() < 0.03


def test_local_gradients_of_a_linear_field():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 100, (200, 2))
    a = np.array([[0.05, -0.02], [0.03, 0.01]])
    uv = np.array([1.0, -2.0]) + xy @ a.T
    assert_allclose(local_gradients(xy, uv), np.broadcast_to(a, (200, 2, 2)), atol=1e-5)  # the ridge
    assert_array_equal(local_gradients(xy[:5], uv[:5]), np.zeros((5, 2, 2)))


def test_registration_follows_a_strong_gradient():
    """A speckle pattern stretched by 8 % along x about its centre: with the gradient the window registers
    to the field at each point; moved only, it misses by up to about the stretch across the window."""
    from scipy import ndimage

    ref, _ = speckle_pair((128, 128), seed=1, amplitude=0.0, grain=3.0, noise=0.0)
    a = np.array([[0.08, 0.0], [0.0, 0.0]])
    centre = 63.5
    # gradient(x) = ref(x - u(x)), u = a (x - centre): sample ref at centre + (x - centre) / 1.08
    rows, cols = np.mgrid[0:128, 0:128].astype(float)
    grad = ndimage.map_coordinates(ref, [rows, centre + (cols - centre) / 1.08], order=5, mode="nearest")
    rng = np.random.default_rng(3)
    xy = rng.uniform(30, 98, (40, 2))
    truth = (xy - centre) @ a.T
    coef = spline_coefficients(grad)
    grads = np.broadcast_to(a, (40, 2, 2))
    c, ok = registration_offsets_numpy(ref, coef, xy, truth + 0.2, half=4, gradients=grads)
    assert ok.all()
    assert_allclose(truth + 0.2 + c, truth, atol=0.03)
    c_moved, _ = registration_offsets_numpy(ref, coef, xy, truth, half=4)
    assert np.abs(c_moved).max() > 0.05


def test_registration_kernel_matches_numpy_reference(device):
    ref, grad, xy, truth = _speckle_case()
    xy = np.vstack([xy, [[0.2, 50.0], [127.0, 127.0], [-30.0, 10.0]]])  # at the edge, and outside: not solved
    truth = np.vstack([truth, np.zeros((3, 2))])
    coef = spline_coefficients(grad)
    grads = local_gradients(xy, truth)
    c_np, ok_np = registration_offsets_numpy(ref, coef, xy, truth + 0.2, half=4, gradients=grads)
    c_wp, ok_wp = registration_offsets(ref, coef, xy, truth + 0.2, half=4, gradients=grads, device=device)
    assert_array_equal(ok_wp, ok_np)
    assert not ok_np[-1]
    assert_allclose(c_wp, c_np, atol=1e-10)


def test_each_step_of_a_run_without_a_prior_matches_its_reference(monkeypatch):
    """Standard tracking of squares: the registration step (the MISREGISTERED rule) and the other steps
    checked against their NumPy references on the run's own inputs."""
    ref, grad = squares_pair((128, 128), seed=5, amplitude=1.0)
    calls = record_steps(monkeypatch)
    a = track_pair(ref, grad, settings=TrackingSettings())
    steps = ("measure_windows", "stack.fit_stack", "stack.neighbour_outliers_stack", "registration_offsets")
    assert all(calls[name] for name in steps)
    assert_steps_agree(calls, atol=1e-9)
    assert ((a["status"] & DotStatus.MISREGISTERED) != 0).sum() >= 5
    (c, ok), _ = calls["registration_offsets"][-1]
    assert (~ok | (np.hypot(c[:, 0], c[:, 1]) > 0.25)).sum() >= 5  # the flagged dots are the registration's


def test_registration_tolerance_is_checked():
    with pytest.raises(SynthbosError, match="registration_tolerance"):
        TrackingSettings(registration_tolerance=0.0)
    with pytest.raises(SynthbosError, match="registration_tolerance"):
        TrackingSettings(registration_tolerance=float("nan"))


@pytest.mark.parametrize(("pitch", "shift"), [(8, (1.2, -0.7)), (8, (0.2, 0.1)), (10, (2.5, -1.5))])
def test_a_regular_dot_grid_is_tracked_at_its_true_shift(pitch, shift):
    """A printed grid of 3 px dots whose pitch divides the predictor's tiles (8 px) or not (10 px), moved by
    less than half a pitch: every dot measured, at the true shift, with and without the grid as a prior
    (the predictor once took any lattice shift: 0-28 of 1024 dots measured, some a whole pitch off)."""
    rng = np.random.default_rng(pitch)
    line = np.arange(pitch / 2, 256, pitch)
    xy = np.stack(np.meshgrid(line, line), axis=-1).reshape(-1, 2)
    ref = draw_dots(SHAPE, xy, 3.0) + 0.01 * rng.standard_normal(SHAPE)
    grad = draw_dots(SHAPE, xy + np.asarray(shift), 3.0) + 0.01 * rng.standard_normal(SHAPE)
    for prior in (None, xy):
        res = track_pair(ref, grad, prior_xy=prior, device="cpu")
        ok = is_valid(res["status"])
        at = np.stack([res["x"], res["y"]], axis=1) + np.asarray(shift)  # where each dot lands in the gradient image
        inside = ((at >= 3) & (at <= 252)).all(axis=1)  # its whole disk in both images
        assert ok[inside].mean() == 1.0, (prior is None, ok.mean())
        err = np.hypot(res["u_cc"][ok] - shift[0], res["v_cc"][ok] - shift[1])
        assert err.max() < 0.1
