"""Least-squares fit of the pixel-integrated Gaussian dot model, each dot jointly with its neighbours.

The model of a dot is the one the images are made of: a Gaussian of peak ``I0`` and standard deviation
``sigma`` centred at ``(x, y)``, integrated over each pixel's area, on a local constant background
``b``. Integration over a square pixel separates into a product of two 1-D pixel profiles (differences
of error functions), so a dot's model, its derivatives and its Jacobian cost a few error functions per
row and column of its window.

Dots of a dense pattern overlap in their tails. Every dot is therefore fitted to the image minus the
current model of all the *other* dots (the residual image with its own model added back), and the
model image is redrawn between Gauss-Newton steps (block-Jacobi iteration on the joint least-squares
problem of all dots). At zero noise the fit converges to the exact positions; under white noise it is
the maximum-likelihood estimate and reaches the Cramer-Rao bound (:mod:`tracking.crlb`).

:func:`fit_dots` runs the iteration with Warp kernels (one thread per dot); :func:`tracking.reference.fit_dots_numpy` is
the array-program reference that defines the result. :func:`fit_stack` runs ``track_pair``'s model fit
(the joint fit, the first-moment step, the fit's results taken) for every pair of a stack on one device.
One pair and a stack take the same steps (``_fit_steps``, ``_moment_codes``) through the same kernels
(``tracking.fit_kernels.fit_step_stack``, ``tracking.moment_kernels.moment_shift_stack``): one pair is a stack of one.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import warp as wp

from . import fit_kernels as fk
from . import moment_kernels as mk
from .ellipse import ellipse_step
from .frame_stats import segment_medians
from .kernel_step import kernel_step
from .settings import FIT_MAX_MOVE_PX, MODEL_WIDTH_RANGE, distortion_options, start_width
from .workspace import per_thread, scratch

__all__ = [
    "PARAMS",
    "erf_from_gauss",
    "fit_dots",
    "fit_stack",
    "fit_window_half",
    "integrated_profile",
    "moment_shifts",
]

PARAMS = ("x", "y", "peak", "sigma", "background")
"""Columns of a parameter array: centre (x = column), peak ``I0``, standard deviation, background."""

_SQRT_HALF_PI = np.sqrt(np.pi / 2.0)


def fit_window_half(sigma):
    """Half-widths ``(fit, render)`` of the windows used for dots of standard deviation ``sigma`` (px).

    The fit window (``2 fit + 1`` pixels square, at least 5) holds the pixels that carry nearly all of
    the position information (out to ~2.7 sigma); the rendering stamp reaches 4 sigma, where a dot's
    intensity is below 4e-4 of its peak.
    """
    fit = max(2, int(np.ceil(2.5 * sigma - 0.05)))
    return fit, max(fit, int(np.ceil(4.0 * sigma)))


def erf_from_gauss(x, g):
    """``erf(x)`` given ``g = exp(-x^2)`` (Abramowitz and Stegun 1964, 7.1.26; absolute error < 1.5e-7).

    The profiles need ``exp(-x^2)`` at every pixel edge anyway, so the error function costs a division
    and a polynomial.
    """
    t = 1.0 / (1.0 + 0.3275911 * np.abs(x))
    poly = ((((1.061405429 * t - 1.453152027) * t + 1.421413741) * t - 0.284496736) * t + 0.254829592) * t
    return np.copysign(1.0 - poly * g, x)


def integrated_profile(centre, sigma, first, n):
    """1-D pixel profile of a unit-peak Gaussian and its derivatives, for a stack of dots.

    Parameters
    ----------
    centre, sigma : (N,) arrays
        Centre and standard deviation, pixels.
    first : (N,) int array
        First pixel of each dot's window; pixel ``k`` spans ``[k - 0.5, k + 0.5]``.
    n : int
        Window length.

    Returns
    -------
    p, dp_dc, dp_ds : (N, n) arrays
        ``p_k = int_{k-1/2}^{k+1/2} exp(-(t - c)^2 / (2 s^2)) dt`` and its derivatives with respect to
        ``c`` and ``s``.

    Notes
    -----
    With the standardised edges ``z = (k -+ 1/2 - c) / s``: ``p = sqrt(pi / 2) s [erf(z / sqrt 2)]``,
    ``dp/dc = [-exp(-z^2 / 2)]`` and ``dp/ds = [-z exp(-z^2 / 2)] + p / s``, each ``[f]`` meaning
    ``f(z_upper) - f(z_lower)``. A dot's model is ``I0 p_x p_y + b``. The error function is
    :func:`erf_from_gauss` (absolute error below 1.5e-7 of the peak: a position bias below 1e-6 px).
    """
    centre = np.asarray(centre, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    z0 = (np.asarray(first) - 0.5 - centre) / sigma
    z = z0[:, None] + np.arange(n + 1)[None, :] / sigma[:, None]
    g = np.exp(-0.5 * z * z)
    p = np.diff(_SQRT_HALF_PI * sigma[:, None] * erf_from_gauss(z / np.sqrt(2.0), g), axis=1)
    dp_dc = g[:, :-1] - g[:, 1:]
    zg = z * g
    dp_ds = zg[:, :-1] - zg[:, 1:] + p / sigma[:, None]
    return p, dp_dc, dp_ds



def _saturation(saturation, k):
    if saturation is None:
        return np.full(k, np.inf)
    return np.broadcast_to(np.asarray(saturation, dtype=np.float64), (k,)).copy()


def _image_list(images):
    """The images as a list of 2-D float64 arrays (no copy where they already are)."""
    if isinstance(images, np.ndarray) and images.ndim == 2:
        images = [images]
    out = [np.asarray(a, dtype=np.float64) for a in images]
    if not out or any(a.ndim != 2 or a.shape != out[0].shape for a in out):
        raise ValueError("fit_dots needs one 2-D image or a stack of images of one shape")
    return out


def _checked(images, params, frame, partner):
    stack = _image_list(images)
    p = np.asarray(params, dtype=np.float64).reshape(-1, 5)  # not modified: no copy
    if not np.isfinite(p).all():
        raise ValueError("fit_dots needs finite starting parameters")
    n = len(p)
    frame = np.zeros(n, dtype=np.int64) if frame is None else np.asarray(frame, dtype=np.int64)
    partner = np.full(n, -1, dtype=np.int64) if partner is None else np.asarray(partner, dtype=np.int64)
    if frame.shape != (n,) or partner.shape != (n,):
        raise ValueError("frame and partner need one entry per dot")
    if n and (frame.min() < 0 or frame.max() >= len(stack) or partner.max() >= n):
        raise ValueError("frame or partner index out of range")
    return stack, p, frame, partner



def _raster_order(p, frame):
    """Dots in raster order of 4-row bands, and its inverse: neighbouring threads read neighbouring pixels.

    Only the speed depends on the order; one integer key, quicksorted, sorts in a twentieth of the time
    of a lexsort of the floats. Bands of 4 rows keep fewer model-image rows in flight than 8 (a tenth
    less time for the render and step kernels on the CPU; 16 rows take a quarter more).
    """
    band = np.floor(p[:, 1] / 4.0).astype(np.int64)
    col = np.rint(p[:, 0]).astype(np.int64)
    band -= band.min()
    col -= col.min()
    order = np.argsort((frame * (band.max() + 1) + band) * (col.max() + 1) + col)
    back = np.empty_like(order)
    back[order] = np.arange(len(p))
    return order, back


def _device_layout(stack, p, frame, partner, what, device):
    """The images of frames 0 and 1 on ``device`` as they are (no stacked copy; the same one twice for a
    single image), each as a stack of one (1, H, W), the dots' raster order and its inverse, and their
    frames and partners in that order."""
    if len(stack) > 2:
        raise ValueError(f"{what} takes one image or a pair, got {len(stack)}")
    order, back = _raster_order(p, frame)
    img0 = _on_device(stack[0], wp.float64, device).reshape((1, *stack[0].shape))
    img1 = _on_device(stack[-1], wp.float64, device).reshape((1, *stack[0].shape))
    fr = _on_device(np.take(frame, order), wp.int32, device)
    po = np.take(partner, order)
    pa = _on_device(np.where(po >= 0, np.take(back, np.maximum(po, 0)), -1), wp.int32, device)
    return img0, img1, order, back, fr, pa


def _on_device(a, dtype, device):
    """A Warp array of ``a``; on the CPU it shares the NumPy array's memory (no copy)."""
    a = np.ascontiguousarray(a, dtype=np.float64 if dtype == wp.float64 else np.int32)
    return wp.array(a, dtype=dtype, device=device, copy=not wp.get_device(device).is_cpu)


