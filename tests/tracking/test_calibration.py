"""Calibration from a drawn grid image with a known (distorted) mapping: lattice finding, the Soloff fit,
prediction of every dot, and tracking driven by the predicted dots."""

import json

import numpy as np
import pytest
from _synth import smooth_displacement
from numpy.testing import assert_allclose
from scipy.spatial import cKDTree
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import TrackingSettings, is_valid, track_pair
from synthbos.tracking.calibration import (
    calibrate_grid,
    fit_soloff,
    index_lattice,
    mapping_from_dict,
    mapping_to_dict,
)

from synthbos import SynthbosError

SHAPE = (256, 300)
SPACING = 2.0  # mm


def _camera(angle_deg=3.0):
    """Target mm -> image px: ~8 px/mm, a small rotation, and quadratic distortion of up to ~2 px."""
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))

    def to_image(t):
        x, y = t[:, 0], t[:, 1]
        u = 7.9 * (c * x - s * y)
        v = 8.1 * (s * x + c * y)
        return np.stack([151.3 + u + 0.02 * x**2 - 0.015 * x * y, 127.6 + v + 0.01 * y**2 + 0.012 * x**2], axis=1)

    return to_image


def _grid_image(rng, to_image, *, diameter=4.0, noise=0.01, faint=None):
    gi, gj = np.meshgrid(np.arange(-25, 26), np.arange(-25, 26), indexing="ij")
    target = np.stack([gi.ravel(), gj.ravel()], axis=1) * SPACING
    px = to_image(target)
    near = (px[:, 0] > -6) & (px[:, 0] < SHAPE[1] + 6) & (px[:, 1] > -6) & (px[:, 1] < SHAPE[0] + 6)
    target, px = target[near], px[near]
    intensity = np.ones(len(px))
    if faint is not None:
        intensity[faint(px)] = 0.05  # below the detection threshold: the image shows them poorly
    img = draw_dots(SHAPE, px, diameter, intensity=intensity) + noise * rng.standard_normal(SHAPE)
    inside = (px[:, 0] >= 0) & (px[:, 0] <= SHAPE[1] - 1) & (px[:, 1] >= 0) & (px[:, 1] <= SHAPE[0] - 1)
    return img, px[inside]


@pytest.mark.parametrize("angle", [3.0, -25.0])
def test_grid_calibration_predicts_every_dot(angle):
    rng = np.random.default_rng(40)
    to_image = _camera(angle)
    img, truth = _grid_image(rng, to_image, faint=lambda p: (np.abs(p[:, 0] - 80) < 12) & (p[:, 1] < 120))
    cal = calibrate_grid(img, SPACING)
    # every dot inside the image, and nothing else, is predicted
    _, idx = cKDTree(truth).query(cal.image_xy)
    err = np.hypot(*(cal.image_xy - truth[idx]).T)
    print(
        f"grid at {angle} deg: {cal.n_detected} blobs, {cal.detected.sum()} used, {len(cal.image_xy)} dots "
        f"predicted of {len(truth)}; residual rms {cal.residual_rms:.4f} px, max {cal.residual_max:.4f} px; "
        f"prediction error max {err.max():.4f} px"
    )
    assert len(cal.image_xy) == len(truth)
    assert len(np.unique(idx)) == len(truth)
    assert err.max() < 0.05
    assert cal.residual_rms < 0.05
    assert (~cal.detected).sum() >= 5  # the faint patch was predicted, not detected
    # the mapping's target frame: spacing-multiples, with the grid's own orientation
    assert_allclose(np.round(cal.target_xy / SPACING) * SPACING, cal.target_xy)


