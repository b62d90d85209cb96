"""NumPy references of the tracker's Warp steps, for the tests only.

Each function here is the array-program definition of one step that production runs as Warp kernels
(on the CPU Warp compiles them to native code): the tests compare each kernel with its reference on
every available device. No production module imports this one (``tests/test_imports.py`` checks it).

- :func:`frame_statistics_numpy`: :func:`tracking.frame_stats.frame_statistics`;
- :func:`measure_windows_numpy`: :func:`tracking.windows.measure_windows` (identification, Eq. 1);
- :func:`deform_nearest_numpy`: the predictor's ``tracking.predict._deform_nearest``;
- :func:`fit_dots_numpy`, :func:`render_dots`, :func:`common_shape`: :func:`tracking.dotfit.fit_dots`;
- :func:`moment_shifts_numpy`: :func:`tracking.dotfit.moment_shifts` (with ``ellipse=True`` the elliptical
  moment step, :func:`tracking.ellipse.ellipse_step`; with ``kernel=True`` the shared-kernel step,
  :func:`tracking.kernel_step.kernel_step`, whose reference is in :mod:`tracking.reference_kernel`);
- :func:`neighbour_fit_numpy`: :func:`tracking.neighbours.neighbour_fit` (the outlier tests);
- :func:`neighbour_outliers_numpy`, :func:`confirmed_by_neighbours_numpy`: the two neighbour tests
  (:func:`tracking.neighbours.neighbour_outliers_stack`, :func:`tracking.neighbours.confirmed_by_neighbours_stack`);
- :func:`registration_offsets_numpy`: :func:`tracking.register.registration_offsets`.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.spatial import cKDTree
from synthbos.correlation.median_test import residual_limit

from .diameter import estimate_dot_diameter
from .dotfit import _checked, _noise, _saturation, integrated_profile
from .frame_stats import FRAME_STATISTICS, fill_level, saturation_level
from .identify import blob_score, estimate_noise, segment_windows
from .moment_kernels import (
    MAX_RESIDUAL_FLUX_REL,
    MAX_SHIFT_PER_SPREAD_REL,
    MAX_SHIFT_PX,
    MIN_SHIFT_PX,
    SHARE_FLOOR_REL,
)
from .predict import _bilinear, _tile_stack, _tiles_view
from .reference_kernel import kernel_shifts, taking_part
from .register import _gradients
from .register_kernels import MAX_STEP_PX, MIN_PIXELS, REGISTRATION_STEPS
from .settings import (
    ELLIPSE_DAMPING,
    ELLIPSE_MARQUARDT,
    ELLIPSE_MAX_STEP,
    ELLIPSE_MOMENT_ITERATIONS,
    ELLIPSE_SWEEPS,
    ELLIPSE_WIDTH_RANGE,
    FIT_MAX_MOVE_PX,
)

__all__ = [
    "common_shape",
    "confirmed_by_neighbours_numpy",
    "deform_nearest_numpy",
    "fit_dots_numpy",
    "frame_statistics_numpy",
    "measure_windows_numpy",
    "moment_shifts_numpy",
    "neighbour_fit_numpy",
    "neighbour_outliers_numpy",
    "registration_offsets_numpy",
    "render_dots",
]


def frame_statistics_numpy(images):
    """Reference of :func:`frame_statistics`: the tracker's host functions, frame by frame.

    Parameters
    ----------
    images : (F, H, W) array

    Returns
    -------
    dict of (F,) NumPy arrays
        The keys of :func:`frame_statistics`; ``bad`` int32, the others float64.
    """
    stack = np.asarray(images, dtype=np.float64)
    n = len(stack)
    out = {name: np.empty(n) for name in FRAME_STATISTICS}
    out["bad"] = np.zeros(n, dtype=np.int32)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite frames: NaN, as the device gives
        for f, image in enumerate(stack):
            lo, hi = image.min(), image.max()
            out["lo"][f], out["hi"][f] = lo, hi
            # the stack's two refusals of a frame (tracking.stack._frame_statistics)
            if not (np.isfinite(lo) and np.isfinite(hi)):
                out["bad"][f] = 1
            elif lo == 0 and hi == 0:
                out["bad"][f] = 2
            out["saturation"][f] = saturation_level(image, None)
            out["fill"][f] = fill_level(image)
            out["noise"][f] = estimate_noise(image)
            out["diameter"][f] = estimate_dot_diameter(image)
    return out


def _ring(w):
    idx = list(range(w)) + [(w - 1) * w + k for k in range(w)]
    for row in range(1, w - 1):
        idx += [row * w, row * w + w - 1]
    return np.array(idx)


def _dilate(mask):
    """3x3 dilation of a stack of boolean windows."""
    out = mask.copy()
    out[:, :, 1:] |= mask[:, :, :-1]
    out[:, :, :-1] |= mask[:, :, 1:]
    row = out.copy()
    out[:, 1:, :] |= row[:, :-1, :]
    out[:, :-1, :] |= row[:, 1:, :]
    return out


def measure_windows_numpy(
    image,
    origin,
    pred,
    *,
    half,
    map_half,
    radius,
    threshold_fraction,
    noise_floor,
    weights,
    use_minimum=False,
    saturation=np.inf,
    fill=0.0,
):
    """Reference of :func:`tracking.windows.measure_windows` (full dot maps): segment the window of each dot,
    choose its blob with Eq. 1 and cut out its dot map.

    Parameters
    ----------
    image : (H, W) float array
        The (residual) image.
    origin : (N, 2) int array
        Column and row of each window's first pixel; windows are ``2 half + 1`` pixels square.
    pred : (N, 2) array
        Predicted position (x, y) in the image; ``pred - origin`` is its place in the window.
    half, map_half : int, keyword-only
        Window and dot-map half-widths.
    radius : float, keyword-only
        Blobs whose peak lies farther than this from the prediction are not candidates.
    threshold_fraction, noise_floor : float, keyword-only
        Segmentation threshold ``bg + max(threshold_fraction (max - bg), noise_floor)``.
    weights : (W_A, W_I, W_dx), keyword-only
        Eq. 1 weights.
    use_minimum : bool, keyword-only
        Background = window minimum instead of the median of the window's edge pixels.
    saturation : float, keyword-only
        Pixels at or above it count as saturated.
    fill : float, keyword-only
        Value of pixels outside the image.

    Returns
    -------
    dict
        ``chosen`` (N,) flat window index of the chosen blob's peak pixel (-1: no candidate), ``nblobs``
        (blobs in the window), ``nsat`` (saturated pixels of the chosen blob), ``bg`` (background),
        ``peak`` (chosen peak minus background), ``dist`` (its distance from the prediction) and ``dotmap``
        (N, 2 map_half + 1, 2 map_half + 1): the chosen blob and its one-pixel rim minus background, other
        pixels zero, centred on the peak pixel.
    """
    image = np.asarray(image, dtype=np.float64)
    local = np.asarray(pred, dtype=np.float64) - origin
    n = len(origin)
    w = 2 * half + 1
    c = 2 * map_half + 1
    pad = w
    padded = np.pad(image, pad, constant_values=fill)
    win = sliding_window_view(padded, (w, w))[origin[:, 1] + pad, origin[:, 0] + pad]
    flat = win.reshape(n, w * w)
    bg = flat.min(axis=1) if use_minimum else np.median(flat[:, _ring(w)], axis=1)
    thr = bg + np.maximum(threshold_fraction * (flat.max(axis=1) - bg), noise_floor)
    lab = segment_windows(win, thr)
    pix = np.arange(w * w)
    roots = lab == pix
    fg = lab >= 0
    area = np.bincount((np.arange(n)[:, None] * (w * w) + lab)[fg], minlength=n * w * w).reshape(n, -1)
    dist = np.sqrt(((pix % w) - local[:, 0:1]) ** 2 + ((pix // w) - local[:, 1:2]) ** 2)
    cand = roots & (dist <= radius)
    peakv = flat - bg[:, None]
    score = blob_score(
        np.where(cand, area, np.nan),
        np.where(cand, peakv, np.nan),
        np.where(cand, dist, np.nan),
        weights=weights,
    )
    has = cand.any(axis=1)
    chosen = np.where(has, np.argmax(np.where(cand, score, -np.inf), axis=1), -1)
    rows = np.arange(n)
    ch = np.maximum(chosen, 0)
    chosen_mask = (lab == ch[:, None]) & has[:, None]
    other = fg & ~chosen_mask
    keep = _dilate(chosen_mask.reshape(n, w, w)) & ~other.reshape(n, w, w)
    maps = np.where(keep, win - bg[:, None, None], 0.0)
    mp = np.zeros((n, w + 2 * map_half, w + 2 * map_half))
    mp[:, map_half:-map_half, map_half:-map_half] = maps
    rr, rc = np.divmod(ch, w)
    dotmap = sliding_window_view(mp, (c, c), axis=(1, 2))[rows, rr, rc]
    return {
        "chosen": chosen,
        "nblobs": roots.sum(axis=1),
        "nsat": np.where(has, ((flat >= saturation) & chosen_mask).sum(axis=1), 0),
        "bg": bg,
        "peak": np.where(has, peakv[rows, ch], 0.0),
        "dist": np.where(has, dist[rows, ch], 0.0),
        "dotmap": np.where(has[:, None, None], dotmap, 0.0),
    }


def deform_nearest_numpy(image, valid, field, ys, xs, size):
    """NumPy reference of the predictor's ``tracking.predict._deform_nearest`` (for the tests)."""
    h, w = image.shape
    u, v, cy, cx = field
    ny, nx = len(ys), len(xs)
    rows = ys[0] + np.arange(ny * size)
    cols = xs[0] + np.arange(nx * size)
    shifts = [np.rint(_bilinear(f, cy, cx, rows[:, None], cols[None, :])).astype(np.int64) for f in (u, v)]
    ry, rx = rows[:, None] + shifts[1], cols[None, :] + shifts[0]
    inside = (ry >= 0) & (ry < h) & (rx >= 0) & (rx < w)
    ry, rx = np.clip(ry, 0, h - 1), np.clip(rx, 0, w - 1)
    weights = inside.astype(np.float32) * (1.0 if valid is None else valid[ry, rx])
    means = [s.reshape(ny, size, nx, size).mean(axis=(1, 3)) for s in shifts]
    partial = (weights != 1).reshape(ny, size, nx, size).any(axis=(1, 3))
    moved = image[ry, rx].astype(np.float32)
    at = size * np.arange(ny), size * np.arange(nx)
    stacks = [_tile_stack(_tiles_view(f, *at, size)) for f in (moved, weights)]
    return stacks[0], stacks[1][partial.ravel()] if partial.any() else None, means[0], means[1], partial


