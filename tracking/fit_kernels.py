# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of the model fit: the pixel-integrated dot model, its rendering and its joint fit.

Kernels and ``@wp.func`` steps only; the host code lives in :mod:`tracking.dotfit` (one thread per dot;
``tracking.reference.fit_dots_numpy`` is the NumPy reference) and :mod:`tracking.stack`.
Windows are held flat, pixel ``p`` of a ``w x w`` window at row ``p // w``, column ``p % w``.

The last section holds the model fit of a stack of pairs (:func:`model_starts` ... :func:`take_model`), whose
step kernel also serves one pair or one image (a stack of one):
rows ``0 ... M - 1`` are the reference-image dots of every pair, ``M ... 2 M - 1`` their gradient-image
dots, and row ``i``'s model frame ``2 b`` (``2 b + 1``) is pair ``b``'s reference (gradient) image; the
step is :func:`fit_dot_step`. The first-moment step's kernels on the same rows are
:mod:`tracking.moment_kernels`' ``moment_shift_stack`` and ``apply_moment_shift``.
"""

import warp as wp

from synthbos.device import quiet_warp

from .kernel_constants import DISTORTED, FIT_FALLBACK

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile


vec5d = wp.types.vector(length=5, dtype=wp.float64)
mat32d = wp.types.matrix(shape=(3, 2), dtype=wp.float64)


@wp.struct
class NormalEquations:
    """Normal equations of one dot, parameters split into position and background ``(x, y, b)`` and shape
    ``(I0, sigma)``: ``J^T J = [[p, q], [q^T, r]]``, ``J^T res = (g1, g2)``; ``h1`` is the position part
    of ``J^T res'`` against the common-shape model image."""

    p: wp.mat33d
    q: mat32d
    r: wp.mat22d
    g1: wp.vec3d
    g2: wp.vec2d
    h1: wp.vec3d



# --- the pixel-integrated dot model and its joint fit ---------------------------------------------


@wp.func
def erf_from_gauss(x: wp.float64, g: wp.float64) -> wp.float64:
    """``erf(x)`` given ``g = exp(-x^2)``: Abramowitz and Stegun 7.1.26 (absolute error below 1.5e-7)."""
    t = wp.float64(1.0) / (wp.float64(1.0) + wp.float64(0.3275911) * wp.abs(x))
    poly = wp.float64(1.061405429) * t - wp.float64(1.453152027)
    poly = poly * t + wp.float64(1.421413741)
    poly = poly * t - wp.float64(0.284496736)
    poly = poly * t + wp.float64(0.254829592)
    e = wp.float64(1.0) - poly * t * g
    if x < wp.float64(0.0):
        return -e
    return e


@wp.func
def profile_start(first: int, c: wp.float64, inv: wp.float64):
    """Standardised first edge ``z0 = (first - 1/2 - c) / s`` of a 1-D pixel profile (``inv = 1 / s``),
    ``g0 = exp(-z0^2 / 2)``, ``erf(z0 / sqrt 2)``, the ratio ``exp(-z0 h - h^2 / 2)`` of ``g`` at the
    next edge to ``g0`` (``h = 1 / s``) and whether every edge takes its own exponential instead."""
    z0 = (wp.float64(first) - wp.float64(0.5) - c) * inv
    g0 = wp.exp(wp.float64(-0.5) * z0 * z0)
    e0 = erf_from_gauss(z0 * wp.float64(0.7071067811865476), g0)
    # exp(-z^2 / 2) at the next edge is g times exp(-z h - h^2 / 2), a ratio that itself changes by
    # exp(-h^2) per edge: two exponentials per axis and one per dot, unless the first ratio would
    # overflow or g underflow (very narrow dots on a wide stamp), where every edge takes its own.
    direct = z0 < wp.float64(-20.0) or z0 * inv < wp.float64(-200.0)
    ratio = wp.exp(-z0 * inv - wp.float64(0.5) * inv * inv)
    return z0, g0, e0, ratio, direct


