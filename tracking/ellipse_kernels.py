"""Warp kernels of the elliptical moment step: a distorted dot's share of the light drawn from its own shape.

The first-moment step (:mod:`tracking.moment_kernels`) splits each pixel's light among overlapping dots
by their symmetric models. A distorted dot is not symmetric: the flow spreads it along the density's
gradient, so the symmetric models hand part of its light to its neighbours and part of theirs to it, and
in a crowded pattern that mis-split light, 2-3 px from the centre, is most of the error left. This step
gives each distorted gradient-image dot an elliptical Gaussian model,

``m(x, y) = F r1 r3 / (2 pi) exp(-|R (x - x0, y - y0)|^2 / 2)``, ``R = [[r1, r2], [0, r3]]``

(flux ``F``, centre, and the upper Cholesky factor ``R`` of its inverse covariance), fitted by a few
block-Jacobi Gauss-Newton sweeps against the image less its neighbours' current models, and then takes the
first moment of the share of the light these models give it, re-centring the model at each moment.

Rows are dots in a stack of model frames: frame ``f`` is image ``f % 2`` (0 the reference, 1 the gradient
image) of pair ``f // 2``, the model images ``[frames, height, width]`` are fixed point (units of
``1 / scale``), as the model fit's. The state of a row is ``ell[i] = (F, x0, y0, r1, r2, r3)``. The host
code is :func:`tracking.ellipse.ellipse_step`; the NumPy reference,
``tracking.reference.moment_shifts_numpy(..., ellipse=True)``, defines the result.
"""

import warp as wp

from .fit_kernels import to_fixed
from .kernel_constants import ELL_DAMPING, ELL_MARQUARDT, ELL_MAX_STEP, ELL_WIDTH_HI, ELL_WIDTH_LO
from .moment_kernels import MAX_RESIDUAL_FLUX, SHARE_FLOOR, moves, reference_background

wp.set_module_options({"enable_backward": False})

vec6d = wp.types.vector(length=6, dtype=wp.float64)
mat66d = wp.types.matrix(shape=(6, 6), dtype=wp.float64)
INV_TWO_PI = wp.constant(wp.float64(0.15915494309189535))
TWO_PI = wp.constant(wp.float64(6.283185307179586))
TWELFTH = wp.constant(wp.float64(1.0 / 12.0))


@wp.func
def ellipse_model(ell: wp.array2d(dtype=wp.float64), i: int, dx: wp.float64, dy: wp.float64) -> wp.float64:
    """Row i's elliptical model at ``(dx, dy)`` from its centre."""
    e1 = ell[i, 3] * dx + ell[i, 4] * dy
    e2 = ell[i, 5] * dy
    return ell[i, 0] * ell[i, 3] * ell[i, 5] * INV_TWO_PI * wp.exp(wp.float64(-0.5) * (e1 * e1 + e2 * e2))


@wp.func
def cholesky_solve6(a: mat66d, g: vec6d) -> vec6d:
    """``a^-1 g`` for a symmetric positive definite ``a``; zeros where ``a`` is not."""
    low = mat66d()
    for j in range(6):
        s = a[j, j]
        for k in range(j):
            s -= low[j, k] * low[j, k]
        if not (s > wp.float64(0.0)):
            return vec6d()
        d = wp.sqrt(s)
        low[j, j] = d
        for r in range(j + 1, 6):
            t = a[r, j]
            for k in range(j):
                t -= low[r, k] * low[j, k]
            low[r, j] = t / d
    y = vec6d()
    for j in range(6):
        t = g[j]
        for k in range(j):
            t -= low[j, k] * y[k]
        y[j] = t / low[j, j]
    x = vec6d()
    for jj in range(6):
        j = 5 - jj
        t = y[j]
        for k in range(j + 1, 6):
            t -= low[k, j] * x[k]
        x[j] = t / low[j, j]
    return x


@wp.func
def start_width(params: wp.array2d(dtype=wp.float64), i: int) -> wp.float64:
    """The elliptical model's starting width: the symmetric fit's, broadened by the pixel, ``sqrt(sigma^2 + 1/12)``."""
    return wp.sqrt(params[i, 3] * params[i, 3] + TWELFTH)


@wp.func
def round_start(params: wp.array2d(dtype=wp.float64), i: int, ell: wp.array2d(dtype=wp.float64)):
    """Row i's elliptical model as its symmetric fit: flux ``2 pi I0 sigma^2``, its centre, round, of width
    ``start_width``."""
    r = wp.float64(1.0) / start_width(params, i)
    ell[i, 0] = TWO_PI * params[i, 2] * params[i, 3] * params[i, 3]
    ell[i, 1] = params[i, 0]
    ell[i, 2] = params[i, 1]
    ell[i, 3] = r
    ell[i, 4] = wp.float64(0.0)
    ell[i, 5] = r