def _origin(params, half):
    return np.rint(params[:, 0]).astype(np.int64) - half, np.rint(params[:, 1]).astype(np.int64) - half


def common_shape(params, partner):
    """Each dot's common ``(I0, sigma)`` with its partner in the other image: the mean of the two fits.

    Parameters
    ----------
    params : (N, 5) array
    partner : (N,) int array
        Row of the same dot in the other image, -1 for none (its own shape is kept).

    Returns
    -------
    (N, 2) array
    """
    own = params[:, 2:4]
    other = params[np.maximum(partner, 0), 2:4]
    return np.where((partner >= 0)[:, None], 0.5 * (own + other), own)


def render_dots(shape, params, *, half, frame=None, common=None):
    """Images of the dots' models (backgrounds left out), each drawn on a ``2 half + 1`` square stamp.

    Parameters
    ----------
    shape : (H, W) or (K, H, W)
        Shape of one image or of a stack of K images.
    params : (N, 5) array
        Columns :data:`PARAMS`.
    half : int, keyword-only
        Stamp half-width, centred on the pixel nearest each dot.
    frame : (N,) int array, optional
        Image of each dot in the stack (all 0 by default).
    common : (N, 2) array, optional
        Draw each dot with this ``(I0, sigma)`` instead, linearised in sigma about the dot's own:
        ``I0' (p_x p_y + (sigma' - sigma) d(p_x p_y)/d sigma)``.

    Returns
    -------
    float64 array of ``shape``
    """
    params = np.asarray(params, dtype=np.float64).reshape(-1, 5)
    full = (1, *shape) if len(shape) == 2 else tuple(shape)
    k, h, w = full
    frame = np.zeros(len(params), dtype=np.int64) if frame is None else np.asarray(frame)
    if len(params) == 0:
        return np.zeros(shape)
    n = 2 * half + 1
    ox, oy = _origin(params, half)
    px, _, spx = integrated_profile(params[:, 0], params[:, 3], ox, n)
    py, _, spy = integrated_profile(params[:, 1], params[:, 3], oy, n)
    stamp = py[:, :, None] * px[:, None, :]
    if common is None:
        stamp = params[:, 2, None, None] * stamp
    else:
        ds = (common[:, 1] - params[:, 3])[:, None, None]
        dstamp = spy[:, :, None] * px[:, None, :] + py[:, :, None] * spx[:, None, :]
        stamp = common[:, 0, None, None] * (stamp + ds * dstamp)
    cols = np.broadcast_to((ox[:, None] + np.arange(n))[:, None, :], stamp.shape)
    rows = np.broadcast_to((oy[:, None] + np.arange(n))[:, :, None], stamp.shape)
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    flat = ((frame[:, None, None] * h + rows) * w + cols)[inside]
    return np.bincount(flat, weights=stamp[inside], minlength=k * h * w).reshape(shape)


