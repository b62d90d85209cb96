"""Accuracy of the default tracker against the Cramer-Rao bound, next to the paper's procedure.

Images: integrated Gaussian dots of 3 px, 20 dots per 32x32 px, centre spacing >= 1 d, displaced by
smooth random fields of up to 2 px with gradients up to 0.08 px/px, white noise of 0-5 % of the peak.
"tracking" is the centroid difference ``u, v``; "tracking-cc" the corrected ``u_cc, v_cc``.
"""

import numpy as np
import pytest
from _synth import dot_pattern, jittered_grid, smooth_displacement
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import TrackingSettings, is_valid, track_pair
from synthbos.tracking.crlb import displacement_crlb, position_crlb
from synthbos.tracking.dotfit import fit_dots, fit_window_half
from synthbos.tracking.reference import fit_dots_numpy

SHAPE = (256, 256)
D = 3.0
SEEDS = (31, 32, 33)


def smooth_field(rng, xy, *, amplitude=2.0, gradient=0.08):
    """A random smooth field: two sine modes per component, |u| <= amplitude, |grad u| <= gradient."""
    out = np.zeros_like(xy)
    for comp in range(2):
        for _ in range(2):
            k = gradient / amplitude  # wavenumber so that amplitude * k = gradient
            theta = rng.uniform(0, 2 * np.pi)
            phase = rng.uniform(0, 2 * np.pi)
            out[:, comp] += 0.5 * amplitude * np.sin(k * (xy[:, 0] * np.cos(theta) + xy[:, 1] * np.sin(theta)) + phase)
    return out


def _case(seed, noise, *, min_distance=D):
    rng = np.random.default_rng(seed)
    xy = dot_pattern(rng, SHAPE, per_32x32=20, min_distance=min_distance)
    disp = smooth_field(rng, xy)
    ref = draw_dots(SHAPE, xy, D) + noise * rng.standard_normal(SHAPE)
    grad = draw_dots(SHAPE, xy + disp, D) + noise * rng.standard_normal(SHAPE)
    return xy, disp, ref, grad


def _errors(res, disp):
    ok = is_valid(res["status"])
    e = np.r_[res["u"] - disp[:, 0], res["v"] - disp[:, 1]][np.r_[ok, ok]]
    ec = np.r_[res["u_cc"] - disp[:, 0], res["v_cc"] - disp[:, 1]][np.r_[ok, ok]]
    return ok, e, ec


def _rms(e):
    return float(np.sqrt(np.mean(e**2)))


def _bound_per_unit_noise(xy, disp):
    """RMS (over dots and axes) of the displacement CRLB for noise 1; the bound scales with the noise."""
    sub = slice(None, None, 3)  # a third of the dots estimate the mean well
    b = displacement_crlb(xy[sub], (xy + disp)[sub], SHAPE, diameter=D, noise=1.0)
    return float(np.sqrt(np.mean(b**2)))


@pytest.mark.parametrize(("seed", "diameter"), [(31, D), (32, D), (33, None), (34, None)])
def test_no_noise_p95_below_0p005(seed, diameter):
    """Without noise both displacements are exact to well below 0.005 px (diameter given or estimated)."""
    xy, disp, ref, grad = _case(seed, 0.0)
    res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=diameter))
    ok, e, ec = _errors(res, disp)
    paper = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings.paper(diameter=D))
    _, ep, ecp = _errors(paper, disp)
    p95, p95c = np.percentile(np.abs(e), 95), np.percentile(np.abs(ec), 95)
    print(
        f"seed {seed}, no noise, {len(xy)} dots, max |u| {np.abs(disp).max():.2f} px, diameter "
        f"{'estimated' if diameter is None else diameter}: yield {ok.mean():.4f}; "
        f"p95 tracking {p95:.5f} px, tracking-cc {p95c:.5f} px (paper's procedure: "
        f"{np.percentile(np.abs(ep), 95):.5f}, {np.percentile(np.abs(ecp), 95):.5f})"
    )
    assert ok.mean() == 1.0
    assert p95 < 0.005
    assert p95c < 0.005


