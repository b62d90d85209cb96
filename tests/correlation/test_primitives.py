"""Building blocks of the correlator: deformation kernels (against NumPy/SciPy references), spline
carrying of the predictor, window grids, peak ratio, RPC, validation."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy import ndimage
from synthbos.correlation.deform import bspline3_coefficients, deform_pair, grid_to_pixels, spline_weights
from synthbos.correlation.peak import peak_ratio, subpixel_peak
from synthbos.correlation.validation import fill_by_interpolation, normalized_median_test, replace_outliers
from synthbos.correlation.windows import extract_windows, window_starts
from synthbos.correlation.xcorr import cross_correlate, robust_phase_correlate
from synthbos.raytrace.dots import draw_dots


def _mirror(k, n):
    period = 2 * n - 2
    m = np.abs(k) % period
    return np.where(m >= n, period - m, m)


def lanczos3_reference(image, y, x):
    """Plain NumPy Lanczos-3 sampling, weights normalised per axis, mirror boundary."""
    h, w = image.shape
    iy, ix = np.floor(y).astype(int), np.floor(x).astype(int)

    def weights(t):
        s = t[..., None] - np.arange(-2, 4)
        wt = np.sinc(s) * np.sinc(s / 3)
        return wt / wt.sum(-1, keepdims=True)

    wy, wx = weights(y - iy), weights(x - ix)
    out = np.zeros(np.shape(y))
    for a in range(6):
        for b in range(6):
            out += wy[..., a] * wx[..., b] * image[_mirror(iy - 2 + a, h), _mirror(ix - 2 + b, w)]
    return out


@pytest.mark.parametrize("interpolator", ["cubic", "lanczos"])
def test_deform_pair_matches_reference(device, interpolator):
    rng = np.random.default_rng(3)
    image = rng.random((37, 45)).astype(np.float32)
    du = rng.uniform(-5, 5, (30, 41)).astype(np.float32)  # reaches beyond the edges: mirror extension
    dv = rng.uniform(-5, 5, (30, 41)).astype(np.float32)
    origin = (2.25, 1.25)
    rows, cols = np.meshgrid(np.arange(30) + origin[0], np.arange(41) + origin[1], indexing="ij")
    src = bspline3_coefficients(image) if interpolator == "cubic" else image
    first, second = deform_pair(src, src, du, dv, origin=origin, interpolator=interpolator, device=device)
    if interpolator == "cubic":
        ref_first = ndimage.map_coordinates(
            image.astype(float), [rows - dv / 2, cols - du / 2], order=3, mode="mirror"
        )
        ref_second = ndimage.map_coordinates(
            image.astype(float), [rows + dv / 2, cols + du / 2], order=3, mode="mirror"
        )
    else:
        ref_first = lanczos3_reference(image, rows - dv / 2, cols - du / 2)
        ref_second = lanczos3_reference(image, rows + dv / 2, cols + du / 2)
    assert_allclose(first, ref_first, atol=2e-5)
    assert_allclose(second, ref_second, atol=2e-5)


def test_bspline_coefficients_interpolate_the_pixels(device):
    image = np.random.default_rng(1).random((20, 33))
    zero = np.zeros((20, 33), np.float32)
    first, _ = deform_pair(
        bspline3_coefficients(image), bspline3_coefficients(image), zero, zero, device=device
    )
    assert_allclose(first, image, atol=1e-5)


def test_spline_carry_is_exact_for_linear_fields_and_extrapolates():
    ny, nx = np.arange(5) * 16 + 7.5, np.arange(6) * 16 + 7.5
    field = 0.3 + 0.02 * ny[:, None] - 0.015 * nx[None, :]
    rows, cols = np.arange(-3, 90.0), np.arange(0, 100.0) + 0.25
    dense = grid_to_pixels(field, ny, nx, rows, cols)
    assert_allclose(dense, 0.3 + 0.02 * rows[:, None] - 0.015 * cols[None, :], atol=1e-5)
    assert_allclose(spline_weights([1.0, 3.0], [2.0]), [[0.5, 0.5]])
    assert_allclose(spline_weights([4.0], [0.0, 9.0]), [[1.0], [1.0]])


def test_window_grid_is_centred_and_views_the_image():
    starts = window_starts(100, 16, 8)
    assert_allclose(starts, 2 + 8 * np.arange(11))  # 100 - 16 - 80 = 4 spare pixels, 2 on each side
    image = np.arange(100 * 90.0).reshape(100, 90)
    win = extract_windows(image, 16, 8, 2, 5, 3, 4)
    assert win.shape == (3, 4, 16, 16)
    assert_allclose(win[2, 3], image[18:34, 29:45])


@pytest.mark.parametrize("rpc", [False, True])
def test_window_correlation_finds_known_shift(rpc):
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 64, (80, 2))
    a = draw_dots((64, 64), xy, 3.0).astype(np.float32)
    b = draw_dots((64, 64), xy + np.array([1.3, -2.4]), 3.0).astype(np.float32)
    wa = extract_windows(a, 32, 32, 16, 16, 1, 1).reshape(1, 32, 32)
    wb = extract_windows(b, 32, 32, 16, 16, 1, 1).reshape(1, 32, 32)
    plane = robust_phase_correlate(wa, wb, diameter=3.0) if rpc else cross_correlate(wa, wb)
    assert plane.dtype == np.float32
    row, col, border = subpixel_peak(plane)
    assert not border[0]
    assert_allclose([col[0] - 16, row[0] - 16], [1.3, -2.4], atol=0.1)
    assert peak_ratio(plane)[0] > 1.5


def test_peak_ratio_two_peaks():
    plane = np.zeros((1, 16, 16))
    plane[0, 8, 8], plane[0, 2, 3] = 4.0, 2.0
    assert_allclose(peak_ratio(plane), [2.0])
    plane[0, 9, 9] = 3.9  # inside the first peak's exclusion square: not a second peak
    assert_allclose(peak_ratio(plane), [2.0])
    assert_allclose(peak_ratio(np.ones((2, 8, 8))), [1.0, 1.0])  # flat planes: 1, not NaN


def test_median_test_flags_planted_outliers_and_replacement_restores():
    y, x = np.mgrid[0:12, 0:14].astype(float)
    u, v = 0.05 * x + 0.3, -0.08 * y  # a linear field: no node, edges included, may be flagged
    assert not normalized_median_test(u, v).any()
    bad = np.zeros(u.shape, bool)
    bad[[0, 5, 11], [0, 7, 13]] = True
    ub, vb = u + 3.0 * bad, v - 2.0 * bad
    flagged = normalized_median_test(ub, vb, epsilon=0.1, threshold=2.0)
    assert_allclose(flagged, bad)
    ur, vr = replace_outliers(ub, vb, flagged)
    assert_allclose(ur[~bad], u[~bad])
    assert_allclose(ur[bad], u[bad], atol=0.08)  # median of the valid neighbours of a linear field
    assert_allclose(vr[bad], v[bad], atol=0.09)


def test_fill_by_interpolation_beats_the_median_on_a_smooth_field_with_holes():
    """A drawn smooth field (wavelengths of 36-47 nodes) with a 6 x 6 hole, a hole on the grid's edge and
    8 % of single vectors rejected: harmonic interpolation is 2.3 times closer to the truth than the
    neighbours' median, 2.8 times in the hole; accepted vectors stay as they are."""
    y, x = np.mgrid[0:32, 0:40].astype(float)
    u = 1.5 * np.sin(2 * np.pi * x / 36) * np.cos(2 * np.pi * y / 43.2) + 0.05 * x
    v = np.cos(2 * np.pi * (x + y) / 46.8)
    rejected = np.random.default_rng(3).random(u.shape) < 0.08
    rejected[10:16, 12:18] = True
    rejected[0:3, 30:36] = True
    bad_u, bad_v = np.where(rejected, np.nan, u), np.where(rejected, 99.0, v)  # NaN or wild: no matter

    def rms(fu, fv, where):
        return np.sqrt(np.mean((fu - u)[where] ** 2 + (fv - v)[where] ** 2))

    hole = np.zeros(u.shape, bool)
    hole[10:16, 12:18] = True
    mu, mv = replace_outliers(bad_u, bad_v, rejected)
    fu, fv = fill_by_interpolation(bad_u, bad_v, rejected)
    assert_allclose([rms(mu, mv, rejected), rms(mu, mv, hole)], [0.172, 0.218], atol=0.002)
    assert_allclose([rms(fu, fv, rejected), rms(fu, fv, hole)], [0.075, 0.079], atol=0.002)
    assert_allclose(fu[~rejected], u[~rejected], rtol=0, atol=0)
    assert_allclose(fv[~rejected], v[~rejected], rtol=0, atol=0)
    # a linear field is filled exactly (converged) in a hole inside the grid
    lin_u, lin_v = 0.3 * x - 0.1 * y, 0.2 * y
    eu, ev = fill_by_interpolation(np.where(hole, 0.0, lin_u), lin_v, hole, sweeps=2000)
    assert_allclose(eu, lin_u, atol=1e-6)
    assert_allclose(ev, lin_v, atol=1e-6)