def _windows(stack, frame, ox, oy, n):
    pad = n + 1
    padded = np.pad(stack, ((0, 0), (pad, pad), (pad, pad)))
    return sliding_window_view(padded, (n, n), axis=(1, 2))[frame, oy + pad, ox + pad]


def _step_numpy(images, models, params, start, frame, partner, saturation, *, half, max_move, sigma_range):
    """One Gauss-Newton step of every dot against its image minus the other dots (NumPy).

    ``models`` holds the free and the common-shape model images; returns the new parameters, the
    step's success and the position of the common-shape step (NaN without a partner).
    """
    n_dots = len(params)
    n = 2 * half + 1
    _, h, w = images.shape
    ox, oy = _origin(params, half)
    cols = ox[:, None] + np.arange(n)
    rows = oy[:, None] + np.arange(n)
    inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
    inside &= _windows(images, frame, ox, oy, n) < saturation[frame][:, None, None]  # saturated: no data
    x, y, a, s, b = params.T
    px, dpx, spx = integrated_profile(x, s, ox, n)
    py, dpy, spy = integrated_profile(y, s, oy, n)
    shape_xy = py[:, :, None] * px[:, None, :]
    jac = (
        np.stack(
            [
                a[:, None, None] * py[:, :, None] * dpx[:, None, :],
                a[:, None, None] * dpy[:, :, None] * px[:, None, :],
                shape_xy,
                a[:, None, None] * (spy[:, :, None] * px[:, None, :] + py[:, :, None] * spx[:, None, :]),
                np.ones_like(shape_xy),
            ],
            axis=-1,
        )
        * inside[..., None]
    )
    jac = jac.reshape(n_dots, n * n, 5)
    normal = np.einsum("npk,npl->nkl", jac, jac)
    # The model images hold every dot, this one included: the residual of the image less the other
    # dots against this dot's model and background is ``image - model - b``.
    rhs = []
    for model in models:
        resid = np.where(inside, _windows(images - model, frame, ox, oy, n) - b[:, None, None], 0.0)
        rhs.append(np.einsum("npk,np->nk", jac, resid.reshape(n_dots, n * n)))
    new = params + _limited(_solve_free(normal, rhs[0], np.ones(5)))
    ok = np.isfinite(new).all(axis=1)
    ok &= (np.abs(new[:, 0] - start[:, 0]) <= max_move) & (np.abs(new[:, 1] - start[:, 1]) <= max_move)
    ok &= (new[:, 2] > 0) & (new[:, 3] >= sigma_range[0]) & (new[:, 3] <= sigma_range[1])
    shared = params[:, :2] + _limited(_solve_free(normal, rhs[1], np.array([1.0, 1.0, 0.0, 0.0, 1.0])))[:, :2]
    shared[partner < 0] = np.nan
    return np.where(ok[:, None], new, params), ok, shared