def fit_dots(
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
    device=None,
):
    """Fit the pixel-integrated Gaussian model to every dot of one image or a pair, jointly with its neighbours.

    Parameters
    ----------
    images : (H, W) array, (K, H, W) array or sequence of (H, W) arrays
        One image or a stack (the reference and gradient images of a pair; :func:`fit_dots` takes at
        most two).
    params : (N, 5) array
        Starting parameters, columns :data:`PARAMS` (finite).
    half, render_half : int, keyword-only
        Half-widths of each dot's fit window and of its rendered stamp (:func:`fit_window_half`).
    frame : (N,) int array, optional, keyword-only
        Image of each dot in the stack; all 0 by default.
    partner : (N,) int array, optional, keyword-only
        Row of the same dot in the other image of a pair, -1 for none.
    saturation : float or (K,) array, optional, keyword-only
        Saturation level of each image: pixels at or above it are left out of the fit (they only tell
        that the intensity is at least that). None: no saturation.
    iterations : int, keyword-only
        Gauss-Newton steps; the model images are redrawn before each.
    max_move : float, keyword-only
        A step that takes a dot farther than this (px, per axis) from its start is refused.
    sigma_range : (float, float), keyword-only
        A step that takes ``sigma`` outside this range (or ``I0`` to zero) is refused.

    device : str or None, keyword-only
        Warp device ("cpu", "cuda:0"); Warp's default when None.

    Returns
    -------
    params : (N, 5) array
        Fitted parameters, each image fitted on its own.
    ok : (N,) bool array
        False where the last step was refused (the dot keeps its previous parameters).
    shared_xy : (N, 2) array
        Positions of the last step taken with every paired dot at its pair's common shape
        (the mean of the two fits' ``I0`` and ``sigma``); NaN for dots without a partner. Their difference
        across a pair is the model correction.

    Notes
    -----
    Block-Jacobi Gauss-Newton on ``sum_pixels (I - sum_dots (I0 p_x p_y + b))^2``: before each step the
    model image ``R`` of all dots is drawn, and dot ``i`` takes one Gauss-Newton step on its window of
    ``I - R + I0_i p_x p_y`` (the image with the other dots removed) with its five parameters. For
    non-touching dots it is the Gauss-Newton fit of Brady, Raben and Vlachos (2009, section 2.3) with
    the pixel-integrated model instead of a sampled Gaussian, which removes that fit's bias on small
    dots; the joint fit removes the bias that neighbours' tails cause in a dense pattern.

    The common-shape step is the same step for position and background only, against the model image
    ``R'`` in which every paired dot has its pair's mean ``I0`` and ``sigma``: the shift that best maps
    the reference dot onto the gradient dot when both share one shape. With two fewer free parameters
    per dot, and its neighbours' shapes averaged over both images, it is the more precise of the two.
    """
    stack, p, frame, partner = _checked(images, params, frame, partner)
    n = len(p)
    if n == 0:
        return p, np.ones(0, dtype=bool), np.zeros((0, 2))
    if render_half < half:
        raise ValueError(f"render_half ({render_half}) must be at least half ({half})")
    refs, grads, order, back, fr, pa = _device_layout(stack, p, frame, partner, "fit_dots", device)
    sat = wp.array(np.minimum(_saturation(saturation, len(stack)), 1e300), dtype=wp.float64, device=device)
    width = wp.array(np.asarray([sigma_range], dtype=np.float64), dtype=wp.vec2d, device=device)
    # Working arrays from the thread's workspace (results are copied out at the end). The starting
    # parameters are gathered in the new order straight into ``start`` (np.take gathers rows several
    # times faster than fancy indexing); ``nxt`` needs no start: every step writes all of its rows.
    start = scratch("fit_start", (n, 5), wp.float64, device)
    if wp.get_device(device).is_cpu:
        np.take(p, order, axis=0, out=start.numpy(), mode="clip")  # (valid indices; "raise" buffers `out`)
    else:
        start.assign(np.take(p, order, axis=0))
    live = scratch("fit_live", (n,), wp.int32, device)
    live.fill_(1)
    rows = _Rows(start, fr, pa, live)
    bufs = _FitBuffers(
        scratch("fit_models", (2 * len(stack) * refs.shape[1] * refs.shape[2],), wp.int64, device),
        scratch("fit_params", (n, 5), wp.float64, device),
        scratch("fit_params_next", (n, 5), wp.float64, device),
        scratch("fit_ok", (n,), wp.int32, device),
        scratch("fit_shared", (n, 2), wp.float64, device),
        _profiles("fit_profiles", n, render_half, device),
    )
    cur = _fit_steps(refs, grads, rows, bufs, sat, width, half=half, render_half=render_half, iterations=iterations,
                     max_move=max_move, device=device)  # fmt: skip
    ok = bufs.ok.numpy()[back].astype(bool)
    return np.take(cur.numpy(), back, axis=0), ok, np.take(bufs.shared.numpy(), back, axis=0)