@pytest.mark.parametrize("noise", [0.01, 0.03, 0.05])
def test_noisy_rms_against_crlb(noise):
    """tracking-cc <= 1.2 x CRLB and <= tracking; tracking <= 1.3 x CRLB (per axis, displacement)."""
    for seed, diameter in ((31, D), (32, None)):
        xy, disp, ref, grad = _case(seed, noise)
        bound = noise * _bound_per_unit_noise(xy, disp)
        res = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings(diameter=diameter))
        ok, e, ec = _errors(res, disp)
        paper = track_pair(ref, grad, prior_xy=xy, settings=TrackingSettings.paper(diameter=diameter))
        _, ep, ecp = _errors(paper, disp)
        rms, rms_c = _rms(e), _rms(ec)
        msg = (
            f"seed {seed}, noise {noise:.0%}, diameter {'estimated' if diameter is None else diameter}: "
            f"displacement CRLB {bound:.4f} px per axis; tracking RMS "
            f"{rms:.4f} ({rms / bound:.3f}x), tracking-cc {rms_c:.4f} ({rms_c / bound:.3f}x); paper's "
            f"procedure {_rms(ep) / bound:.3f}x, {_rms(ecp) / bound:.3f}x; yield {ok.mean():.4f}"
        )
        print(msg)
        assert ok.mean() >= 0.998, msg
        assert rms_c <= 1.2 * bound, msg
        assert rms_c <= rms, msg
        assert rms <= 1.3 * bound, msg