def test_grid_dots_drive_tracking_to_full_yield():
    rng = np.random.default_rng(41)
    to_image = _camera()
    img, truth = _grid_image(rng, to_image, diameter=3.0, noise=0.0)
    cal = calibrate_grid(img + 0.01 * rng.standard_normal(SHAPE), SPACING)
    disp = smooth_displacement(truth, SHAPE, 1.0)
    ref = draw_dots(SHAPE, truth, 3.0) + 0.01 * rng.standard_normal(SHAPE)
    grad = draw_dots(SHAPE, truth + disp, 3.0) + 0.01 * rng.standard_normal(SHAPE)
    res = track_pair(ref, grad, prior_xy=cal.image_xy, settings=TrackingSettings(diameter=3.0))
    ok = is_valid(res["status"])
    _, idx = cKDTree(truth).query(cal.image_xy)
    e = np.hypot(res["u_cc"] - disp[idx, 0], res["v_cc"] - disp[idx, 1])[ok]
    print(f"tracking with the calibrated dots: {ok.sum()} of {len(ok)} matched, u_cc rms {np.sqrt(np.mean(e**2)):.4f}")
    inner = (truth[idx, 0] > 2) & (truth[idx, 0] < SHAPE[1] - 3) & (truth[idx, 1] > 2) & (truth[idx, 1] < SHAPE[0] - 3)
    assert ok[inner].all()
    assert np.sqrt(np.mean(e**2)) < 0.03


def test_target_positions_through_a_saved_mapping():
    rng = np.random.default_rng(42)
    to_image = _camera()
    img, _ = _grid_image(rng, to_image)
    cal = calibrate_grid(img, SPACING)
    data = json.loads(json.dumps(mapping_to_dict(cal.mapping, target_unit="mm")))
    mapping = mapping_from_dict(data)
    pattern = rng.uniform([-15, -12], [15, 12], (300, 2))  # a random BOS pattern, mm in the grid's frame
    # the grid's frame: node (0, 0) is the dot nearest the image centre
    origin = cal.target_xy[np.argmin(np.hypot(*(cal.image_xy - [149.5, 127.5]).T))]
    assert_allclose(origin, [0.0, 0.0])
    ref_t = cal.target_xy[np.argmin(np.hypot(*(cal.image_xy - to_image(np.zeros((1, 2)))).T))]
    assert_allclose(mapping(pattern + ref_t), to_image(pattern + ref_t), atol=0.05)
    assert_allclose(mapping(cal.target_xy), cal.image_xy, atol=1e-9)


def test_index_lattice_skips_stray_blobs():
    rng = np.random.default_rng(43)
    gi, gj = np.meshgrid(np.arange(12), np.arange(10), indexing="ij")
    ij = np.stack([gi.ravel(), gj.ravel()], axis=1)
    xy = ij * [10.0, 11.0] + rng.normal(0, 0.2, ij.shape) + 5
    stray = rng.uniform(0, 120, (6, 2))
    stray = stray[cKDTree(xy).query(stray)[0] > 4]
    got, ok = index_lattice(np.vstack([xy, stray]), origin_xy=xy[0])
    assert ok[: len(xy)].all() and not ok[len(xy) :].any()
    assert_allclose(got[: len(xy)], ij)


def test_no_lattice_and_bad_mapping_raise():
    rng = np.random.default_rng(44)
    img = draw_dots(SHAPE, rng.uniform(5, 250, (150, 2)), 4.0)
    with pytest.raises(SynthbosError, match="no regular dot grid"):
        calibrate_grid(img, SPACING)
    with pytest.raises(SynthbosError, match=r"the calibration image is blank \(every pixel 0\): no dot grid"):
        calibrate_grid(np.zeros(SHAPE), SPACING)
    good = mapping_to_dict(fit_soloff(rng.uniform(0, 1, (20, 2)), rng.uniform(0, 1, (20, 2))))
    for bad, text in [
        ({"format": "other"}, "not a calibration mapping"),
        ({**good, "coef_x": good["coef_x"][:-1]}, "coefficients"),
        ({**good, "scale": [0.0, 1.0]}, "scale"),
        ({**good, "order": "x"}, "malformed"),
    ]:
        with pytest.raises(SynthbosError, match=text):
            mapping_from_dict(bad)