def _solve_free(normal, rhs, free):
    """Gauss-Newton steps for the parameters with ``free = 1`` (the others' step is zero)."""
    a = normal * free[:, None] * free[None, :] + np.diag(1.0 - free + 1e-12)
    return np.linalg.solve(a, (rhs * free)[:, :, None])[:, :, 0]


def _limited(step):
    """Steps scaled so that the position moves at most half a pixel per axis."""
    big = np.abs(step[:, :2]).max(axis=1)
    return step * np.where(big > 0.5, 0.5 / np.where(big > 0.5, big, 1.0), 1.0)[:, None]


def fit_dots_numpy(
    images,
    params,
    *,
    half,
    render_half,
    frame=None,
    partner=None,
    saturation=None,
    iterations=2,
    max_move=FIT_MAX_MOVE_PX,
    sigma_range=(0.2, 10.0),
):
    """NumPy reference of :func:`tracking.dotfit.fit_dots` (for the tests).

    Parameters and result are those of :func:`tracking.dotfit.fit_dots`, without ``device``.
    """
    stack, p, frame, partner = _checked(images, params, frame, partner)
    stack = np.stack(stack)
    sat = _saturation(saturation, len(stack))
    start = p.copy()
    ok = np.ones(len(p), dtype=bool)
    shared = np.full((len(p), 2), np.nan)
    for _ in range(iterations):
        models = (
            render_dots(stack.shape, p, half=render_half, frame=frame),
            render_dots(stack.shape, p, half=render_half, frame=frame, common=common_shape(p, partner)),
        )
        p, ok, shared = _step_numpy(
            stack,
            models,
            p,
            start,
            frame,
            partner,
            sat,
            half=half,
            max_move=max_move,
            sigma_range=sigma_range,
        )
    return p, ok, shared