@wp.func
def profile_pixel(
    z0: wp.float64,
    g0: wp.float64,
    e0: wp.float64,
    ratio: wp.float64,
    direct: bool,
    inv: wp.float64,
    step: wp.float64,
    scale: wp.float64,
):
    """One pixel of a 1-D profile (``profile_start``'s recurrence): from the pixel's first edge (``z0``,
    ``g0``, ``erf``, the ratio of ``g`` to the next edge) its next edge's four values, then its
    ``p``, ``dp/dc`` and ``dp/ds`` (``inv = 1 / s``, ``step = exp(-inv^2)``, ``scale = sqrt(pi / 2) s``)."""
    z1 = z0 + inv
    g1 = g0 * ratio
    if direct:
        g1 = wp.exp(wp.float64(-0.5) * z1 * z1)
    e1 = erf_from_gauss(z1 * wp.float64(0.7071067811865476), g1)
    p = scale * (e1 - e0)
    return z1, g1, e1, ratio * step, p, g0 - g1, z0 * g0 - z1 * g1 + p * inv


@wp.func
def dot_profiles(params: wp.array2d(dtype=wp.float64), i: int, half: int, prof: wp.array3d(dtype=wp.float64)):
    """Both axes' pixel profiles of dot i on its ``2 half + 1`` stamp centred on the nearest pixel.

    Rows 0-2 of ``prof[i]``: the x profile of a unit-peak Gaussian and its c- and s-derivatives,
    ``p_k = sqrt(pi / 2) s [erf(z / sqrt 2)]``, ``dp/dc = [-exp(-z^2 / 2)]``,
    ``dp/ds = [-z exp(-z^2 / 2)] + p / s`` over the pixel's standardised edges ``z = (k -+ 1/2 - c) / s``;
    rows 3-5: the same along y. Both axes in one loop (they share ``s``).
    """
    n = 2 * half + 1
    s = params[i, 3]
    inv = wp.float64(1.0) / s
    scale = wp.float64(1.2533141373155003) * s  # sqrt(pi / 2) s
    step = wp.exp(-inv * inv)
    zx, gx, ex, rx, dx = profile_start(int(wp.rint(params[i, 0])) - half, params[i, 0], inv)
    zy, gy, ey, ry, dy = profile_start(int(wp.rint(params[i, 1])) - half, params[i, 1], inv)
    k = int(0)
    while k < n:
        zx, gx, ex, rx, p, dpdc, dpds = profile_pixel(zx, gx, ex, rx, dx, inv, step, scale)
        prof[i, 0, k] = p
        prof[i, 1, k] = dpdc
        prof[i, 2, k] = dpds
        zy, gy, ey, ry, p, dpdc, dpds = profile_pixel(zy, gy, ey, ry, dy, inv, step, scale)
        prof[i, 3, k] = p
        prof[i, 4, k] = dpdc
        prof[i, 5, k] = dpds
        k += 1


@wp.func
def common_shape(params: wp.array2d(dtype=wp.float64), partner: wp.array(dtype=wp.int32), i: int) -> wp.vec2d:
    """(I0, sigma) of dot i shared with its partner in the other image: the mean of both (own if none)."""
    j = partner[i]
    if j < 0:
        return wp.vec2d(params[i, 2], params[i, 3])
    half = wp.float64(0.5)
    return wp.vec2d(half * (params[i, 2] + params[j, 2]), half * (params[i, 3] + params[j, 3]))


@wp.func
def to_fixed(value: wp.float64, scale: wp.float64) -> wp.int64:
    """``value`` in fixed point: the nearest integer to ``value * scale``."""
    return wp.int64(wp.floor(value * scale + wp.float64(0.5)))


@wp.func
def draw_stamp(
    params: wp.array2d(dtype=wp.float64),
    partner: wp.array(dtype=wp.int32),
    prof: wp.array3d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    i: int,
    common: int,
    first: int,
    step: int,
    c1: int,
    r0: int,
    r1: int,
    base: int,
    width: int,
    scale: wp.float64,
):
    """Dot i's stamp columns ``first, first + step, ... < c1`` of its rows ``r0 ... r1 - 1`` into the model
    images (:func:`render_dots_kernel`; ``base``: the flat index of the stamp's pixel (0, 0))."""
    a = params[i, 2]
    if common == 0:
        r = int(r0)
        while r < r1:
            apy = a * prof[i, 3, r]
            at = base + r * width
            c = int(first)
            while c < c1:
                wp.atomic_add(models, at + c, to_fixed(apy * prof[i, 0, c], scale))
                c += step
            r += 1
    else:  # both images in one pass over the stamp; the partner's shape is a scattered read
        cs = common_shape(params, partner, i)
        ds = cs[1] - params[i, 3]
        layer = models.shape[0] // 2
        r = int(r0)
        while r < r1:
            py = prof[i, 3, r]
            spy = prof[i, 5, r]
            apy = a * py
            at = base + r * width
            c = int(first)
            while c < c1:
                px = prof[i, 0, c]
                wp.atomic_add(models, at + c, to_fixed(apy * px, scale))
                shared = cs[0] * (py * px + ds * (spy * px + py * prof[i, 2, c]))
                wp.atomic_add(models, at + layer + c, to_fixed(shared, scale))
                c += step
            r += 1


