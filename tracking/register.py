"""Registration check of measured displacements: does the image around a dot, moved by its displacement,
land on the gradient image?

The dot model fit measures a blob well only where the blob is a dot. On other patterns (speckle, squares,
blobs that merge or part between the images) a fit can miss the blob's motion by a pixel while every
other test passes. This step asks the images instead of the model: the reference window around the dot
(``2 half + 1`` pixels square, on the dot's nearest pixel) is registered onto the gradient image by
Lucas-Kanade steps (Lucas and Kanade 1981) that start from the measured displacement, and the
correction they find is the measurement's error as the images see it, whatever the pattern.
:func:`registration_offsets` is a Warp kernel (one thread per dot);
:func:`tracking.reference.registration_offsets_numpy` (tests only) is the array-program reference that
defines the result.
"""

from __future__ import annotations

import numpy as np
import warp as wp
from scipy import ndimage
from scipy.spatial import cKDTree

from .register_kernels import registration_kernel

__all__ = ["local_gradients", "misregistered", "registration_offsets", "spline_coefficients"]


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



def _gradients(gradients, n):
    if gradients is None:
        return np.zeros((n, 2, 2))
    return np.ascontiguousarray(np.broadcast_to(np.asarray(gradients, dtype=np.float64), (n, 2, 2)))



def registration_offsets(reference, coefficients, xy, uv, *, half, gradients=None, device=None):
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

    device : str or None, keyword-only
        Warp device ("cpu", "cuda:0"); Warp's default when None.

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
    >>> c, ok = registration_offsets(ref, spline_coefficients(grad), [[7.0, 7.0]], [[0.3, 0.0]], half=4)
    >>> np.round(c, 2).tolist(), ok.tolist()
    ([[0.2, -0.2]], [True])
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


def misregistered(reference, gradient, xy, uv_cc, uv, *, half, k, tolerance, device=None):
    """The MISREGISTERED rule: True where a dot's window, registered onto the gradient image from its
    correction ``uv_cc`` (:func:`registration_offsets`, with the field's local gradients from its ``k``
    nearest dots), ends further than ``tolerance`` px from ``uv_cc`` or from the centroid difference ``uv``,
    or cannot be registered. ``xy``, ``uv_cc`` and ``uv`` are (N, 2) arrays, ``half`` the window's half-size.

    Examples
    --------
    >>> import numpy as np
    >>> from synthbos.raytrace.dots import draw_dots
    >>> xy = np.array([[20.0, 20.0], [40.0, 22.0], [30.0, 40.0], [18.0, 44.0], [44.0, 42.0]])
    >>> ref, grad = draw_dots((64, 64), xy, 3.0), draw_dots((64, 64), xy + [0.6, 0.0], 3.0)
    >>> uv = np.tile([0.6, 0.0], (5, 1))
    >>> misregistered(ref, grad, xy, uv, uv, half=3, k=4, tolerance=0.25, device="cpu").tolist()
    [False, False, False, False, False]
    >>> misregistered(ref, grad, xy, uv + 1.0, uv + 1.0, half=3, k=4, tolerance=0.25, device="cpu").any()
    np.True_
    """
    xy, uv_cc, uv = (np.asarray(a, dtype=np.float64).reshape(-1, 2) for a in (xy, uv_cc, uv))
    coef = spline_coefficients(gradient)
    grads = local_gradients(xy, uv_cc, k=k)
    c, ok = registration_offsets(reference, coef, xy, uv_cc, half=half, gradients=grads, device=device)
    far = np.hypot(c[:, 0], c[:, 1]) > tolerance
    far |= np.hypot(*(uv_cc + c - uv).T) > tolerance
    return far | ~ok