def moment_shifts_numpy(
    images,
    params,
    *,
    half,
    frame=None,
    partner=None,
    saturation=None,
    noise=None,
    chi2=25.0,
    max_shift=MAX_SHIFT_PX,
    ellipse=False,
    kernel=False,
    kernels=None,
):
    """NumPy reference of :func:`tracking.dotfit.moment_shifts` (for the tests).

    Parameters and result are those of :func:`tracking.dotfit.moment_shifts`, without ``device``;
    ``ellipse=True`` is the elliptical moment step (:func:`tracking.ellipse.ellipse_step`), ``kernel=True``
    that and then the shared-kernel step (:func:`tracking.kernel_step.kernel_step`; "prior": unfitted kernels).
    """
    stack, p, frame, partner = _checked(images, params, frame, partner)
    stack = np.stack(stack)
    k, h, w = stack.shape
    other = p[np.maximum(partner, 0)]
    background = np.where((frame == 1) & (partner >= 0), other[:, 4], p[:, 4])
    spread2 = np.where(partner >= 0, MAX_SHIFT_PER_SPREAD_REL**2 * np.maximum(p[:, 3] ** 2 - other[:, 3] ** 2, 0), 0.0)
    sat, sigma = _saturation(saturation, k), _noise(noise, k)
    n = 2 * half + 1
    ox, oy = _origin(p, half)
    px, _, _ = integrated_profile(p[:, 0], p[:, 3], ox, n)
    py, _, _ = integrated_profile(p[:, 1], p[:, 3], oy, n)
    own = p[:, 2, None, None] * py[:, :, None] * px[:, None, :]
    image, inside, xs, ys = _stamps(stack, p, frame, half)
    total = render_dots(stack.shape, p, half=half, frame=frame)
    total = total[frame[:, None, None], np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)]
    unsaturated = ~((image >= sat[frame][:, None, None]) & inside).any(axis=(1, 2))
    share = np.clip(own / np.maximum(total, SHARE_FLOOR_REL * np.abs(p[:, 2, None, None])), 0.0, 1.0) * inside
    wr = share * (image - background[:, None, None] - total)  # outside the image: the own model only
    dx = xs - p[:, 0, None, None]
    dy = ys - p[:, 1, None, None]
    own_flux = own.sum(axis=(1, 2))
    flux = own_flux + wr.sum(axis=(1, 2))
    safe = np.where(flux > 0, flux, 1.0)
    shift = np.stack([(dx * wr).sum(axis=(1, 2)), (dy * wr).sum(axis=(1, 2))], axis=1) / safe[:, None]
    var = sigma[frame] ** 2 * ((dx**2 + dy**2) * share**2).sum(axis=(1, 2)) / safe**2
    size2 = (shift**2).sum(axis=1)
    usable = (
        unsaturated
        & (flux > 0)
        & (np.abs(flux - own_flux) <= MAX_RESIDUAL_FLUX_REL * own_flux)
        & (size2 <= max_shift**2)
    )
    distorted = usable & (size2 > 0.5 * chi2 * var) & (size2 >= MIN_SHIFT_PX**2) & (size2 <= spread2)
    applied = usable & (distorted | ((partner >= 0) & distorted[np.maximum(partner, 0)]))
    if (ellipse or kernel) and (applied & (frame == 1)).any():
        active = applied & (frame == 1)
        centre, flux = _ellipse_moments(stack, p, frame, active, background, half)
        d = centre - p[active, :2]
        model_flux = 2 * np.pi * p[active, 2] * p[active, 3] ** 2
        ok = (d**2).sum(axis=1) <= max_shift**2
        ok &= np.abs(flux - model_flux) <= MAX_RESIDUAL_FLUX_REL * np.abs(model_flux)
        shift[np.flatnonzero(active)[ok]] = d[ok]
    if kernel and applied.any():
        part = taking_part(p, frame, applied)
        ell = _ellipse_fit(stack, p, frame, part, background, half)[0]  # the kernels' prior
        others = render_dots(stack.shape, p[~part], half=half, frame=frame[~part])  # the rest, symmetric
        shift = kernel_shifts(stack, p, frame, partner, applied, distorted, part, others, shift, background, half,
                              max_shift, ell, {} if kernels is None else kernels, fit=kernel != "prior")  # fmt: skip
    return np.where(applied[:, None], shift, 0.0), applied


def _stamps(stack, p, frame, half):
    """Each dot's ``2 half + 1`` stamp of its image (0 outside it), where it lies inside, and the stamp's
    pixel coordinates (x, y)."""
    h, w = stack.shape[1:]
    n = 2 * half + 1
    ox, oy = _origin(p, half)
    xs = np.broadcast_to((ox[:, None] + np.arange(n))[:, None, :], (len(p), n, n))
    ys = np.broadcast_to((oy[:, None] + np.arange(n))[:, :, None], (len(p), n, n))
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    image = stack[frame[:, None, None], np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)] * inside
    return image, inside, xs, ys


def _ellipse_model(ell, xs, ys):
    """The elliptical models ``(F, x0, y0, r1, r2, r3)`` (rows of ``ell``) at pixels ``xs, ys``, and
    ``e1, e2, dx, dy`` (``R (x - x0, y - y0) = (e1, e2)``)."""
    f, x0, y0, r1, r2, r3 = (ell[:, j, None, None] for j in range(6))
    dx, dy = xs - x0, ys - y0
    e1, e2 = r1 * dx + r2 * dy, r3 * dy
    return f * r1 * r3 / (2 * np.pi) * np.exp(-0.5 * (e1 * e1 + e2 * e2)), e1, e2, dx, dy


def _cholesky_solve6(a, g):
    """``a^-1 g`` for each of a stack of symmetric 6 x 6 matrices, 0 where one is not positive definite
    (the kernel's ``cholesky_solve6``, step by step)."""
    m = len(a)
    low = np.zeros_like(a)
    good = np.ones(m, dtype=bool)
    for j in range(6):
        s = a[:, j, j] - (low[:, j, :j] ** 2).sum(axis=1)
        good &= s > 0
        d = np.sqrt(np.where(s > 0, s, 1.0))
        low[:, j, j] = d
        for r in range(j + 1, 6):
            low[:, r, j] = (a[:, r, j] - (low[:, r, :j] * low[:, j, :j]).sum(axis=1)) / d
    y = np.zeros((m, 6))
    for j in range(6):
        y[:, j] = (g[:, j] - (low[:, j, :j] * y[:, :j]).sum(axis=1)) / low[:, j, j]
    x = np.zeros((m, 6))
    for j in range(5, -1, -1):
        x[:, j] = (y[:, j] - (low[:, j + 1 :, j] * x[:, j + 1 :]).sum(axis=1)) / low[:, j, j]
    return np.where(good[:, None], x, 0.0)


