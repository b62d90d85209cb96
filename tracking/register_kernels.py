"""Warp kernel of the registration check: the window around a dot, moved by its displacement, refined by
Lucas-Kanade steps (Lucas and Kanade 1981) on the gradient image.

The host code lives in :mod:`tracking.register`, the NumPy reference that defines the result in
:mod:`tracking.reference` (``registration_offsets_numpy``, tests only).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

#: Gauss-Newton (Lucas-Kanade) steps of the registration; each step is clipped to this many pixels per
#: axis.
REGISTRATION_STEPS = 3
MAX_STEP_PX = 1.0
#: A window needs at least this many usable pixels (inside the image with the spline's taps and the
#: reference's central differences) to be registered.
MIN_PIXELS = 9
STEPS = wp.constant(REGISTRATION_STEPS)
MAX_STEP = wp.constant(wp.float64(MAX_STEP_PX))
MIN_COUNT = wp.constant(wp.float64(MIN_PIXELS))
SIXTH = wp.constant(wp.float64(1.0 / 6.0))  # a float64 constant: a literal quotient in a kernel is float32


@wp.func
def bspline3(t: wp.float64):
    """Weights and slopes of the cubic B-spline's four taps (offsets -1, 0, 1, 2 from ``floor``) at
    fraction ``t``."""
    one = wp.float64(1.0)
    sixth = SIXTH
    s = one - t
    t2 = t * t
    t3 = t2 * t
    w = wp.vec4d(
        s * s * s * sixth,
        (wp.float64(3.0) * t3 - wp.float64(6.0) * t2 + wp.float64(4.0)) * sixth,
        (-wp.float64(3.0) * t3 + wp.float64(3.0) * t2 + wp.float64(3.0) * t + one) * sixth,
        t3 * sixth,
    )
    dw = wp.vec4d(
        -s * s * wp.float64(0.5),
        wp.float64(1.5) * t2 - wp.float64(2.0) * t,
        -wp.float64(1.5) * t2 + t + wp.float64(0.5),
        t2 * wp.float64(0.5),
    )
    return w, dw


@wp.func
def registration_sums(
    ref: wp.array2d(dtype=wp.float64),
    coef: wp.array2d(dtype=wp.float64),
    bx: int,
    by: int,
    half: int,
    x0: wp.float64,
    y0: wp.float64,
    tx: wp.float64,
    ty: wp.float64,
    a: wp.mat22d,
):
    """The window's sums for one step at the trial displacement (tx, ty) at the dot (x0, y0), with the
    displacement gradient ``a``: count, Jx, Jy, r, JxJx, JxJy, JyJy, Jx r, Jy r (see
    ``tracking.reference.registration_offsets_numpy``)."""
    h = ref.shape[0]
    w = ref.shape[1]
    zero = wp.float64(0.0)
    half_f = wp.float64(0.5)
    n = zero
    sx = zero
    sy = zero
    sr = zero
    sxx = zero
    sxy = zero
    syy = zero
    sxr = zero
    syr = zero
    for j in range(-half, half + 1):
        py = by + j
        dy0 = wp.float64(py) - y0
        for i in range(-half, half + 1):
            px = bx + i
            dx0 = wp.float64(px) - x0
            qx = wp.float64(px) + tx + (a[0, 0] * dx0 + a[0, 1] * dy0)
            qy = wp.float64(py) + ty + (a[1, 0] * dx0 + a[1, 1] * dy0)
            ix = int(wp.floor(qx))
            iy = int(wp.floor(qy))
            if px < 1 or py < 1 or px > w - 2 or py > h - 2 or ix < 1 or iy < 1 or ix > w - 3 or iy > h - 3:
                continue
            wx, dwx = bspline3(qx - wp.float64(ix))
            wy, dwy = bspline3(qy - wp.float64(iy))
            g = zero
            gx = zero
            gy = zero
            for ky in range(4):
                taps = wp.vec4d(
                    coef[iy - 1 + ky, ix - 1],
                    coef[iy - 1 + ky, ix],
                    coef[iy - 1 + ky, ix + 1],
                    coef[iy - 1 + ky, ix + 2],
                )
                row = wp.dot(wx, taps)
                drow = wp.dot(dwx, taps)
                g += wy[ky] * row
                gx += wy[ky] * drow
                gy += dwy[ky] * row
            r0 = ref[py, px]
            jx = half_f * (half_f * (ref[py, px + 1] - ref[py, px - 1]) + gx)
            jy = half_f * (half_f * (ref[py + 1, px] - ref[py - 1, px]) + gy)
            res = g - r0
            n += wp.float64(1.0)
            sx += jx
            sy += jy
            sr += res
            sxx += jx * jx
            sxy += jx * jy
            syy += jy * jy
            sxr += jx * res
            syr += jy * res
    return n, sx, sy, sr, sxx, sxy, syy, sxr, syr


@wp.kernel
def registration_kernel(
    ref: wp.array2d(dtype=wp.float64),
    coef: wp.array2d(dtype=wp.float64),
    xy: wp.array(dtype=wp.vec2d),
    uv: wp.array(dtype=wp.vec2d),
    gradients: wp.array(dtype=wp.mat22d),
    half: int,
    out: wp.array(dtype=wp.vec2d),
    ok: wp.array(dtype=wp.int32),
):
    """One thread per dot: ``out`` the correction to ``uv`` after ``REGISTRATION_STEPS`` steps, ``ok`` 1
    where every step could be solved (see ``tracking.reference.registration_offsets_numpy``)."""
    d = wp.tid()
    x0 = xy[d][0]
    y0 = xy[d][1]
    bx = int(wp.rint(x0))
    by = int(wp.rint(y0))
    a = gradients[d]
    cx = wp.float64(0.0)
    cy = wp.float64(0.0)
    good = wp.int32(1)
    lim = MAX_STEP
    for _ in range(STEPS):
        tx = uv[d][0] + cx
        ty = uv[d][1] + cy
        n, sx, sy, sr, sxx, sxy, syy, sxr, syr = registration_sums(ref, coef, bx, by, half, x0, y0, tx, ty, a)
        if n < MIN_COUNT:
            good = wp.int32(0)
            break
        axx = sxx - sx * sx / n
        axy = sxy - sx * sy / n
        ayy = syy - sy * sy / n
        bxr = sxr - sx * sr / n
        byr = syr - sy * sr / n
        det = axx * ayy - axy * axy
        if not (det > wp.float64(0.0)):
            good = wp.int32(0)
            break
        cx += wp.clamp(-(ayy * bxr - axy * byr) / det, -lim, lim)
        cy += wp.clamp(-(axx * byr - axy * bxr) / det, -lim, lim)
    out[d] = wp.vec2d(cx, cy)
    ok[d] = good
