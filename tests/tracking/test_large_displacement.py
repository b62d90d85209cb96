"""Large displacements, wrong gradient frames, masks and dark dots: the correlation predictor and the
flags that keep a wrong match from being reported as a measurement."""

import itertools

import numpy as np
import pytest
from _synth import dot_pattern, smooth_displacement
from numpy.testing import assert_allclose, assert_array_equal
from scipy.spatial import cKDTree
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import DotStatus, TrackingSettings, is_valid, track_pair
from synthbos.tracking.predict import (
    _cell,
    _deform_nearest,
    _tile_grid,
    _uniform_tile_shifts,
    local_normalized_correlation,
    predict_displacement,
)
from synthbos.tracking.reference import deform_nearest_numpy

from synthbos import SynthbosError

SHAPE = (256, 256)
D = 3.0
NOISE = 0.01  # of the dot peak


def _dense(seed):
    rng = np.random.default_rng(seed)
    return rng, dot_pattern(rng, SHAPE, per_32x32=20, min_distance=D)


def _pair(rng, xy, gradient_xy, *, noise=NOISE):
    ref = draw_dots(SHAPE, xy, D) + noise * rng.standard_normal(SHAPE)
    grad = draw_dots(SHAPE, gradient_xy, D) + noise * rng.standard_normal(SHAPE)
    return ref, grad


def _truth_rows(res, xy, prior):
    """Index of the true dot of each row (rows are prior dots, or identified dots without a prior)."""
    if prior:
        return np.arange(len(xy))
    dist, idx = cKDTree(xy).query(np.stack([res["x"], res["y"]], axis=1))
    assert (dist[is_valid(res["status"])] < 0.3).all()
    return idx


def _errors(res, disp, idx):
    ok = is_valid(res["status"])
    e = np.stack([res["u_cc"] - disp[idx, 0], res["v_cc"] - disp[idx, 1]], axis=1)[ok]
    return ok, e


CASES = {
    "uniform 5 px": lambda xy: np.tile([5.0, 0.0], (len(xy), 1)),
    "uniform 10 px": lambda xy: np.tile([6.0, -8.0], (len(xy), 1)),
    "smooth 8 px": lambda xy: smooth_displacement(xy, SHAPE, 8.0),
}


@pytest.mark.parametrize("prior", [True, False], ids=["prior", "standard"])
@pytest.mark.parametrize("case", list(CASES))
def test_large_displacements_are_tracked(case, prior):
    rng, xy = _dense(30)
    disp = CASES[case](xy)
    ref, grad = _pair(rng, xy, xy + disp)
    res = track_pair(ref, grad, prior_xy=xy if prior else None, settings=TrackingSettings(diameter=D))
    ok, e = _errors(res, disp, _truth_rows(res, xy, prior))
    rms = float(np.sqrt(np.mean(e**2)))
    worst = float(np.abs(e).max())
    mode = "prior" if prior else "standard"
    msg = f"{case}, {mode}: {ok.sum()} of {len(xy)} dots matched, u_cc rms {rms:.4f} px, worst {worst:.3f} px"
    print(msg)
    assert ok.sum() >= 0.95 * len(xy), msg  # dots leaving the image or cut by its edge are flagged
    assert rms <= 0.05, msg
    assert worst < 0.35, msg  # no wrong pairing among the matched dots
    # matched dots agree with the prediction, but for a few near the edge whose neighbours overrule it
    agree = np.hypot(res["u_pred"] - res["u"], res["v_pred"] - res["v"])[ok] <= 1.5
    assert agree.mean() > 0.97


@pytest.mark.parametrize("prior", [True, False], ids=["prior", "standard"])
def test_flipped_gradient_frame_is_not_matched(prior):
    rng, xy = _dense(31)
    ref, grad = _pair(rng, xy, xy)
    grad = grad[::-1]
    res = track_pair(ref, grad, prior_xy=xy if prior else None, settings=TrackingSettings(diameter=D))
    ok = is_valid(res["status"])
    weak = (res["status"] & DotStatus.PREDICTOR_WEAK) != 0
    found = (res["status"] & DotStatus.FOUND_GRADIENT) != 0
    print(
        f"flipped frame ({'prior' if prior else 'standard'}): {found.sum()} of {len(res)} dots found in the "
        f"gradient image, {ok.sum()} matched, {weak.sum()} flagged PREDICTOR_WEAK, predictor correlation "
        f"median {np.nanmedian(res['pred_correlation']):.3f}"
    )
    assert ok.sum() <= 0.01 * len(res)
    assert weak.mean() > 0.95