def _ellipse_moments(stack, p, frame, active, background, half):
    """The elliptical moment step's centres and fluxes of the ``active`` rows (NaN where the share holds
    no light): the reference of :func:`tracking.ellipse.ellipse_step`."""
    ell, rows, xs, ys, inside, image, b, model_image = _ellipse_fit(stack, p, frame, active, background, half)
    live = np.ones(len(rows), dtype=bool)
    for _ in range(ELLIPSE_MOMENT_ITERATIONS):
        m = _ellipse_model(ell, xs, ys)[0]
        floor = SHARE_FLOOR_REL * np.abs(p[rows, 2, None, None])
        share = np.clip(m / np.maximum(model_image(m), floor), 0.0, 1.0)
        light = np.where(inside, share * (image - b), m)
        flux = light.sum(axis=(1, 2))
        go = live & (flux > 0)
        safe = np.where(go, flux, 1.0)
        cx = p[rows, 0] + ((xs - p[rows, 0, None, None]) * light).sum(axis=(1, 2)) / safe
        cy = p[rows, 1] + ((ys - p[rows, 1, None, None]) * light).sum(axis=(1, 2)) / safe
        ell[go, 0], ell[go, 1], ell[go, 2] = flux[go], cx[go], cy[go]
        live = go
    return np.where(live[:, None], ell[:, 1:3], np.nan), np.where(live, ell[:, 0], np.nan)


def _ellipse_fit(stack, p, frame, active, background, half):
    """The elliptical models ``(F, x0, y0, r1, r2, r3)`` of the ``active`` rows after ``ELLIPSE_SWEEPS``
    sweeps (the others drawn symmetric), with their rows, stamps and a function drawing the model image."""
    rows = np.flatnonzero(active)
    others = render_dots(stack.shape, p[~active], half=half, frame=frame[~active])
    image, inside, xs, ys = (a[rows] for a in _stamps(stack, p, frame, half))
    h, w = stack.shape[1:]
    at = (np.broadcast_to(frame[rows, None, None], xs.shape)[inside], ys[inside], xs[inside])
    b = background[rows, None, None]
    w0 = np.sqrt(p[rows, 3] ** 2 + 1.0 / 12.0)
    ell = np.column_stack([2 * np.pi * p[rows, 2] * p[rows, 3] ** 2, p[rows, 0], p[rows, 1], 1 / w0, 0 * w0, 1 / w0])

    def model_image(m):
        img = others.copy()
        np.add.at(img, at, m[inside])
        return img[frame[rows, None, None], np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)]

    for _ in range(ELLIPSE_SWEEPS):
        m, e1, e2, dx, dy = _ellipse_model(ell, xs, ys)
        r1, r2, r3 = (ell[:, j, None, None] for j in (3, 4, 5))
        jac = np.stack([m / ell[:, 0, None, None], m * r1 * e1, m * (r2 * e1 + r3 * e2), m * (1 - r1 * e1 * dx),
                        -m * e1 * dy, m * (1 - r3 * e2 * dy)], axis=1) * inside[:, None]  # fmt: skip
        res = (image - b - model_image(m)) * inside
        a = np.einsum("nkij,nlij->nkl", jac, jac)
        g = np.einsum("nkij,nij->nk", jac, res)
        diag = np.arange(6)
        a[:, diag, diag] += ELLIPSE_MARQUARDT * np.maximum(a[:, diag, diag], 1e-12)
        step = _cholesky_solve6(a, g)
        step[:, 1:] = np.clip(step[:, 1:], -ELLIPSE_MAX_STEP, ELLIPSE_MAX_STEP)
        step *= ELLIPSE_DAMPING
        lo, hi = 1 / (ELLIPSE_WIDTH_RANGE[1] * w0), 1 / (ELLIPSE_WIDTH_RANGE[0] * w0)
        ell = np.column_stack([np.maximum(ell[:, 0] + step[:, 0], 0.1 * ell[:, 0]), ell[:, 1] + step[:, 1],
                               ell[:, 2] + step[:, 2], np.clip(ell[:, 3] * np.exp(step[:, 3]), lo, hi),
                               ell[:, 4] + step[:, 4], np.clip(ell[:, 5] * np.exp(step[:, 5]), lo, hi)])  # fmt: skip
    return ell, rows, xs, ys, inside, image, b, model_image


