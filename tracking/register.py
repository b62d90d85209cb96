"""Registration check of measured displacements: does the image around a dot, moved by its displacement,
land on the gradient image?

The dot model fit measures a blob well only where the blob is a dot. On other patterns (speckle, squares,
blobs that merge or part between the images) a fit can miss the blob's motion by a pixel while every
other test passes. This step asks the images instead of the model: the reference window around the dot
(``2 half + 1`` pixels square, on the dot's nearest pixel) is registered onto the gradient image by
Lucas-Kanade steps (Lucas and Kanade 1981) that start from the measured displacement, and the
correction they find is the measurement's error as the images see it, whatever the pattern.
:func:`registration_offsets` is a Warp kernel (one thread per dot); :func:`registration_offsets_numpy`
is the array-program reference that defines the result.
"""

from __future__ import annotations

import numpy as np
import warp as wp
from scipy import ndimage

from .register_kernels import MAX_STEP_PX, MIN_PIXELS, REGISTRATION_STEPS, registration_kernel

__all__ = ["registration_offsets", "registration_offsets_numpy", "spline_coefficients"]

_CHUNK = 1024


def spline_coefficients(image):
    """Cubic B-spline coefficients of an image (mirror boundary): the gradient image as the registration
    samples it between pixels."""
    return ndimage.spline_filter(np.asarray(image, dtype=np.float64), order=3, mode="mirror")


def _bspline3(t):
    """(..., 4) weights and slopes of the cubic B-spline taps at offsets -1, 0, 1, 2 for fractions ``t``."""
    t = np.asarray(t)[..., None]
    s = 1.0 - t
    w = np.concatenate([s**3 / 6, (3 * t**3 - 6 * t**2 + 4) / 6, (-3 * t**3 + 3 * t**2 + 3 * t + 1) / 6, t**3 / 6], -1)
    dw = np.concatenate([-(s**2) / 2, 1.5 * t**2 - 2 * t, -1.5 * t**2 + t + 0.5, t**2 / 2], -1)
    return w, dw


def _sums(ref, coef, bx, by, half, tx, ty):
    """Per dot: usable pixel count and the centred normal equations (axx, axy, ayy, bxr, byr)."""
    h, w = ref.shape
    off = np.arange(-half, half + 1)
    px = (bx[:, None] + off)[:, None, :]  # (N, 1, n): column of each window pixel
    py = (by[:, None] + off)[:, :, None]  # (N, n, 1)
    qx, qy = px + tx[:, None, None], py + ty[:, None, None]
    ix, iy = np.floor(qx).astype(np.int64), np.floor(qy).astype(np.int64)
    use = (px >= 1) & (py >= 1) & (px <= w - 2) & (py <= h - 2) & (ix >= 1) & (iy >= 1) & (ix <= w - 3) & (iy <= h - 3)
    wx, dwx = _bspline3(qx - ix)  # (N, 1, n, 4)
    wy, dwy = _bspline3(qy - iy)  # (N, n, 1, 4)
    rows = np.clip(iy[..., None] - 1 + np.arange(4), 0, h - 1)  # (N, n, 1, 4)
    cols = np.clip(ix[..., None] - 1 + np.arange(4), 0, w - 1)  # (N, 1, n, 4)
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


def registration_offsets_numpy(reference, coefficients, xy, uv, *, half):
    """Lucas-Kanade correction of each displacement, registering the reference window onto the gradient image.

    Parameters
    ----------
    reference : (H, W) array
        Reference image.
    coefficients : (H, W) array
        The gradient image's cubic B-spline coefficients (:func:`spline_coefficients`).
    xy : (N, 2) array
        Reference-image positions of the dots (x = column); the window is centred on the nearest pixel.
    uv : (N, 2) array
        Their measured displacements, px.
    half : int, keyword-only
        Half-width of the window.

    Returns
    -------
    correction : (N, 2) array
        ``c`` such that the gradient image at ``p + uv + c`` matches the reference at ``p`` over the window
        (least squares, up to a constant offset), px.
    ok : (N,) bool array
        Every step was solved: at least ``MIN_PIXELS`` usable pixels and a positive determinant.

    Notes
    -----
    ``REGISTRATION_STEPS`` Gauss-Newton steps on ``sum_p (G(p + uv + c) - R(p) - b)^2`` over the window
    pixels ``p`` (those whose reference central differences and spline taps lie inside the image), the
    offset ``b`` eliminated by centring the sums; the Jacobian is the mean of the two images' gradients
    (the reference's central differences and the spline's exact slope), as in the symmetric
    (efficient second-order) variant of the method. Each step is clipped to ``MAX_STEP_PX`` per axis; a
    dot whose step cannot be solved keeps the correction it had.
    """
    ref = np.asarray(reference, dtype=np.float64)
    coef = np.asarray(coefficients, dtype=np.float64)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    c = np.zeros_like(uv)
    ok = np.ones(len(xy), dtype=bool)
    for a in range(0, len(xy), _CHUNK):  # bounded memory: 16 taps per window pixel per dot
        c[a : a + _CHUNK], ok[a : a + _CHUNK] = _register(ref, coef, xy[a : a + _CHUNK], uv[a : a + _CHUNK], half)
    return c, ok


def _register(ref, coef, xy, uv, half):
    bx, by = np.rint(xy[:, 0]).astype(np.int64), np.rint(xy[:, 1]).astype(np.int64)
    c = np.zeros_like(uv)
    ok = np.ones(len(xy), dtype=bool)
    for _ in range(REGISTRATION_STEPS):
        act = np.flatnonzero(ok)
        if act.size == 0:
            break
        n, axx, axy, ayy, bxr, byr = _sums(ref, coef, bx[act], by[act], half, *(uv[act] + c[act]).T)
        det = axx * ayy - axy * axy
        solved = (n >= MIN_PIXELS) & (det > 0)
        ok[act[~solved]] = False
        safe = np.where(solved, det, 1.0)
        step = np.stack([-(ayy * bxr - axy * byr) / safe, -(axx * byr - axy * bxr) / safe], axis=1)
        c[act[solved]] += np.clip(step[solved], -MAX_STEP_PX, MAX_STEP_PX)
    return c, ok


def registration_offsets(reference, coefficients, xy, uv, *, half, device=None):
    """Same as :func:`registration_offsets_numpy`, with a Warp kernel (one thread per dot).

    Parameters
    ----------
    device : str or None, keyword-only
        Warp device ("cpu", "cuda:0"); Warp's default when None.

    Other parameters and the result are those of :func:`registration_offsets_numpy`.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n = len(xy)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)

    def up(a, dtype):
        return wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=dtype, device=device)

    out = wp.empty(n, dtype=wp.vec2d, device=device)
    ok = wp.empty(n, dtype=wp.int32, device=device)
    wp.launch(
        registration_kernel,
        dim=n,
        inputs=[up(reference, wp.float64), up(coefficients, wp.float64), up(xy, wp.vec2d), up(uv, wp.vec2d),
                int(half), out, ok],
        device=device,
    )  # fmt: skip
    return out.numpy(), ok.numpy().astype(bool)