@pytest.mark.parametrize("prior", [True, False], ids=["prior", "standard"])
def test_20px_shift_is_tracked_or_flagged_never_wrong(prior):
    rng, xy = _dense(32)
    disp = np.tile([20.0, 0.0], (len(xy), 1))
    ref, grad = _pair(rng, xy, xy + disp)
    res = track_pair(ref, grad, prior_xy=xy if prior else None, settings=TrackingSettings(diameter=D))
    ok, e = _errors(res, disp, _truth_rows(res, xy, prior))
    inside = (xy[:, 0] + 20.0 < SHAPE[1] - 3).sum()
    print(
        f"20 px shift ({'prior' if prior else 'standard'}): {ok.sum()} matched of {inside} dots that stay "
        f"in the image, worst error {np.abs(e).max() if e.size else 0:.3f} px"
    )
    assert (np.abs(e) < 0.35).all()
    assert ok.sum() >= 0.9 * inside


def test_matches_that_disagree_with_the_predictor_are_flagged():
    # 5 % of the dots move 2.2 px away from where the field (and the predictor, right from the other
    # dots) takes them: within the second search's reach, beyond the predictor tolerance.
    rng, xy = _dense(33)
    disp = np.tile([4.0, 0.0], (len(xy), 1))
    swap = rng.random(len(xy)) < 0.05
    gxy = xy + disp
    angle = rng.uniform(0, 2 * np.pi, swap.sum())
    gxy[swap] += 2.2 * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    ref, grad = _pair(rng, xy, gxy)
    res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=D))
    ok = is_valid(res["status"])
    flagged = (res["status"] & (DotStatus.PREDICTOR_MISMATCH | DotStatus.OUTLIER)) != 0
    found = (res["status"] & DotStatus.FOUND_GRADIENT) != 0
    print(
        f"{swap.sum()} dots moved 2.2 px off the field: {(swap & ok).sum()} matched, "
        f"{(swap & found).sum()} found in the gradient image, {(swap & flagged).sum()} of them flagged"
    )
    assert not (swap & ok).any()
    assert (flagged | ~found)[swap].all()
    assert ok[~swap].mean() > 0.95


def test_predictor_and_its_significance():
    rng, xy = _dense(34)
    disp = np.tile([9.3, -4.6], (len(xy), 1))
    ref, grad = _pair(rng, xy, xy + disp)
    uv, quality = predict_displacement(ref, grad, xy)
    inner = (xy[:, 0] < SHAPE[1] - 20) & (xy[:, 1] > 10)
    assert_allclose(uv[inner], disp[inner], atol=0.2)
    assert np.median(quality[inner]) > 0.95
    _, quality = predict_displacement(ref, grad[:, ::-1], xy)
    assert np.percentile(quality, 99) < 0.4
    # local_normalized_correlation against a direct computation in one box
    a, b = rng.standard_normal((2, 40, 40))
    b = 0.5 * a + b
    ncc = local_normalized_correlation(a, b, size=9)
    box = np.s_[16:25, 6:15]
    assert_allclose(ncc[20, 10], np.corrcoef(a[box].ravel(), b[box].ravel())[0, 1], rtol=1e-10)