def neighbour_fit_numpy(xy, uv, query, self_index, *, k, return_neighbours=False):
    """NumPy reference of :func:`tracking.neighbours.neighbour_fit` (for the tests).

    Parameters and result are those of :func:`tracking.neighbours.neighbour_fit`, without ``device``.
    """
    xy = np.asarray(xy, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64)
    self_index = np.asarray(self_index)
    _, idx = cKDTree(xy).query(query, k=k + 1)
    drop = np.where((idx == self_index[:, None]).any(axis=1), np.argmax(idx == self_index[:, None], axis=1), k)
    keep = np.ones(idx.shape, dtype=bool)
    keep[np.arange(len(idx)), drop] = False
    nb = idx[keep].reshape(len(idx), k)
    # Components as separate (n, k) arrays: contiguous and cheap to gather.
    ex, ey = xy[:, 0][nb], xy[:, 1][nb]
    ex -= query[:, 0:1]
    ey -= query[:, 1:2]
    dmx, dmy = ex.mean(axis=1, keepdims=True), ey.mean(axis=1, keepdims=True)
    ex -= dmx
    ey -= dmy
    sxx, syy, sxy = (ex * ex).sum(1), (ey * ey).sum(1), (ex * ey).sum(1)
    ridge = 1e-6 * (k + sxx + syy)
    sxx += ridge
    syy += ridge
    det = sxx * syy - sxy * sxy
    value = np.empty((len(nb), 2))
    resid2 = np.zeros(nb.shape)
    for c in range(2):
        g = uv[:, c][nb]
        fm = g.mean(axis=1, keepdims=True)
        g -= fm
        bx, by = (ex * g).sum(1), (ey * g).sum(1)
        gx = ((syy * bx - sxy * by) / det)[:, None]
        gy = ((sxx * by - sxy * bx) / det)[:, None]
        value[:, c] = (fm - dmx * gx - dmy * gy)[:, 0]
        g -= ex * gx
        g -= ey * gy
        resid2 += g * g
    spread = np.median(np.sqrt(resid2), axis=1)
    return (value, spread, nb) if return_neighbours else (value, spread)


_CHUNK = 1024


def _bspline3(t):
    """(..., 4) weights and slopes of the cubic B-spline taps at offsets -1, 0, 1, 2 for fractions ``t``."""
    t = np.asarray(t)[..., None]
    sixth = 1.0 / 6.0
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    w1 = (3.0 * t3 - 6.0 * t2 + 4.0) * sixth
    w2 = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) * sixth
    w = np.concatenate([s * s * s * sixth, w1, w2, t3 * sixth], -1)
    dw = np.concatenate([-s * s * 0.5, 1.5 * t2 - 2.0 * t, -1.5 * t2 + t + 0.5, t2 * 0.5], -1)
    return w, dw


def _sums(ref, coef, xy, half, t, a):
    """Per dot: usable pixel count and the centred normal equations (axx, axy, ayy, bxr, byr)."""
    h, w = ref.shape
    off = np.arange(-half, half + 1)
    bx, by = np.rint(xy[:, 0]).astype(np.int64), np.rint(xy[:, 1]).astype(np.int64)
    px = np.broadcast_to((bx[:, None] + off)[:, None, :], (len(xy), off.size, off.size))  # column of each pixel
    py = np.broadcast_to((by[:, None] + off)[:, :, None], px.shape)
    dx0, dy0 = px - xy[:, 0, None, None], py - xy[:, 1, None, None]
    qx = px + t[:, 0, None, None] + (a[:, 0, 0, None, None] * dx0 + a[:, 0, 1, None, None] * dy0)
    qy = py + t[:, 1, None, None] + (a[:, 1, 0, None, None] * dx0 + a[:, 1, 1, None, None] * dy0)
    ix, iy = np.floor(qx).astype(np.int64), np.floor(qy).astype(np.int64)
    use = (px >= 1) & (py >= 1) & (px <= w - 2) & (py <= h - 2) & (ix >= 1) & (iy >= 1) & (ix <= w - 3) & (iy <= h - 3)
    wx, dwx = _bspline3(qx - ix)  # (N, n, n, 4)
    wy, dwy = _bspline3(qy - iy)
    rows = np.clip(iy[..., None] - 1 + np.arange(4), 0, h - 1)  # (N, n, n, 4)
    cols = np.clip(ix[..., None] - 1 + np.arange(4), 0, w - 1)
    taps = coef[rows[..., :, None], cols[..., None, :]]  # (N, n, n, 4 rows, 4 cols)
    row = (taps * wx[..., None, :]).sum(-1)
    drow = (taps * dwx[..., None, :]).sum(-1)
    g, gy, gx = (row * wy).sum(-1), (row * dwy).sum(-1), (drow * wy).sum(-1)
    pr, pc = np.clip(py, 1, h - 2), np.clip(px, 1, w - 2)
    r0 = ref[pr, pc]
    jx = 0.5 * (0.5 * (ref[pr, pc + 1] - ref[pr, pc - 1]) + gx)
    jy = 0.5 * (0.5 * (ref[pr + 1, pc] - ref[pr - 1, pc]) + gy)
    res = np.where(use, g - r0, 0.0)
    jx, jy = np.where(use, jx, 0.0), np.where(use, jy, 0.0)
    n = use.sum(axis=(1, 2)).astype(np.float64)
    safe = np.maximum(n, 1.0)
    s = {k: v.sum(axis=(1, 2)) for k, v in (("x", jx), ("y", jy), ("r", res))}
    axx = (jx * jx).sum(axis=(1, 2)) - s["x"] * s["x"] / safe
    axy = (jx * jy).sum(axis=(1, 2)) - s["x"] * s["y"] / safe
    ayy = (jy * jy).sum(axis=(1, 2)) - s["y"] * s["y"] / safe
    bxr = (jx * res).sum(axis=(1, 2)) - s["x"] * s["r"] / safe
    byr = (jy * res).sum(axis=(1, 2)) - s["y"] * s["r"] / safe
    return n, axx, axy, ayy, bxr, byr