@wp.kernel
def ellipse_start(
    params: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    shift: wp.array(dtype=wp.vec3d),
    active: wp.array(dtype=wp.int32),
    ell: wp.array2d(dtype=wp.float64),
):
    """Row i takes part where it lies in a gradient image and the first-moment step ``moves`` it (its
    shift usable, it or its partner distorted); its model starts as the symmetric fit's: the same flux
    ``2 pi I0 sigma^2`` and centre, round, of width ``start_width``."""
    i = wp.tid()
    active[i] = 0
    if frame[i] % 2 != 1 or not moves(shift, partner, i):
        return
    active[i] = 1
    round_start(params, i, ell)


@wp.kernel
def ellipse_render(
    params: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    ell: wp.array2d(dtype=wp.float64),
    prof: wp.array3d(dtype=wp.float64),
    symmetric: int,
    sign: int,
    half: int,
    scales: wp.array(dtype=wp.float64),
    height: int,
    width: int,
    models: wp.array(dtype=wp.int64),
):
    """Add ``sign`` times active row i's model on its ``2 half + 1`` stamp (centred on the pixel nearest
    its fitted centre) to its frame's model image: the elliptical model, or if ``symmetric`` the model
    fit's (``I0 p_x p_y`` from its profiles ``prof``, as ``render_dots_kernel`` drew it: -1 takes it
    out again to the bit)."""
    i = wp.tid()
    if active[i] == 0:
        return
    scale = scales[frame[i]]
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    for r in range(wp.max(-oy, 0), wp.min(n, height - oy)):
        at = (frame[i] * height + oy + r) * width + ox
        dy = wp.float64(oy + r) - ell[i, 2]
        for c in range(wp.max(-ox, 0), wp.min(n, width - ox)):
            if symmetric != 0:
                v = to_fixed(params[i, 2] * prof[i, 3, r] * prof[i, 0, c], scale)
            else:
                v = to_fixed(ellipse_model(ell, i, wp.float64(ox + c) - ell[i, 1], dy), scale)
            wp.atomic_add(models, at + c, wp.int64(sign) * v)


@wp.func
def ellipse_fit_step(
    image: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    f: int,
    params: wp.array2d(dtype=wp.float64),
    i: int,
    half: int,
    background: wp.float64,
    ell: wp.array2d(dtype=wp.float64),
):
    """One damped Gauss-Newton step of row i's elliptical model against the image less the background
    and every other dot's current model, over the pixels of its stamp inside the image. The unknowns are
    ``(F, x0, y0, log r1, r2, log r3)``; the step is limited to ``ELL_MAX_STEP`` per unknown but the flux
    and scaled by ``ELL_DAMPING``, and the widths ``1 / r1``, ``1 / r3`` kept within ``ELL_WIDTH_LO``
    and ``ELL_WIDTH_HI`` times ``start_width``."""
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    height = image.shape[0]
    width = image.shape[1]
    flux = ell[i, 0]
    r1 = ell[i, 3]
    r2 = ell[i, 4]
    r3 = ell[i, 5]
    one = wp.float64(1.0)
    a = mat66d()
    g = vec6d()
    for r in range(wp.max(-oy, 0), wp.min(n, height - oy)):
        at = (f * height + oy + r) * width + ox
        dy = wp.float64(oy + r) - ell[i, 2]
        for c in range(wp.max(-ox, 0), wp.min(n, width - ox)):
            dx = wp.float64(ox + c) - ell[i, 1]
            m = ellipse_model(ell, i, dx, dy)
            e1 = r1 * dx + r2 * dy
            e2 = r3 * dy
            jac = vec6d(m / flux, m * r1 * e1, m * (r2 * e1 + r3 * e2), m * (one - r1 * e1 * dx), -m * e1 * dy,
                        m * (one - r3 * e2 * dy))  # fmt: skip
            res = image[oy + r, ox + c] - background - wp.float64(models[at + c]) * inv_scale
            a += wp.outer(jac, jac)
            g += jac * res
    for k in range(6):
        a[k, k] = a[k, k] + ELL_MARQUARDT * wp.max(a[k, k], wp.float64(1.0e-12))
    step = cholesky_solve6(a, g)
    for k in range(1, 6):
        step[k] = wp.clamp(step[k], -ELL_MAX_STEP, ELL_MAX_STEP)
    step = ELL_DAMPING * step
    w0 = start_width(params, i)
    lo = one / (ELL_WIDTH_HI * w0)
    hi = one / (ELL_WIDTH_LO * w0)
    ell[i, 0] = wp.max(flux + step[0], wp.float64(0.1) * flux)
    ell[i, 1] = ell[i, 1] + step[1]
    ell[i, 2] = ell[i, 2] + step[2]
    ell[i, 3] = wp.clamp(r1 * wp.exp(step[3]), lo, hi)
    ell[i, 4] = r2 + step[4]
    ell[i, 5] = wp.clamp(r3 * wp.exp(step[5]), lo, hi)