@pytest.mark.parametrize("prior", [True, False], ids=["prior", "standard"])
def test_masked_dots_are_flagged_not_measured(prior):
    rng, xy = _dense(35)
    disp = smooth_displacement(xy, SHAPE, 1.5)
    ref, grad = _pair(rng, xy, xy + disp)
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    mask = np.hypot(xx - 120.0, yy - 140.0) < 40.0  # True = excluded
    ref[mask] = 5.0  # an opaque, bright object: nothing to measure there
    grad[mask] = 5.0
    res = track_pair(ref, grad, prior_xy=xy if prior else None, mask=mask, settings=TrackingSettings(diameter=D))
    ok = is_valid(res["status"])
    masked = (res["status"] & DotStatus.MASKED) != 0
    r = np.hypot(res["x"] - 120.0, res["y"] - 140.0) if not prior else np.hypot(xy[:, 0] - 120, xy[:, 1] - 140)
    print(f"mask ({'prior' if prior else 'standard'}): {masked.sum()} dots flagged MASKED, {ok.sum()} matched")
    assert not (ok & masked).any()
    assert not ok[r < 40.0].any()
    far = r > 45.0
    assert ok[far].mean() > 0.99
    if prior:
        assert masked[r < 40.0].all()
        assert np.isnan(res["u"][masked]).all()
    idx = _truth_rows(res, xy, prior)
    e = np.hypot(res["u_cc"] - disp[idx, 0], res["v_cc"] - disp[idx, 1])[ok]
    assert np.sqrt(np.mean(e**2)) < 0.05


def test_bad_mask_raises():
    rng, xy = _dense(36)
    ref, grad = _pair(rng, xy, xy)
    s = TrackingSettings(diameter=D)
    for mask, text in [
        (np.zeros((10, 10), bool), "shape"),
        (np.ones(SHAPE, bool), "every pixel"),
        (np.full(SHAPE, "a"), "boolean"),
    ]:
        with pytest.raises(SynthbosError, match=text):
            track_pair(ref, grad, prior_xy=xy, mask=mask, settings=s)


@pytest.mark.parametrize("prior", [True, False], ids=["prior", "standard"])
def test_dark_dots_inverted_give_the_bright_dot_result(prior):
    rng, xy = _dense(37)
    disp = smooth_displacement(xy, SHAPE, 3.0)
    bright_r, bright_g = _pair(rng, xy, xy + disp, noise=0.02)
    dark_r, dark_g = 1.3 - bright_r, 1.3 - bright_g  # dark dots on a bright background
    top = max(dark_r.max(), dark_g.max())
    s = TrackingSettings(diameter=D)
    a = track_pair(bright_r, bright_g, prior_xy=xy if prior else None, settings=s)
    b = track_pair(top - dark_r, top - dark_g, prior_xy=xy if prior else None, settings=s)
    assert_array_equal(a["status"], b["status"])
    for name in ("x", "y", "u", "v", "u_cc", "v_cc"):
        assert_allclose(b[name], a[name], atol=1e-9, equal_nan=True, err_msg=name)
    for name in ("u_pred", "v_pred"):  # the correlation runs in float32
        assert_allclose(b[name], a[name], atol=1e-4, equal_nan=True, err_msg=name)
    assert is_valid(a["status"]).mean() > 0.97


def test_mask_leaving_a_narrow_band():
    # the mask excludes more than half of every 64 px window: the predictor starts at a finer pass
    rng, xy = _dense(38)
    ref, grad = _pair(rng, xy, xy + np.array([3.0, 0.0]))
    mask = np.ones(SHAPE, dtype=bool)
    mask[100:130, :] = False
    res = track_pair(ref, grad, prior_xy=xy, mask=mask, settings=TrackingSettings(diameter=D))
    ok = is_valid(res["status"])
    band = (xy[:, 1] > 103) & (xy[:, 1] < 127) & (xy[:, 0] > 3) & (xy[:, 0] < SHAPE[1] - 8)
    assert ok[band].mean() > 0.95 and not ok[(xy[:, 1] < 97) | (xy[:, 1] > 133)].any()
    assert_allclose(res["u"][ok], 3.0, atol=0.1)