def registration_offsets_numpy(reference, coefficients, xy, uv, *, half, gradients=None):
    """NumPy reference of :func:`tracking.register.registration_offsets` (for the tests).

    Parameters and result are those of :func:`tracking.register.registration_offsets`, without ``device``.
    """
    ref = np.asarray(reference, dtype=np.float64)
    coef = np.asarray(coefficients, dtype=np.float64)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    grads = _gradients(gradients, len(xy))
    c = np.zeros_like(uv)
    ok = np.ones(len(xy), dtype=bool)
    for a in range(0, len(xy), _CHUNK):  # bounded memory: 16 taps per window pixel per dot
        part = slice(a, a + _CHUNK)
        c[part], ok[part] = _register(ref, coef, xy[part], uv[part], grads[part], half)
    return c, ok


def _register(ref, coef, xy, uv, grads, half):
    c = np.zeros_like(uv)
    ok = np.ones(len(xy), dtype=bool)
    for _ in range(REGISTRATION_STEPS):
        act = np.flatnonzero(ok)
        if act.size == 0:
            break
        n, axx, axy, ayy, bxr, byr = _sums(ref, coef, xy[act], half, uv[act] + c[act], grads[act])
        det = axx * ayy - axy * axy
        solved = (n >= MIN_PIXELS) & (det > 0)
        ok[act[~solved]] = False
        safe = np.where(solved, det, 1.0)
        step = np.stack([-(ayy * bxr - axy * byr) / safe, -(axx * byr - axy * bxr) / safe], axis=1)
        c[act[solved]] += np.clip(step[solved], -MAX_STEP_PX, MAX_STEP_PX)
    return c, ok


def _outliers_of(xy, uv, k, threshold, epsilon, fit):
    """The outlier flags of one pair's vectors: two rounds, the second refitting only the vectors with a
    neighbour the first dropped, from the kept ones."""
    n = len(xy)
    if n <= k + 3 or not np.isfinite(threshold):
        return np.zeros(n, dtype=bool)

    def far(value, spread):  # |uv - fit| (the root of the sum of the two squares) beyond the limit
        d = uv - value
        return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) > residual_limit(spread, epsilon=epsilon,
                                                                                threshold=threshold)  # fmt: skip

    value, spread, near = fit(xy, uv, xy, np.arange(n), k=k, return_neighbours=True)
    bad = far(value, spread)
    clean = np.flatnonzero(~bad)
    if bad.any() and len(clean) > k + 3:
        where = np.full(n, -1)
        where[clean] = np.arange(len(clean))
        redo = np.flatnonzero(bad[near].any(axis=1))
        value[redo], spread[redo] = fit(xy[clean], uv[clean], xy[redo], where[redo], k=k)
        bad = far(value, spread)
    return bad


def neighbour_outliers_numpy(xy, uv, valid, *, k, threshold, epsilon, fit=neighbour_fit_numpy):
    """Reference of :func:`tracking.neighbours.neighbour_outliers_stack` (for the tests): (B, N) bool.

    ``fit`` is the local linear fit (:func:`neighbour_fit_numpy`'s parameters); the tests also pass
    :func:`tracking.neighbours.neighbour_fit`, whose fits are the stacked kernel's to the bit.
    """
    xy, uv, valid = np.asarray(xy, dtype=np.float64), np.asarray(uv, dtype=np.float64), np.asarray(valid, bool)
    bad = np.zeros(valid.shape, dtype=bool)
    for b in range(len(valid)):
        s = np.flatnonzero(valid[b])
        bad[b, s] = _outliers_of(xy[b, s], uv[b, s], int(k), threshold, epsilon, fit)
    return bad


def confirmed_by_neighbours_numpy(xy, uv, good, query, *, k, threshold, epsilon, tolerance,
                                  fit=neighbour_fit_numpy):  # fmt: skip
    """Reference of :func:`tracking.neighbours.confirmed_by_neighbours_stack` (for the tests): (B, N) bool.

    ``fit`` as for :func:`neighbour_outliers_numpy`.
    """
    xy, uv = np.asarray(xy, dtype=np.float64), np.asarray(uv, dtype=np.float64)
    good, query = np.asarray(good, bool), np.asarray(query, bool)
    ok = np.zeros(good.shape, dtype=bool)
    for b in range(len(good)):
        gi, qi = np.flatnonzero(good[b]), np.flatnonzero(query[b])
        if qi.size == 0 or gi.size <= k + 3 or not np.isfinite(threshold):
            continue
        value, spread = fit(xy[b, gi], uv[b, gi], xy[b, qi], np.full(len(qi), -1), k=int(k))
        r = np.linalg.norm(uv[b, qi] - value, axis=1)
        limit = np.minimum(residual_limit(spread, epsilon=epsilon, threshold=threshold), tolerance)
        ok[b, qi] = r <= limit
    return ok