def test_overlapping_dots_no_worse_than_paper_procedure():
    """Centre spacing 0.7 to 1 d: yield and error of the default next to the paper's procedure."""
    rows = []
    for seed in SEEDS[:2]:
        rng = np.random.default_rng(seed + 100)
        centres = jittered_grid(rng, SHAPE, spacing=11.0, margin=6.0)
        angle = rng.uniform(0, 2 * np.pi, len(centres))
        sep = rng.uniform(0.7 * D, 1.0 * D, len(centres))
        off = 0.5 * sep[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        xy = np.vstack([centres - off, centres + off])
        disp = smooth_field(rng, xy)
        ref = draw_dots(SHAPE, xy, D) + 0.01 * rng.standard_normal(SHAPE)
        grad = draw_dots(SHAPE, xy + disp, D) + 0.01 * rng.standard_normal(SHAPE)
        for name, s in (("default", TrackingSettings(diameter=D)), ("paper", TrackingSettings.paper(diameter=D))):
            ok, e, ec = _errors(track_pair(ref, grad, prior_xy=xy, settings=s), disp)
            rows.append((seed, name, ok.mean(), _rms(e), _rms(ec)))
            print(
                f"seed {seed}, pairs 0.7-1 d apart, noise 1%, {name}: yield {ok.mean():.4f}, "
                f"RMS tracking {_rms(e):.4f} px, tracking-cc {_rms(ec):.4f} px"
            )
    for k in range(0, len(rows), 2):
        new, old = rows[k], rows[k + 1]
        assert new[2] >= old[2] - 0.002
        assert new[3] <= old[3]
        assert new[4] <= old[4]


def test_model_fit_is_exact_without_noise_and_efficient_with():
    """Isolated dots: the fit has no bias, and its scatter under noise matches the position CRLB."""
    rng = np.random.default_rng(40)
    g = np.arange(8.0, 248.0, 10.0)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + rng.uniform(-0.5, 0.5, (len(g) ** 2, 2))
    clean = draw_dots(SHAPE, xy, D)
    half, render_half = fit_window_half(D / 4)
    start = np.c_[
        xy + rng.uniform(-0.3, 0.3, xy.shape), np.full(len(xy), 0.8), np.full(len(xy), 0.7), np.zeros(len(xy))
    ]
    p, ok, _ = fit_dots(clean, start, half=half, render_half=render_half, iterations=4, device="cpu")
    err0 = np.abs(p[:, :2] - xy).max()
    noise = 0.05
    errs = []
    for _ in range(4):
        img = clean + noise * rng.standard_normal(SHAPE)
        q, _, _ = fit_dots(img, start, half=half, render_half=render_half, iterations=4, device="cpu")
        errs.append(q[:, :2] - xy)
    rms = np.sqrt(np.mean(np.concatenate(errs) ** 2))
    bound = np.sqrt(np.mean(position_crlb(xy, SHAPE, diameter=D, noise=noise) ** 2))
    print(
        f"model fit, isolated dots: max error without noise {err0:.2e} px; at 5 % noise RMS {rms:.4f} px per "
        f"axis, position CRLB {bound:.4f} px ({rms / bound:.3f}x); sigma {np.median(p[:, 3]):.4f} (0.75)"
    )
    assert ok.all()
    assert err0 < 1e-4
    assert_allclose(p[:, 2:4], np.tile([1.0, 0.75], (len(xy), 1)), atol=1e-4)
    assert 0.9 < rms / bound < 1.1


def test_crlb_of_an_isolated_dot():
    """Pixel integration of a 3 px dot: about 0.92 sigma_n / I0 per axis (0.80 for a sampled Gaussian)."""
    xy = np.array([[20.0, 20.0], [40.3, 20.2], [60.5, 20.5]])
    c = position_crlb(xy, (64, 80), diameter=D, noise=1.0)
    c_known = position_crlb(xy, (64, 80), diameter=D, noise=1.0, nuisance=False)
    print(f"isolated 3 px dot CRLB per axis (noise 1, peak 1): {c[:, 0]}, shape known: {c_known[:, 0]}")
    assert_allclose(c, 0.92, atol=0.025)
    assert (c >= c_known - 1e-12).all()
    assert_allclose(position_crlb(xy, (64, 80), diameter=D, noise=0.5), 0.5 * c, rtol=1e-12)
    # A large dot holds more information per unit peak: the bound tends to sqrt(2 / pi) / I0.
    assert_allclose(position_crlb(xy[:1], (64, 80), diameter=12.0, noise=1.0, nuisance=False), 0.80, atol=0.01)


def test_fit_dots_kernel_matches_numpy_reference(device):
    rng = np.random.default_rng(41)
    shape = (96, 96)
    xy = dot_pattern(rng, shape, per_32x32=20, min_distance=D)
    n = len(xy)
    disp = rng.uniform(-1, 1, (n, 2))
    stack = np.stack([draw_dots(shape, xy, D), draw_dots(shape, xy + disp, D)]) + 0.03 * rng.standard_normal(
        (2, *shape)
    )
    start = np.c_[xy + rng.uniform(-0.3, 0.3, xy.shape), np.full(n, 0.9), np.full(n, 0.8), np.zeros(n)]
    params = np.vstack([start, start + np.c_[disp, np.zeros((n, 3))]])
    frame = np.r_[np.zeros(n, int), np.ones(n, int)]
    partner = np.r_[np.arange(n) + n, np.arange(n)]
    partner[[2, n + 2]] = -1  # one dot unpaired
    stack[0] = np.minimum(stack[0], 0.8)  # saturated pixels in the first image: left out of the fit
    half, render_half = fit_window_half(D / 4)
    kw = dict(half=half, render_half=render_half, frame=frame, partner=partner, saturation=(0.8, np.inf), iterations=3)
    a = fit_dots_numpy(stack, params, **kw)
    b = fit_dots(stack, params, device=device, **kw)
    for x, y in zip(a, b, strict=True):
        assert_allclose(y, x, rtol=0, atol=1e-10, equal_nan=True)
    assert np.isnan(a[2][[2, n + 2]]).all() and np.isfinite(np.delete(a[2], [2, n + 2], axis=0)).all()
    # the working arrays are kept between calls: a smaller fit in between leaves the result unchanged
    fit_dots(stack[:, :40, :50], params[:5], device=device, **{**kw, "frame": None, "partner": None})
    c = fit_dots(stack, params, device=device, **kw)
    for x, y in zip(b, c, strict=True):
        assert_array_equal(y, x)


def test_tracking_is_bit_reproducible(device):
    """The model images are summed in fixed point, so overlapping dots give the same bits in any thread
    order: two runs on one device (CUDA threads race) give identical tables."""
    rng = np.random.default_rng(43)
    shape = (128, 128)
    xy = dot_pattern(rng, shape, per_32x32=20, min_distance=0.8 * D)  # overlapping dots share pixels
    disp = smooth_displacement(xy, shape, amplitude=1.5)
    ref = draw_dots(shape, xy, D) + 0.02 * rng.standard_normal(shape)
    grad = draw_dots(shape, xy + disp, D) + 0.02 * rng.standard_normal(shape)
    first = track_pair(ref, grad, prior_xy=xy, device=device)
    _ = np.ones(1 << 20)  # other work between the runs
    second = track_pair(ref, grad, prior_xy=xy, device=device)
    for name in ("u", "v", "u_cc", "v_cc", "x", "y"):
        assert_array_equal(first[name], second[name])