def test_deform_nearest_kernel_matches_numpy_reference(device):
    """The predictor's nearest-pixel deformation over a block of tiles (sources beyond the image and
    masked pixels weighted 0, rounded shifts averaged per tile) agrees with its NumPy reference."""
    rng = np.random.default_rng(39)
    image = rng.random((100, 90)).astype(np.float32)
    valid = (rng.random(image.shape) > 0.1).astype(np.float32)
    ys, xs = _tile_grid(100, 16), _tile_grid(90, 16)
    coarse_y, coarse_x = _tile_grid(100, 32), _tile_grid(90, 32)
    field = (rng.normal(0, 3, (3, 2)), rng.normal(0, 3, (3, 2)), coarse_y + 15.5, coarse_x + 15.5)
    for v in (None, valid):
        a = [np.copy(x) for x in _deform_nearest(image, v, field, ys, xs, 16, device)]
        b = deform_nearest_numpy(image, v, field, ys, xs, 16)
        for x, y in zip(a, b, strict=True):
            assert_array_equal(x, y)
        if v is None:  # tiles at the edge take pixels from beyond it, inner ones not
            assert a[-1].any() and not a[-1].all()


def test_deform_nearest_kernel_whole_tile_shifts(device):
    """Where a gentle field rounds to one shift over a whole tile from inside the image, the tile is
    copied as a whole (by the kernel or by NumPy): tiles moved as a whole, tiles moved pixel by pixel
    (the field crossing a rounding boundary), tiles taking pixels from beyond the image and masked
    pixels all agree with the NumPy reference."""
    rng = np.random.default_rng(41)
    image = rng.random((128, 112))
    valid = (rng.random(image.shape) > 0.05).astype(np.float32)
    ys, xs = _tile_grid(128, 16), _tile_grid(112, 16)
    coarse_y, coarse_x = _tile_grid(128, 32), _tile_grid(112, 32)
    # u from 2.2 to 2.9 down the image (crossing 2.5 in the middle), v near -7 (rows from beyond the top)
    u = np.linspace(2.2, 2.9, 4)[:, None] + np.zeros((1, 3))
    v = -7.1 + 0.05 * rng.random((4, 3))
    field = (u, v, coarse_y + 15.5, coarse_x + 15.5)
    cells = (_cell(np.arange(n), c)[0] for n, c in ((128, field[2]), (112, field[3])))
    uniform = _uniform_tile_shifts(field, *cells, ys, xs, 16, image.shape)
    assert 0 < uniform[:, 2].sum() < len(uniform)
    for v_, on_host in itertools.product((None, valid), (False, True)):
        a = [np.copy(x) for x in _deform_nearest(image, v_, field, ys, xs, 16, device, whole_on_host=on_host)]
        b = deform_nearest_numpy(image, v_, field, ys, xs, 16)
        for x, y in zip(a, b, strict=True):
            assert_array_equal(x, y)
        if v_ is None:  # the top row and right column of tiles take pixels from beyond the image, the others not
            assert a[-1][0].all() and a[-1][:, -1].all() and not a[-1][1:, :-1].any()


@pytest.mark.parametrize("kind", ["uniform", "smooth"])
def test_predictor_with_a_sparse_first_pass(kind):
    """On a 1024 px image the 64 px first pass takes about every other tile along each axis (8 x 8 of
    them): the field it gives still places the finer passes, for large uniform and smooth shifts (on the
    smooth field the dense first pass gives a 99th percentile error of 0.17 px and a largest of 0.42 px,
    the sparse one 0.17 and 0.36 px: well within the identification's 1.5 px tolerance)."""
    shape = (1024, 1024)
    rng = np.random.default_rng(36)
    xy = dot_pattern(rng, shape, per_32x32=20, min_distance=D)
    disp = np.tile([9.3, -4.6], (len(xy), 1)) if kind == "uniform" else smooth_displacement(xy, shape, 8.0)
    ref = draw_dots(shape, xy, D) + NOISE * rng.standard_normal(shape)
    grad = draw_dots(shape, xy + disp, D) + NOISE * rng.standard_normal(shape)
    uv, quality = predict_displacement(ref, grad, xy)
    inner = (xy > 24).all(axis=1) & (xy < np.array(shape[::-1]) - 24).all(axis=1)
    err = np.abs(uv[inner] - disp[inner]).max(axis=1)
    assert err.max() < 0.5
    assert np.percentile(err, 99) < 0.25
    assert np.median(quality[inner]) > 0.9