class _Rows(NamedTuple):
    """The rows of a fit: their starting (or fitted) parameters (R, 5), frames, partners (-1: none) and
    whether each is a dot (a row not live is neither fitted nor drawn into the model images)."""

    params: wp.array
    frame: wp.array
    partner: wp.array
    live: wp.array


class _FitBuffers(NamedTuple):
    """The fit's working arrays: the flat fixed-point model images (two layers of every frame), the
    parameters of the current and the next step, ``ok``, the common-shape positions and the profiles."""

    models: wp.array
    cur: wp.array
    nxt: wp.array
    ok: wp.array
    shared: wp.array
    prof: wp.array


#: Rows per thread of ``largest_peak``.
_PEAK_CHUNK = 32


def _frame_scales_of(params, live, frame, pairs, device):
    """The fixed-point scale of every frame (units per intensity of the model images), on the device: from
    each pair's largest live peak, ``2**50 / (16 peak)`` for its two frames (``fit_kernels.frame_scales``).
    A model pixel holds at most a few overlapping dots' peaks, so the scale keeps it far inside int64 and
    resolves 1e-14 of the peak; a pair's scale depends on its own dots only, so a pair's bits do not depend
    on its stack.

    Examples
    --------
    >>> params = wp.array([[1.0, 1.0, 2.0**40, 1.0, 0.0], [1.0, 1.0, -(2.0**44), 1.0, 0.0]], dtype=wp.float64)
    >>> ones = wp.array([1, 1], dtype=wp.int32)
    >>> _frame_scales_of(params, ones, wp.array([1, 2], dtype=wp.int32), 2, "cpu").numpy().tolist()
    [64.0, 64.0, 4.0, 4.0]
    """
    n = params.shape[0]
    peak = wp.zeros(pairs, dtype=wp.float64, device=device)
    _launch(fk.largest_peak, (n + _PEAK_CHUNK - 1) // _PEAK_CHUNK, [params, live, frame, _PEAK_CHUNK, peak], device)
    scales = wp.empty(2 * pairs, dtype=wp.float64, device=device)
    _launch(fk.frame_scales, 2 * pairs, [peak, scales], device)
    return scales


def _fit_steps(refs, grads, rows, bufs, sat, width, *, half, render_half, iterations, max_move, device):
    """The block-Jacobi Gauss-Newton steps of :func:`fit_dots` on the rows of a stack of pairs.

    ``refs``, ``grads``: (B, H, W) float64 Warp arrays (model frame ``2 b``: ``refs[b]``, ``2 b + 1``:
    ``grads[b]``); ``rows``: :class:`_Rows` (the starting parameters, kept); ``bufs``: :class:`_FitBuffers`
    (``ok`` and ``shared`` written at the live rows); ``sat``: per frame; ``width``: each pair's width range
    (vec2d). Returns the parameters of the last step (``bufs.cur`` or ``bufs.nxt``).
    """
    H, W = refs.shape[1:]
    n = rows.params.shape[0]
    layer = bufs.models.shape[0] // 2
    cur, nxt = bufs.cur, bufs.nxt
    cur.assign(rows.params)
    for it in range(iterations):
        last = it == iterations - 1
        scales = _frame_scales_of(cur, rows.live, rows.frame, refs.shape[0], device)
        # the free model image every step; the common-shape one only for the last step (the only one whose
        # common-shape positions are kept)
        if last:
            bufs.models.zero_()
        else:
            bufs.models[:layer].zero_()
        _render(cur, rows, render_half, last, it == 0, bufs.prof, scales, (H, W), bufs.models, device)
        _launch(
            fk.fit_step_stack,
            n,
            [
                refs, grads, bufs.models, scales, cur, rows.params, rows.frame, rows.partner, rows.live, sat, width,
                int(half), int(render_half), int(last), float(max_move), bufs.prof, nxt, bufs.ok, bufs.shared,
            ],
            device,
        )  # fmt: skip
        cur, nxt = nxt, cur
    return cur


def _noise(noise, k):
    return np.zeros(k) if noise is None else np.broadcast_to(np.asarray(noise, dtype=np.float64), (k,)).copy()



def moment_shifts(
    images,
    params,
    *,
    half,
    frame=None,
    partner=None,
    saturation=None,
    noise=None,
    chi2=25.0,
    max_shift=mk.MAX_SHIFT_PX,
    ellipse=False,
    kernel=False,
    kernels=None,
    device=None,
):
    """Shift from each dot's fitted centre to the first moment of its share of the light (the reference).

    A symmetric model's centre is the mean of a dot's light only while the dot's image is symmetric. A
    dot seen through a flow is the spot spread by the landing positions of rays that crossed different
    density, and the mean landing position is what the truth (and BOS) defines. The step weighs what the
    model leaves over: with ``M`` the model image of every dot, ``m_i`` dot i's own model and ``R = I - b_i
    - M`` the residual on dot i's stamp, dot i's share of the light is ``m_i + w R`` with ``w = m_i / M``
    (``M`` at least ``SHARE_FLOOR_REL`` = 1e-6 of the dot's peak), and its first moment about the model
    centre ``(x_i, y_i)`` is (the own model, symmetric about the centre, adds nothing to the numerators)

    ``dx = sum (x - x_i) w R / F``, ``dy = sum (y - y_i) w R / F``, ``F = sum (m_i + w R)``.

    Parameters
    ----------
    images : (H, W) array, (K, H, W) array or sequence of (H, W) arrays
        As for :func:`fit_dots`.
    params : (N, 5) array
        Fitted parameters (columns :data:`PARAMS`).
    half : int, keyword-only
        Half-width of the stamp on which each dot is rendered and weighed (the fit's ``render_half``).
    frame : (N,) int array, optional, keyword-only
        Image of each dot in the stack: 0 the reference, 1 the gradient image.
    partner : (N,) int array, optional, keyword-only
        Row of the same dot in the other image, -1 for none. The background ``b_i`` under a gradient
        image's dot is its reference partner's fitted background (the same target and light, seen
        undistorted: a distorted dot's own fit lifts or lowers its background by up to 1 % of the peak
        to absorb the asymmetric light, which would bias the moment); other dots keep their own.
    saturation : float or (K,) array, optional, keyword-only
        Saturation level of each image; a stamp holding a pixel at or above it is left alone.
    noise : float or (K,) array, optional, keyword-only
        Noise standard deviation of each image (0 by default).
    chi2 : float, keyword-only
        The shift is applied only where it is significant: ``|d|^2 / (var_d / 2) > chi2``, with
        ``var_d = noise^2 sum (r - r_i)^2 w^2 / F^2`` (both axes) its variance under white noise.
        Where the dot is an undistorted spot under noise, a shift this large is a chance event of
        probability ``exp(-chi2 / 2)`` (3.7e-6 at 25), so the fit keeps its Cramer-Rao precision there.
    max_shift : float, keyword-only
        A larger shift (px) is not applied (default ``tracking.moment_kernels.MAX_SHIFT_PX``, 1 px).
    ellipse : bool; kernel : bool or "prior", keyword-only
        The elliptical moment step (:func:`tracking.ellipse.ellipse_step`: moving gradient-image dots share
        the light by fitted elliptical models), then the shared-kernel step (implies ``ellipse``; "prior":
        kernels left at their elliptical prior), :func:`tracking.kernel_step.kernel_step`.
    kernels : dict, optional, keyword-only
        With ``kernel``: receives ``rows`` (those of the step, ascending), ``kernel`` ((R, 81), index
        ``9 b + a`` for y tap b, x tap a) and ``position`` ((R, 2)); empty where no dot moves.
    device : str or None, keyword-only
        Warp device ("cpu", "cuda:0"); Warp's default when None.

    Returns
    -------
    shift : (N, 2) array
        ``(dx, dy)``, px: 0 where not applied.
    applied : (N,) bool array
        Where the shift is usable and the dot or its partner is distorted: a matched pair is measured
        alike in both images (the fit's own residuals in a tight cluster, alike in both, then cancel in
        the displacement). Usable: no pixel of the stamp inside the image is saturated (pixels outside
        it count as the dot's own model, which has no first moment), the residual
        light of the dot's share is at most ``MAX_RESIDUAL_FLUX_REL`` (0.25) of its model's (more is
        another dot's light, not a distortion) and the shift is at most ``max_shift``. Distorted: the
        shift is also significant, at least ``MIN_SHIFT_PX`` (1e-3 px) and at most
        ``MAX_SHIFT_PER_SPREAD_REL`` (1) times the spread the dot's fitted width adds to its partner's,
        ``sqrt(sigma^2 - sigma_partner^2)`` (a dot without a partner, or no wider than it, is not).

    Examples
    --------
    A reference spot, and in the gradient image the same spot with a faint second one 1 px to its right:
    the fit's centre sits on the main spot (its width grown to 0.85 px), the first moment 0.111 px further
    right (the second spot holds 1/9 of the light); the undistorted reference's first moment is its centre.

    >>> import numpy as np
    >>> from synthbos.raytrace.dots import draw_dots
    >>> reference = draw_dots((15, 15), [[7.0, 7.0]], 3.2, radius_sigmas=6.25)
    >>> gradient = reference + draw_dots((15, 15), [[8.0, 7.0]], 3.2, intensity=0.125, radius_sigmas=6.25)
    >>> fitted = [[7.0, 7.0, 1.0, 0.8, 0.0], [7.0, 7.0, 1.0, 0.85, 0.0]]
    >>> shift, applied = moment_shifts(
    ...     [reference, gradient], fitted, half=5, frame=[0, 1], partner=[1, 0]
    ... )
    >>> (np.round(shift, 3) + 0.0).tolist(), applied.tolist()  # + 0.0: no negative zeros
    ([[0.0, 0.0], [0.111, 0.0]], [True, True])
    """
    stack, p, frame, partner = _checked(images, params, frame, partner)
    n = len(p)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    k = len(stack)
    refs, grads, order, back, fr, pa = _device_layout(stack, p, frame, partner, "moment_shifts", device)
    live = scratch("moment_live", (n,), wp.int32, device)
    live.fill_(1)
    rows = _Rows(_on_device(np.take(p, order, axis=0), wp.float64, device), fr, pa, live)
    models = scratch("moment_models", (k * refs.shape[1] * refs.shape[2],), wp.int64, device)
    prof = _profiles("moment_profiles", n, half, device)
    sat = wp.array(np.minimum(_saturation(saturation, k), 1e300), dtype=wp.float64, device=device)
    sig = wp.array(_noise(noise, k), dtype=wp.float64, device=device)
    record = {} if kernels is not None else None
    out = _moment_codes(refs, grads, rows, models, prof, sat, sig, half=int(half), chi2=chi2, max_shift=max_shift,
                        ellipse=ellipse, kernel=kernel, record=record, device=device)  # fmt: skip
    if record:
        at = np.argsort(order[record["rows"]])
        kernels.update(rows=order[record["rows"]][at], kernel=record["kernel"][at], position=record["position"][at])
    moved = wp.empty(n, dtype=wp.int32, device=device)
    wp.launch(mk.moment_moves_kernel, dim=n, inputs=[out, pa, moved], device=device)
    applied = moved.numpy()[back].astype(bool)
    return np.where(applied[:, None], np.take(out.numpy()[:, :2], back, axis=0), 0.0), applied


def _moment_codes(refs, grads, rows, models, prof, sat, noise, *, half, chi2, max_shift, ellipse, kernel, device,
                  record=None):
    """The first-moment step's shift and code of every row (``moment_shift``; a row not live gets none):
    the model image of every live row at its parameters is drawn into ``models`` (one layer of every
    frame, with the profiles into ``prof``), then each row's first moment taken (with ``ellipse``, a
    gradient-image row that moves takes its elliptical moment, :func:`tracking.ellipse.ellipse_step`; with
    ``kernel``, then every moving row its shared-kernel moment, :func:`tracking.kernel_step.kernel_step`, its
    kernels into ``record``).
    ``refs``, ``grads``, ``rows``, ``sat``: as for :func:`_fit_steps`; ``noise``: per frame; ``half``: the
    model's half-size. Returns a (R,) vec3d Warp array."""
    H, W = refs.shape[1:]
    n = rows.params.shape[0]
    scales = _frame_scales_of(rows.params, rows.live, rows.frame, refs.shape[0], device)
    models.zero_()
    _render(rows.params, rows, half, False, True, prof, scales, (H, W), models, device)
    shift = wp.empty(n, dtype=wp.vec3d, device=device)
    _launch(
        mk.moment_shift_stack,
        n,
        [
            refs, grads, models, scales, rows.params, rows.frame, rows.partner, rows.live, sat, noise, half,
            float(chi2), float(max_shift), prof, shift,
        ],
        device,
    )  # fmt: skip
    if ellipse or kernel:
        ellipse_step(grads, models, scales, rows.params, rows.frame, rows.partner, prof, shift, half=half,
                     max_shift=float(max_shift), device=device)  # fmt: skip
    if kernel:
        kernel_step(refs, grads, models, scales, rows.params, rows.frame, rows.partner, rows.live, prof, shift,
                    half=half, max_shift=float(max_shift), fit=kernel != "prior", record=record,
                    device=device)  # fmt: skip
    return shift


# --- a stack of pairs on one Warp device ------------------------------------------------------------


def _render(params, rows, half, common, profiles, prof, scales, shape, models, device):
    """Add every row's model at ``params`` into the ``shape`` (H, W) model images ``models``
    (``fit_kernels.render_dots_kernel``; with ``common``, the common-shape layer too; with ``profiles``, the
    rows' stamp profiles into ``prof`` first). A thread per stamp column on a GPU, per row on the CPU: the
    same bits (fixed-point sums)."""
    n, half = params.shape[0], int(half)
    parts = 2 * half + 1 if wp.get_device(device).is_cuda else 1
    if profiles and parts > 1:
        _launch(fk.dot_profiles_kernel, n, [params, half, prof], device)
    inputs = [params, rows.frame, rows.partner, half, int(common), int(profiles and parts == 1), parts, prof, scales,
              *shape, models]  # fmt: skip
    _launch(fk.render_dots_kernel, n * parts, inputs, device)


def _launch(kernel, dim, inputs, device):
    if dim:
        wp.launch(kernel, dim=dim, inputs=inputs, device=device)


def fit_stack(refs, grads, r, g, *, eta0, sat_frames, noise_frames, fit_half, render_half, settings, device,
              take=True):  # fmt: skip
    """The model fit of every dot of a stack of pairs, on one device: the joint least-squares fit of the
    pixel-integrated dot model to the dots found in both images of each pair (rows of one prior row are
    partners, so the last step also gives their positions at the pair's common shape, the model
    correction); with a ``settings.distortion`` step, the moving dots then move to the first moments of
    their light (:func:`moment_shifts`' rule), and their common-shape positions with them.

    Parameters
    ----------
    refs, grads : (B, H, W) float64 Warp arrays
        The image pairs.
    r, g : dict of (M,) Warp arrays
        The reference and gradient images' dots of the ``M = B N`` rows (``"x"``, ``"y"``,
        ``"eta"``, ``"i0"``, ``"flags"``; NaN where not found): the fit's position, width and peak replace
        theirs in place, and the flags gain FIT_FALLBACK and DISTORTED.
    eta0 : (B,) float64 array
        Each pair's nominal dot width (px).
    sat_frames, noise_frames : (2 B,) float64 Warp arrays
        Saturation level and noise of frame ``2 b`` (pair b's reference image) and ``2 b + 1`` (its
        gradient image).
    fit_half, render_half : int, keyword-only
        Half-sizes of the fit's and the model's windows (:func:`fit_window_half`, shared by the stack).
    settings : TrackingSettings, keyword-only
        ``fit_iterations``, ``distortion``, ``distortion_chi2``.
    device : warp.context.Device or str, keyword-only
    take : bool, keyword-only
        Whether the fit's parameters replace the dots' (``centroid="model"``); otherwise only the model
        correction is asked for and ``r`` and ``g`` stay as they are.

    Returns
    -------
    (2 M, 2) float64 Warp array
        Each row's position refitted with its pair's common peak and width (the model correction),
        reference rows first; NaN where it has none.
    """
    params, ok, shared, live, moved = _fit_rows(refs, grads, r, g, eta0, sat_frames, noise_frames, fit_half,
                                                render_half, settings, device)  # fmt: skip
    m = r["x"].shape[0]
    for row0, found in ((0, r), (m, g)) if take else ():
        _launch(
            fk.take_model,
            m,
            [params, ok, moved, live, row0, found["x"], found["y"], found["eta"], found["i0"], found["flags"]],
            device,
        )
    return shared


def _fit_rows(refs, grads, r, g, eta0_host, sat, noise_frames, half, render_half, s, device):
    """The joint fit of the 2 M rows (reference dots, then gradient dots) and the first-moment step:
    params, ok, shared_xy, live and moved of every row."""
    B, H, W = refs.shape
    M = r["x"].shape[0]
    N = M // B
    values = wp.empty(2 * M, dtype=wp.float64, device=device)
    valid = wp.empty(2 * M, dtype=wp.int32, device=device)
    _launch(fk.interleave_pairs, M, [r["eta"], g["eta"], r["x"], g["x"], N, values, valid], device)
    med = segment_medians(values, valid, length=2 * N, segments=B, device=device).numpy()
    sigma0_host = np.ascontiguousarray(start_width(med, eta0_host), dtype=np.float64)
    sigma0 = wp.array(sigma0_host, dtype=wp.float64, device=device)
    # the three-point peak is that of the pixel-broadened dot (variance sigma0^2 + 1/12, the same flux)
    factor = wp.array(1.0 + 1.0 / (12.0 * sigma0_host**2), dtype=wp.float64, device=device)
    eta0_host = np.asarray(eta0_host, dtype=np.float64)
    width = np.stack([MODEL_WIDTH_RANGE[0] * eta0_host, MODEL_WIDTH_RANGE[1] * eta0_host], axis=1)
    width = wp.array(np.ascontiguousarray(width), dtype=wp.vec2d, device=device)
    rows = 2 * M
    start = wp.empty((rows, 5), dtype=wp.float64, device=device)
    live = wp.empty(rows, dtype=wp.int32, device=device)
    frame = wp.empty(rows, dtype=wp.int32, device=device)
    partner = wp.empty(rows, dtype=wp.int32, device=device)
    for row0, found, fb in ((0, r, 0), (M, g, 1)):
        inputs = [found["x"], found["y"], found["i0"], N, sigma0, factor, fb, 2, row0, start, live, frame]
        _launch(fk.model_starts, M, inputs, device)
    _launch(fk.pair_partners, M, [live, M, partner], device)
    order, sorted_rows = _raster_rows(_Rows(start, frame, partner, live), H, W, device)
    bufs = _FitBuffers(
        _large("fit_models", (2 * 2 * B * H * W,), wp.int64, device),
        wp.empty_like(start),
        wp.empty_like(start),
        wp.zeros(rows, dtype=wp.int32, device=device),
        wp.full((rows, 2), np.nan, dtype=wp.float64, device=device),
        _profiles("fit_profiles", rows, render_half, device, large=True),
    )
    cur = _fit_steps(refs, grads, sorted_rows, bufs, sat, width, half=half, render_half=render_half,
                     iterations=s.fit_iterations, max_move=FIT_MAX_MOVE_PX, device=device)  # fmt: skip
    moved = wp.zeros(rows, dtype=wp.int32, device=device)
    if s.distortion != "none":
        shift = _moment_codes(refs, grads, sorted_rows._replace(params=cur), bufs.models[: 2 * B * H * W], bufs.prof,
                              sat, noise_frames, half=render_half, chi2=s.distortion_chi2, max_shift=mk.MAX_SHIFT_PX,
                              **distortion_options(s.distortion), device=device)  # fmt: skip
        _launch(mk.apply_moment_shift, rows, [shift, sorted_rows.partner, cur, bufs.shared, moved], device)
    # back in the rows' order (the parameters into ``start``, which the sorted rows copied)
    out = (start, wp.empty_like(bufs.ok), wp.empty_like(bufs.shared), wp.empty_like(moved))
    _launch(fk.scatter_rows, rows, [order, cur, bufs.ok, bufs.shared, moved, *out], device)
    return out[0], out[1], out[2], live, out[3]


def _profiles(name, rows, half, device, *, large=False):
    """The (rows, 6, 2 half + 1) stamp profiles of ``fit_kernels.dot_profiles``, a row's its thread's
    (:func:`tracking.workspace.per_thread`: on a GPU a warp's rows side by side): the thread's workspace,
    or with ``large`` on a GPU a new array (its memory pool keeps them)."""
    on_gpu = not wp.get_device(device).is_cpu
    return per_thread((rows, 6, 2 * int(half) + 1), wp.float64, device, name=None if large and on_gpu else name)


def _large(name, shape, dtype, device):
    """A large working array of the stack's fit (the model images and profiles, some 50 MB for a 1024 x 1024
    pair): on the CPU the thread's workspace, whose pages stay mapped from one call to the next (fresh
    pages cost more than some of the kernels there); on a GPU a new array (its memory pool keeps them)."""
    if wp.get_device(device).is_cpu:
        return scratch(name, shape, dtype, device)
    return wp.empty(shape, dtype=dtype, device=device)


def _raster_rows(rows, h, w, device):
    """The rows of a stack's fit sorted into raster order (:func:`_raster_order`'s bands of 4 image rows,
    frame by frame; rows not live last), once, on the device: the model and step kernels then read
    neighbouring pixels in neighbouring threads (on the CPU, 84 ms for the fit's and first-moment step's
    kernels on the benchmark pair against 122 ms in the prior's order). Returns the order (sorted row j is
    row ``order[j]``) and the sorted :class:`_Rows`, partners renumbered. The results do not depend on the
    order (the model images are fixed-point sums)."""
    n = rows.params.shape[0]
    keys = wp.empty(2 * n, dtype=wp.int64, device=device)  # (the second half: the radix sort's scratch)
    order = wp.empty(2 * n, dtype=wp.int32, device=device)
    _launch(fk.raster_keys, n, [rows.params, rows.live, rows.frame, h, w, keys, order], device)
    if n:
        wp.utils.radix_sort_pairs(keys, order, n)
    order = order[:n]
    back = wp.empty(n, dtype=wp.int32, device=device)
    _launch(fk.inverse_order, n, [order, back], device)
    out = _Rows(wp.empty_like(rows.params), *(wp.empty(n, dtype=wp.int32, device=device) for _ in range(3)))
    _launch(fk.gather_rows, n, [order, rows.params, rows.live, rows.frame, rows.partner, back, out.params, out.live,
                                out.frame, out.partner], device)  # fmt: skip
    return order, _Rows(out.params, out.frame, out.partner, out.live)