@wp.kernel
def dot_profiles_kernel(params: wp.array2d(dtype=wp.float64), half: int, prof: wp.array3d(dtype=wp.float64)):
    """Dot i's profiles on its ``2 half + 1`` stamp into ``prof[i]`` (``dot_profiles``), ahead of a
    :func:`render_dots_kernel` split over the stamps' columns."""
    i = wp.tid()
    dot_profiles(params, i, half, prof)


@wp.kernel
def render_dots_kernel(
    params: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    half: int,
    common: int,
    profiles: int,
    parts: int,
    prof: wp.array3d(dtype=wp.float64),
    scales: wp.array(dtype=wp.float64),
    height: int,
    width: int,
    models: wp.array(dtype=wp.int64),
):
    """Add each dot's model (no background) on its ``2 half + 1`` stamp into its image's model images.

    Thread t draws the stamp columns ``c0 + t % parts, c0 + t % parts + parts, ...`` (``c0``: the first
    inside the image) of dot ``i = t // parts``:
    ``parts = 1``, the whole stamp (one thread per dot, the CPU's engine); ``parts = 2 half + 1``, one
    column (a GPU's: a warp's neighbouring threads add to neighbouring pixels).
    ``models``: the model images ``[2, frames, height, width]`` flat. ``models[0, f]``: ``I0 p_x p_y``;
    if ``common``, ``models[1, f]``: the same at the pair's common shape, linearised in sigma. ``prof``
    holds the dot's profiles on its stamp (``dot_profiles``); if ``profiles`` (the first render of a fit,
    ``parts = 1`` only: else :func:`dot_profiles_kernel` first), they are computed here first, from ``params``.
    The images are fixed point (units of ``1 / scales[f]`` for frame f: one scale per pair, so a pair's
    bits do not depend on the other pairs of a stack) added with integer atomics, so overlapping
    dots sum to the same bits in any thread order and any split: CUDA fits are reproducible run to run.
    """
    t = wp.tid()
    i = t // parts
    scale = scales[frame[i]]
    if profiles != 0:
        dot_profiles(params, i, half, prof)
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    # the part of the stamp inside the image, rows r0 <= r < r1 and columns c0 <= c < c1
    c0 = wp.max(-ox, 0)
    c1 = wp.min(n, width - ox)
    r0 = wp.max(-oy, 0)
    r1 = wp.min(n, height - oy)
    base = (frame[i] * height + oy) * width + ox  # flat index of the stamp's pixel (0, 0)
    if parts == 1:  # a literal step: the CPU's compiler unrolls the whole stamp's loop
        draw_stamp(params, partner, prof, models, i, common, int(c0), 1, int(c1), int(r0), int(r1), base, width, scale)
    else:
        draw_stamp(params, partner, prof, models, i, common, int(c0) + t - i * parts, parts, int(c1), int(r0), int(r1),
                   base, width, scale)  # fmt: skip


