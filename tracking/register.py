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
from scipy.spatial import cKDTree

from .register_kernels import MAX_STEP_PX, MIN_PIXELS, REGISTRATION_STEPS, registration_kernel

__all__ = ["local_gradients", "registration_offsets", "registration_offsets_numpy", "spline_coefficients"]

_CHUNK = 1024


def spline_coefficients(image):
    """Cubic B-spline coefficients of an image (mirror boundary): the gradient image as the registration
    samples it between pixels."""
    return ndimage.spline_filter(np.asarray(image, dtype=np.float64), order=3, mode="mirror")


def local_gradients(xy, uv, *, k=12):
    """Gradient of a scattered displacement field at each of its points: the least-squares plane through
    the vectors of the point's ``k`` nearest other points.

    Parameters
    ----------
    xy, uv : (N, 2) arrays
        Points (x = column) and their displacements, px.
    k : int, keyword-only
        Neighbours per plane (with fewer than ``k + 1`` points every gradient is zero).

    Returns
    -------
    (N, 2, 2) array
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]``; a ridge of ``1e-6 (k + trace)`` keeps collinear
        neighbourhoods finite.

    Examples
    --------
    A shear ``u = 0.01 y, v = 0.01 x`` seen from the centre of a square of points:

    >>> xy = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0], [5.0, 5.0]])
    >>> np.round(local_gradients(xy, 0.01 * xy[:, ::-1], k=3)[4], 4).tolist()
    [[-0.0, 0.01], [0.01, -0.0]]
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    out = np.zeros((len(xy), 2, 2))
    if len(xy) <= k:
        return out
    _, idx = cKDTree(xy).query(xy, k=k + 1)
    nb = idx[:, 1:]  # the point itself comes first (distance 0)
    d = xy[nb] - xy[nb].mean(axis=1, keepdims=True)  # (N, k, 2)
    f = uv[nb] - uv[nb].mean(axis=1, keepdims=True)
    sxx, syy, sxy = (d[..., 0] ** 2).sum(1), (d[..., 1] ** 2).sum(1), (d[..., 0] * d[..., 1]).sum(1)
    ridge = 1e-6 * (k + sxx + syy)
    sxx, syy = sxx + ridge, syy + ridge
    det = sxx * syy - sxy * sxy
    bx, by = (d[..., 0:1] * f).sum(1), (d[..., 1:2] * f).sum(1)  # (N, 2): one column per component
    out[:, :, 0] = (syy[:, None] * bx - sxy[:, None] * by) / det[:, None]
    out[:, :, 1] = (sxx[:, None] * by - sxy[:, None] * bx) / det[:, None]
    return out


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
    gradients : (N, 2, 2) array, optional, keyword-only
        The displacement's gradient at each dot, ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` (e.g.
        :func:`local_gradients`): the window is deformed by it about the dot's position. Zero by default
        (the window only moves).

    Returns
    -------
    correction : (N, 2) array
        ``c`` such that the gradient image at ``p + uv + c + A (p - xy)`` matches the reference at ``p``
        over the window (least squares, up to a constant offset; ``A`` the gradient), px.
    ok : (N,) bool array
        Every step was solved: at least ``MIN_PIXELS`` usable pixels and a positive determinant.

    Notes
    -----
    ``REGISTRATION_STEPS`` Gauss-Newton steps on ``sum_p (G(p + uv + c + A (p - xy)) - R(p) - b)^2`` over the window
    pixels ``p`` (those whose reference central differences and spline taps lie inside the image), the
    offset ``b`` eliminated by centring the sums; the Jacobian is the mean of the two images' gradients
    (the reference's central differences and the spline's exact slope), as in the symmetric
    (efficient second-order) variant of the method. Each step is clipped to ``MAX_STEP_PX`` per axis; a
    dot whose step cannot be solved keeps the correction it had.

    Examples
    --------
    A 4 px dot moved by (0.5, -0.2) px, measured as (0.3, 0): the correction finds the rest.

    >>> from synthbos.raytrace.dots import draw_dots
    >>> ref = draw_dots((15, 15), [[7.0, 7.0]], 4.0)
    >>> grad = draw_dots((15, 15), [[7.5, 6.8]], 4.0)
    >>> c, ok = registration_offsets_numpy(ref, spline_coefficients(grad), [[7.0, 7.0]], [[0.3, 0.0]], half=4)
    >>> np.round(c, 2).tolist(), ok.tolist()
    ([[0.2, -0.2]], [True])
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


def _gradients(gradients, n):
    if gradients is None:
        return np.zeros((n, 2, 2))
    return np.ascontiguousarray(np.broadcast_to(np.asarray(gradients, dtype=np.float64), (n, 2, 2)))


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


def registration_offsets(reference, coefficients, xy, uv, *, half, gradients=None, device=None):
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
                up(_gradients(gradients, n), wp.mat22d), int(half), out, ok],
        device=device,
    )  # fmt: skip
    return out.numpy(), ok.numpy().astype(bool)