@wp.func
def ellipse_moment(
    image: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    f: int,
    params: wp.array2d(dtype=wp.float64),
    i: int,
    half: int,
    background: wp.float64,
    ell: wp.array2d(dtype=wp.float64),
) -> bool:
    """Row i's model moved to the first moment of its share of the light and given that share's flux:
    ``L = w (I - b)`` with ``w = m_i / M`` (``M`` the model image of every dot, at least ``SHARE_FLOOR``
    of the dot's fitted peak, and ``w`` within [0, 1]) on the stamp's pixels inside the image, and
    ``L = m_i`` (the dot's own model) on those outside it. False (the model left as it was) where the
    share holds no light."""
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    height = image.shape[0]
    width = image.shape[1]
    x0 = params[i, 0]
    y0 = params[i, 1]
    zero = wp.float64(0.0)
    floor = SHARE_FLOOR * wp.abs(params[i, 2])
    flux = zero
    sx = zero
    sy = zero
    for r in range(n):
        row_inside = oy + r >= 0 and oy + r < height
        at = (f * height + oy + r) * width + ox
        dy = wp.float64(oy + r) - y0
        for c in range(n):
            dx = wp.float64(ox + c) - x0
            m = ellipse_model(ell, i, wp.float64(ox + c) - ell[i, 1], wp.float64(oy + r) - ell[i, 2])
            light = m
            if row_inside and ox + c >= 0 and ox + c < width:
                share = wp.clamp(m / wp.max(wp.float64(models[at + c]) * inv_scale, floor), zero, wp.float64(1.0))
                light = share * (image[oy + r, ox + c] - background)
            flux += light
            sx += dx * light
            sy += dy * light
    if flux > zero:
        ell[i, 0] = flux
        ell[i, 1] = x0 + sx / flux
        ell[i, 2] = y0 + sy / flux
        return True
    return False


@wp.kernel
def ellipse_finish(
    params: wp.array2d(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
    ell: wp.array2d(dtype=wp.float64),
    max_shift: wp.float64,
    shift: wp.array(dtype=wp.vec3d),
):
    """Active row i's shift becomes the one from its fitted centre to its model's last centre, its code
    kept, where that is finite, at most ``max_shift`` and the last share's flux within
    ``MAX_RESIDUAL_FLUX`` of the symmetric model's ``2 pi I0 sigma^2``; elsewhere the first-moment
    step's shift stays."""
    i = wp.tid()
    if active[i] != 1:
        return
    dx = ell[i, 1] - params[i, 0]
    dy = ell[i, 2] - params[i, 1]
    own = TWO_PI * params[i, 2] * params[i, 3] * params[i, 3]
    if not (dx * dx + dy * dy <= max_shift * max_shift):  # also false for NaN
        return
    if not (wp.abs(ell[i, 0] - own) <= MAX_RESIDUAL_FLUX * wp.abs(own)):
        return
    shift[i] = wp.vec3d(dx, dy, shift[i][2])


@wp.kernel
def ellipse_fit_kernel(
    gradients: wp.array3d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    scales: wp.array(dtype=wp.float64),
    params: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    half: int,
    ell: wp.array2d(dtype=wp.float64),
):
    """``ellipse_fit_step`` of active row i (a gradient-image dot, on its partner's background)."""
    i = wp.tid()
    if active[i] == 0:
        return
    f = frame[i]
    b = reference_background(params, partner, i, True)
    ellipse_fit_step(gradients[f // 2], models, wp.float64(1.0) / scales[f], f, params, i, half, b, ell)


@wp.kernel
def ellipse_moment_kernel(
    gradients: wp.array3d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    scales: wp.array(dtype=wp.float64),
    params: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    half: int,
    ell: wp.array2d(dtype=wp.float64),
):
    """``ellipse_moment`` of active row i (a gradient-image dot, on its partner's background); a row whose
    share holds no light keeps its model (still drawn for its neighbours) and is marked 2: no result."""
    i = wp.tid()
    if active[i] != 1:
        return
    f = frame[i]
    b = reference_background(params, partner, i, True)
    if not ellipse_moment(gradients[f // 2], models, wp.float64(1.0) / scales[f], f, params, i, half, b, ell):
        active[i] = 2


@wp.kernel
def list_flagged(
    flags: wp.array(dtype=wp.int32),
    start: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32),
    rows: wp.array(dtype=wp.int32),
    frames_of_rows: wp.array(dtype=wp.int32),
):
    """Row i, where flagged, at its place ``start[i]`` (the exclusive prefix sum of the flags) of the list of
    flagged rows, in the rows' order, with its frame."""
    i = wp.tid()
    if flags[i] != 0:
        rows[start[i]] = i
        frames_of_rows[start[i]] = frame[i]


@wp.kernel
def flag_set(flags: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    """1 where the flag is set (any value but 0), else 0: what the prefix sum of :func:`list_flagged` counts."""
    i = wp.tid()
    out[i] = int(flags[i] != 0)