@wp.func
def normal_matrix(
    image: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    f: int,
    params: wp.array2d(dtype=wp.float64),
    i: int,
    half: int,
    skip: int,
    sat: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
) -> NormalEquations:
    """Dot i's normal equations: ``J^T J`` in blocks, ``J^T r`` and ``J^T r'`` (see ``NormalEquations``).

    The window is the central ``2 half + 1`` part of the stamp whose profiles ``prof`` holds (``skip``
    pixels in from its edge). ``r = image - models[0] - b``: the model image holds dot i itself, so
    this is the image less the other dots, minus dot i's model and background; ``r'`` is the same
    against the common-shape model image ``models[1]`` (both fixed point: ``inv_scale`` per unit).
    ``models`` holds the model images ``[2, frames, height, width]`` flat (``image`` is ``height x width``).
    ``J`` is the derivative of the model with
    respect to x, y, I0, sigma and the background. Pixels at or above ``sat`` (saturated: they only
    bound the intensity) take no part.
    """
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    a = params[i, 2]
    b = params[i, 4]
    zero = wp.float64(0.0)
    s00 = zero
    s01 = zero
    s02 = zero
    s03 = zero
    s04 = zero
    s11 = zero
    s12 = zero
    s13 = zero
    s14 = zero
    s22 = zero
    s23 = zero
    s24 = zero
    s33 = zero
    s34 = zero
    s44 = zero
    g0 = zero
    g1 = zero
    g2 = zero
    g3 = zero
    g4 = zero
    h0 = zero
    h1 = zero
    h4 = zero
    for rr in range(n):
        row = oy + rr
        if row >= 0 and row < image.shape[0]:
            py = prof[i, 3, rr + skip]
            dpy = a * prof[i, 4, rr + skip]
            spy = a * prof[i, 5, rr + skip]
            apy = a * py
            for cc in range(n):
                col = ox + cc
                if col >= 0 and col < image.shape[1] and image[row, col] < sat:
                    px = prof[i, 0, cc + skip]
                    v = image[row, col] - b
                    at = (f * image.shape[0] + row) * image.shape[1] + col
                    res = v - wp.float64(models[at]) * inv_scale
                    res2 = v - wp.float64(models[at + models.shape[0] // 2]) * inv_scale
                    j0 = apy * prof[i, 1, cc + skip]
                    j1 = dpy * px
                    j2 = py * px
                    j3 = spy * px + apy * prof[i, 2, cc + skip]
                    s00 += j0 * j0
                    s01 += j0 * j1
                    s02 += j0 * j2
                    s03 += j0 * j3
                    s04 += j0
                    s11 += j1 * j1
                    s12 += j1 * j2
                    s13 += j1 * j3
                    s14 += j1
                    s22 += j2 * j2
                    s23 += j2 * j3
                    s24 += j2
                    s33 += j3 * j3
                    s34 += j3
                    s44 += wp.float64(1.0)
                    g0 += j0 * res
                    g1 += j1 * res
                    g2 += j2 * res
                    g3 += j3 * res
                    g4 += res
                    h0 += j0 * res2
                    h1 += j1 * res2
                    h4 += res2
    eps = wp.float64(1.0e-12)
    ne = NormalEquations()
    ne.p = wp.mat33d(s00 + eps, s01, s04, s01, s11 + eps, s14, s04, s14, s44 + eps)
    ne.q = mat32d(s02, s03, s12, s13, s24, s34)
    ne.r = wp.mat22d(s22 + eps, s23, s23, s33 + eps)
    ne.g1 = wp.vec3d(g0, g1, g4)
    ne.g2 = wp.vec2d(g2, g3)
    ne.h1 = wp.vec3d(h0, h1, h4)
    return ne


@wp.func
def window_is_whole(
    image: wp.array2d(dtype=wp.float64), params: wp.array2d(dtype=wp.float64), i: int, half: int, sat: wp.float64
) -> bool:
    """True where dot i's ``2 half + 1`` window lies inside the image and holds no pixel at or above ``sat``."""
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    if ox < 0 or oy < 0 or ox + n > image.shape[1] or oy + n > image.shape[0]:
        return False
    if sat < wp.float64(1.0e300):
        for rr in range(n):
            for cc in range(n):
                if image[oy + rr, ox + cc] >= sat:
                    return False
    return True


@wp.func
def profile_moments(prof: wp.array3d(dtype=wp.float64), i: int, axis0: int, n: int, skip: int):
    """Sums over one axis of dot ``i``'s profile terms ``p = prof[i, axis0]``, ``d = prof[i, axis0 + 1]``,
    ``s = prof[i, axis0 + 2]`` (entries ``skip ... skip + n - 1``): pp, dd, ss, pd, ps, ds, p, d, s."""
    zero = wp.float64(0.0)
    pp = zero
    dd = zero
    ss = zero
    pd = zero
    ps = zero
    ds = zero
    sp = zero
    sd = zero
    s_ = zero
    k = int(skip)
    while k < skip + n:
        p = prof[i, axis0, k]
        d = prof[i, axis0 + 1, k]
        sg = prof[i, axis0 + 2, k]
        pp += p * p
        dd += d * d
        ss += sg * sg
        pd += p * d
        ps += p * sg
        ds += d * sg
        sp += p
        sd += d
        s_ += sg
        k += 1
    return pp, dd, ss, pd, ps, ds, sp, sd, s_


@wp.func
def normal_matrix_separable(
    image: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    f: int,
    params: wp.array2d(dtype=wp.float64),
    i: int,
    half: int,
    skip: int,
    common: int,
    prof: wp.array3d(dtype=wp.float64),
) -> NormalEquations:
    """``normal_matrix`` for a whole window (``window_is_whole``): every Jacobian column is a product of
    an x and a y profile term, so ``J^T J`` comes from 1-D sums over the rows and columns, and ``J^T r``
    from one pass that sums each row against the x terms first. ``J^T r'`` only if ``common``."""
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    a = params[i, 2]
    b = params[i, 4]
    zero = wp.float64(0.0)
    g0 = zero
    g1 = zero
    g2 = zero
    g3 = zero
    g4 = zero
    h0 = zero
    h1 = zero
    h4 = zero
    width = image.shape[1]
    layer = models.shape[0] // 2
    at = (f * image.shape[0] + oy) * width + ox  # flat index of the window's first pixel in models
    rr = int(0)
    while rr < n:
        row = oy + rr
        r0 = zero
        r1 = zero
        r2 = zero
        r3 = zero
        t0 = zero
        t1 = zero
        t3 = zero
        cc = int(0)
        while cc < n:
            col = ox + cc
            k = cc + skip
            res = image[row, col] - b - wp.float64(models[at + cc]) * inv_scale
            r0 += prof[i, 1, k] * res
            r1 += prof[i, 0, k] * res
            r2 += prof[i, 2, k] * res
            r3 += res
            cc += 1
        if common != 0:
            cc = int(0)
            while cc < n:
                col = ox + cc
                k = cc + skip
                res2 = image[row, col] - b - wp.float64(models[at + layer + cc]) * inv_scale
                t0 += prof[i, 1, k] * res2
                t1 += prof[i, 0, k] * res2
                t3 += res2
                cc += 1
        k = rr + skip
        py = prof[i, 3, k]
        dy = prof[i, 4, k]
        sy = prof[i, 5, k]
        g0 += py * r0
        g1 += dy * r1
        g2 += py * r1
        g3 += sy * r1 + py * r2
        g4 += r3
        h0 += py * t0
        h1 += dy * t1
        h4 += t3
        at += width
        rr += 1
    # 1-D sums of the x terms (p: profile, d: its c-derivative, s: its sigma-derivative) and of the y terms
    # (after the pixel loop: fewer values live across it)
    xpp, xdd, xss, xpd, xps, xds, xp, xd, xs = profile_moments(prof, i, 0, n, skip)
    ypp, ydd, yss, ypd, yps, yds, yp, yd, ys = profile_moments(prof, i, 3, n, skip)
    a2 = a * a
    eps = wp.float64(1.0e-12)
    s00 = a2 * ypp * xdd
    s01 = a2 * ypd * xpd
    s02 = a * ypp * xpd
    s03 = a2 * (yps * xpd + ypp * xds)
    s04 = a * yp * xd
    s11 = a2 * ydd * xpp
    s12 = a * ypd * xpp
    s13 = a2 * (yds * xpp + ypd * xps)
    s14 = a * yd * xp
    s22 = ypp * xpp
    s23 = a * (yps * xpp + ypp * xps)
    s24 = yp * xp
    s33 = a2 * (yss * xpp + wp.float64(2.0) * yps * xps + ypp * xss)
    s34 = a * (ys * xp + yp * xs)
    s44 = wp.float64(n * n)
    ne = NormalEquations()
    ne.p = wp.mat33d(s00 + eps, s01, s04, s01, s11 + eps, s14, s04, s14, s44 + eps)
    ne.q = mat32d(s02, s03, s12, s13, s24, s34)
    ne.r = wp.mat22d(s22 + eps, s23, s23, s33 + eps)
    ne.g1 = wp.vec3d(a * g0, a * g1, g4)
    ne.g2 = wp.vec2d(g2, a * g3)
    ne.h1 = wp.vec3d(a * h0, a * h1, h4)
    return ne


@wp.func
def limited(step: vec5d) -> vec5d:
    """The step scaled so that the position moves at most half a pixel per axis."""
    big = wp.max(wp.abs(step[0]), wp.abs(step[1]))
    if big > wp.float64(0.5):
        return step * (wp.float64(0.5) / big)
    return step


@wp.func
def all_finite(q: vec5d) -> bool:
    """Whether every entry is finite: ``|x| <= DBL_MAX`` fails for NaN and infinity alike (compares inline,
    where ``wp.isfinite`` on the CPU is a call per entry)."""
    big = wp.float64(1.7976931348623157e308)
    xy = wp.abs(q[0]) <= big and wp.abs(q[1]) <= big
    return xy and wp.abs(q[2]) <= big and wp.abs(q[3]) <= big and wp.abs(q[4]) <= big


@wp.func
def fit_dot_step(
    image: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    params: wp.array2d(dtype=wp.float64),
    start: wp.array2d(dtype=wp.float64),
    f: int,
    i: int,
    has_partner: int,
    sat: wp.float64,
    half: int,
    render_half: int,
    common: int,
    max_move: wp.float64,
    smin: wp.float64,
    smax: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
    out: wp.array2d(dtype=wp.float64),
    ok: wp.array(dtype=wp.int32),
    shared_xy: wp.array2d(dtype=wp.float64),
):
    """One Gauss-Newton step of dot i (in model frame ``f``) against its image less the other dots (see
    ``tracking.reference.fit_dots_numpy``).

    ``models``: the fixed-point model images ``[2, frames, height, width]``, flat.

    ``prof`` holds the dot's profiles at ``params`` on its rendering stamp; they are replaced by those
    at the new parameters ``out``, except in the last step (``common``), after which none are needed.
    If ``common``, ``shared_xy`` gets the position of the step for position and background against
    the common-shape model image (NaN without a partner; all NaN without ``common``, when that image
    is not drawn).
    """
    p = vec5d(params[i, 0], params[i, 1], params[i, 2], params[i, 3], params[i, 4])
    skip = render_half - half
    ne = NormalEquations()
    if window_is_whole(image, params, i, half, sat):
        ne = normal_matrix_separable(image, models, inv_scale, f, params, i, half, skip, common, prof)
    else:
        ne = normal_matrix(image, models, inv_scale, f, params, i, half, skip, sat, prof)
    # Block elimination: the shape step from the Schur complement, then position and background.
    pinv = wp.inverse(ne.p)
    pq = pinv * ne.q
    schur = ne.r - wp.transpose(ne.q) * pq
    d2 = wp.inverse(schur) * (ne.g2 - wp.transpose(pq) * ne.g1)
    d1 = pinv * (ne.g1 - ne.q * d2)
    step = vec5d(d1[0], d1[1], d2[0], d2[1], d1[2])
    q = p + limited(step)
    good = all_finite(q)
    good = good and wp.abs(q[0] - start[i, 0]) <= max_move and wp.abs(q[1] - start[i, 1]) <= max_move
    good = good and q[2] > wp.float64(0.0) and q[3] >= smin and q[3] <= smax
    if not good:
        q = p
    hs = pinv * ne.h1
    qs = limited(vec5d(hs[0], hs[1], wp.float64(0.0), wp.float64(0.0), hs[2]))
    nan = wp.float64(wp.nan)
    shared_xy[i, 0] = nan
    shared_xy[i, 1] = nan
    if common != 0 and has_partner != 0:
        shared_xy[i, 0] = p[0] + qs[0]
        shared_xy[i, 1] = p[1] + qs[1]
    for k in range(5):
        out[i, k] = q[k]
    ok[i] = int(good)
    if common == 0:  # not the last step: the next one needs the profiles at the new parameters
        dot_profiles(out, i, render_half, prof)


# --- the model fit of a stack of pairs: starts, partners, steps, first moments and the results -------


@wp.kernel
def interleave_pairs(
    first: wp.array(dtype=wp.float64),
    second: wp.array(dtype=wp.float64),
    x_first: wp.array(dtype=wp.float64),
    x_second: wp.array(dtype=wp.float64),
    per_frame: int,
    values: wp.array(dtype=wp.float64),
    valid: wp.array(dtype=wp.int32),
):
    """Pair b's segment of ``2 per_frame`` values: its dots' ``first`` then ``second`` (taking part where
    the matching ``x`` is finite)."""
    i = wp.tid()
    b = i // per_frame
    j = i % per_frame
    at = b * 2 * per_frame + j
    values[at] = first[i]
    valid[at] = int(wp.isfinite(x_first[i]))
    values[at + per_frame] = second[i]
    valid[at + per_frame] = int(wp.isfinite(x_second[i]))


@wp.kernel
def model_starts(
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    i0: wp.array(dtype=wp.float64),
    per_frame: int,
    sigma0: wp.array(dtype=wp.float64),
    peak_factor: wp.array(dtype=wp.float64),
    frame_base: int,
    frame_step: int,
    row0: int,
    params: wp.array2d(dtype=wp.float64),
    live: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32),
):
    """Starting parameters ``(x, y, I0 f, s0, 0)`` of every found dot (``_model_start``; ``f = 1 + 1 / (12
    s0^2)`` per pair, computed on the host as there: a kernel's arithmetic may round it differently);
    rows of dots not found get a harmless dot of no intensity (drawn as zero, never used)."""
    i = wp.tid()
    b = i // per_frame
    s0 = sigma0[b]
    j = row0 + i
    frame[j] = frame_base + frame_step * b
    if wp.isfinite(x[i]):
        params[j, 0] = x[i]
        params[j, 1] = y[i]
        params[j, 2] = i0[i] * peak_factor[b]
        params[j, 3] = s0
        params[j, 4] = wp.float64(0.0)
        live[j] = 1
    else:
        params[j, 0] = wp.float64(0.0)
        params[j, 1] = wp.float64(0.0)
        params[j, 2] = wp.float64(0.0)
        params[j, 3] = s0
        params[j, 4] = wp.float64(0.0)
        live[j] = 0


@wp.kernel
def pair_partners(live: wp.array(dtype=wp.int32), n: int, partner: wp.array(dtype=wp.int32)):
    """Row ``i`` (reference) and ``n + i`` (gradient) are one dot's pair where both were found."""
    i = wp.tid()
    if live[i] != 0 and live[n + i] != 0:
        partner[i] = n + i
        partner[n + i] = i
    else:
        partner[i] = -1
        partner[n + i] = -1


@wp.kernel
def largest_peak(
    params: wp.array2d(dtype=wp.float64),
    live: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32),
    chunk: int,
    peak: wp.array(dtype=wp.float64),
):
    """The largest |peak| of each pair's live rows (``peak[b]``, pair b: frames 2 b and 2 b + 1): thread t
    takes rows ``t chunk`` .. ``(t + 1) chunk - 1`` and adds its maximum of each run of one pair's rows
    (a stack's rows lie frame by frame: a few atomics per thread, not one per row on 400 addresses)."""
    t = wp.tid()
    n = params.shape[0]
    b = int(-1)
    m = wp.float64(0.0)
    for i in range(t * chunk, wp.min((t + 1) * chunk, n)):
        if live[i] != 0:
            c = frame[i] // 2
            if c != b:
                if b >= 0:
                    wp.atomic_max(peak, b, m)
                b = c
                m = wp.float64(0.0)
            m = wp.max(m, wp.abs(params[i, 2]))
    if b >= 0:
        wp.atomic_max(peak, b, m)


#: The fixed-point scale's numerator, 2**50 (``dotfit._frame_scales_of``).
FIXED_RANGE = wp.constant(wp.float64(2.0**50))


@wp.kernel
def frame_scales(peak: wp.array(dtype=wp.float64), scales: wp.array(dtype=wp.float64)):
    """Frame f's fixed-point scale from its pair's largest peak, ``2**50 / (16 peak)``
    (``dotfit._frame_scales_of``), on the device: the host need not wait for the peaks."""
    f = wp.tid()
    scales[f] = FIXED_RANGE / (wp.float64(16.0) * wp.max(peak[f // 2], wp.float64(1e-300)))


@wp.kernel
def fit_step_stack(
    references: wp.array3d(dtype=wp.float64),
    gradients: wp.array3d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    scales: wp.array(dtype=wp.float64),
    params: wp.array2d(dtype=wp.float64),
    start: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    live: wp.array(dtype=wp.int32),
    saturation: wp.array(dtype=wp.float64),
    width_range: wp.array(dtype=wp.vec2d),
    half: int,
    render_half: int,
    common: int,
    max_move: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
    out: wp.array2d(dtype=wp.float64),
    ok: wp.array(dtype=wp.int32),
    shared_xy: wp.array2d(dtype=wp.float64),
):
    """``fit_dot_step`` of row i (a row not ``live`` keeps its parameters); model frame ``2 b`` is pair b's
    reference image, ``2 b + 1`` its gradient image (a single image is frame 0 of a stack of one, both
    arrays the same); a step that takes the width outside ``width_range[b]`` (the pair's) is refused."""
    i = wp.tid()
    if live[i] == 0:
        for k in range(5):
            out[i, k] = params[i, k]
        return
    f = frame[i]
    inv_scale = wp.float64(1.0) / scales[f]
    b = f // 2
    has_partner = int(partner[i] >= 0)
    lo = width_range[b][0]
    hi = width_range[b][1]
    if f % 2 == 0:
        fit_dot_step(
            references[b], models, inv_scale, params, start, f, i, has_partner, saturation[f], half, render_half,
            common, max_move, lo, hi, prof, out, ok, shared_xy,
        )  # fmt: skip
    else:
        fit_dot_step(
            gradients[b], models, inv_scale, params, start, f, i, has_partner, saturation[f], half, render_half,
            common, max_move, lo, hi, prof, out, ok, shared_xy,
        )  # fmt: skip


@wp.kernel
def take_model(
    params: wp.array2d(dtype=wp.float64),
    ok: wp.array(dtype=wp.int32),
    moved: wp.array(dtype=wp.int32),
    live: wp.array(dtype=wp.int32),
    row0: int,
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    eta: wp.array(dtype=wp.float64),
    i0: wp.array(dtype=wp.float64),
    flags: wp.array(dtype=wp.int32),
):
    """``_take_model``: the fit's position, width and peak (a refused last step flagged FIT_FALLBACK, a
    dot moved to its first moment DISTORTED)."""
    i = wp.tid()
    j = row0 + i
    if live[j] == 0 or not wp.isfinite(params[j, 0]):
        return
    x[i] = params[j, 0]
    y[i] = params[j, 1]
    eta[i] = params[j, 3]
    i0[i] = params[j, 2]
    if ok[j] == 0:
        flags[i] = flags[i] | FIT_FALLBACK
    if moved[j] != 0:
        flags[i] = flags[i] | DISTORTED


@wp.kernel
def raster_keys(
    params: wp.array2d(dtype=wp.float64),
    live: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32),
    h: int,
    w: int,
    keys: wp.array(dtype=wp.int64),
    order: wp.array(dtype=wp.int32),
):
    """Row i's key of the raster order of 4-row bands (frame, band, column; rows not live last) and
    ``order[i] = i``: sorted, neighbouring threads read neighbouring pixels (``dotfit._raster_order``)."""
    i = wp.tid()
    order[i] = i
    x = params[i, 0]
    y = params[i, 1]
    if live[i] == 0 or not (wp.isfinite(x) and wp.isfinite(y)):
        keys[i] = wp.int64(9223372036854775807)
        return
    bands = (h + 3) // 4
    band = wp.clamp(int(wp.floor(y / wp.float64(4.0))), 0, bands - 1)
    col = wp.clamp(int(wp.round(x)), 0, w - 1)
    keys[i] = (wp.int64(frame[i]) * wp.int64(bands) + wp.int64(band)) * wp.int64(w) + wp.int64(col)


@wp.kernel
def gather_rows(
    order: wp.array(dtype=wp.int32),
    params: wp.array2d(dtype=wp.float64),
    live: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    back: wp.array(dtype=wp.int32),
    params_out: wp.array2d(dtype=wp.float64),
    live_out: wp.array(dtype=wp.int32),
    frame_out: wp.array(dtype=wp.int32),
    partner_out: wp.array(dtype=wp.int32),
):
    """Row j of the sorted rows is row ``order[j]``; its partner is renumbered (``back``: the inverse order)."""
    j = wp.tid()
    i = order[j]
    for c in range(5):
        params_out[j, c] = params[i, c]
    live_out[j] = live[i]
    frame_out[j] = frame[i]
    p = partner[i]
    if p >= 0:
        partner_out[j] = back[p]
    else:
        partner_out[j] = -1


@wp.kernel
def inverse_order(order: wp.array(dtype=wp.int32), back: wp.array(dtype=wp.int32)):
    """``back[order[j]] = j``."""
    j = wp.tid()
    back[order[j]] = j


@wp.kernel
def scatter_rows(
    order: wp.array(dtype=wp.int32),
    params: wp.array2d(dtype=wp.float64),
    ok: wp.array(dtype=wp.int32),
    shared_xy: wp.array2d(dtype=wp.float64),
    moved: wp.array(dtype=wp.int32),
    params_out: wp.array2d(dtype=wp.float64),
    ok_out: wp.array(dtype=wp.int32),
    shared_out: wp.array2d(dtype=wp.float64),
    moved_out: wp.array(dtype=wp.int32),
):
    """The fit's results of sorted row j back to row ``order[j]``."""
    j = wp.tid()
    i = order[j]
    for c in range(5):
        params_out[i, c] = params[j, c]
    ok_out[i] = ok[j]
    shared_out[i, 0] = shared_xy[j, 0]
    shared_out[i, 1] = shared_xy[j, 1]
    moved_out[i] = moved[j]
