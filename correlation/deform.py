"""Image deformation for window-deformation correlation: host code of :mod:`correlation.kernels`.

The predictor displacement, known on the window-centre grid of a pass, is carried to every pixel
by a separable cubic spline (:func:`grid_to_pixels`); both images are then resampled symmetrically,
the first at ``x - d(x)/2`` and the second at ``x + d(x)/2`` (:func:`deform_pair`), with cubic
B-spline interpolation on coefficients computed once per image (:func:`bspline3_coefficients`)
or with a Lanczos-3 kernel. Scarano, Meas. Sci. Technol. 13 (2002) R1, section 4; Unser, IEEE Signal
Process. Mag. 16 (1999) 22 for the B-spline prefilter.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.interpolate import CubicSpline

__all__ = ["INTERPOLATORS", "bspline3_coefficients", "deform_pair", "grid_to_pixels", "spline_weights"]

INTERPOLATORS = ("cubic", "keys", "lanczos")


def _warp():
    import warp as wp

    from synthbos.device import init_warp

    from . import kernels

    init_warp()
    return wp, kernels


def bspline3_coefficients(image):
    """Cubic B-spline interpolation coefficients of an image, mirror boundary.

    Parameters
    ----------
    image : (H, W) array
        Samples at the pixel centres.

    Returns
    -------
    (H, W) float32 array
        Coefficients ``c`` with ``sum_kl c[k, l] beta3(y - k) beta3(x - l) = image[y, x]`` at every
        pixel: ``scipy.ndimage.spline_filter(image, order=3, mode="mirror")`` (recursive filtering
        with the pole ``sqrt(3) - 2``, Unser 1999, eqs. 5-8), computed once per image.
    """
    # the recursive filter runs along contiguous rows (about 2.5x faster than down columns): filter
    # the rows, transpose, filter the rows again, transpose back
    rows = ndimage.spline_filter1d(
        np.asarray(image, dtype=np.float32), order=3, axis=1, mode="mirror", output=np.float32
    )
    cols = ndimage.spline_filter1d(
        np.ascontiguousarray(rows.T), order=3, axis=1, mode="mirror", output=np.float32
    )
    return np.ascontiguousarray(cols.T)


def _as_warp(wp, a, device):
    # float32 C-contiguous arrays on the CPU are shared, not copied
    a = np.ascontiguousarray(a, dtype=np.float32)
    return wp.array(a, dtype=wp.float32, device=device, copy=False)


def deform_pair(first, second, du, dv, *, origin=(0, 0), interpolator="cubic", device=None):
    """Resample two images symmetrically along a dense displacement field.

    Parameters
    ----------
    first, second : (H, W) arrays
        For ``interpolator="cubic"`` the images' B-spline coefficients
        (:func:`bspline3_coefficients`); for ``"keys"`` and ``"lanczos"`` the images themselves.
    du, dv : (h, w) arrays
        Displacement (x = column, y = row) at the points ``origin + (i, j)`` of the output,
        ``0 <= i < h``, ``0 <= j < w``.
    origin : (row, col) floats
        Position of the first output point (need not be a pixel centre).
    interpolator : {"cubic", "keys", "lanczos"}
        4x4-tap B-spline or Keys cubic convolution (one Warp thread per output row), or Lanczos-3.
    device : str, optional
        Warp device.

    Returns
    -------
    first_def, second_def : (h, w) float32 arrays
        ``first(y - dv/2, x - du/2)`` and ``second(y + dv/2, x + du/2)`` at the output points.
    """
    if interpolator not in INTERPOLATORS:
        raise ValueError(f"unknown interpolator {interpolator!r}; choose one of {INTERPOLATORS}")
    wp, k = _warp()
    shape = np.shape(du)
    args = [*(_as_warp(wp, a, device) for a in (first, second, du, dv)), float(origin[0]), float(origin[1])]
    out_first = wp.empty(shape, dtype=wp.float32, device=device)
    out_second = wp.empty(shape, dtype=wp.float32, device=device)
    if interpolator == "lanczos":
        wp.launch(k.deform_pair_lanczos3, dim=shape, inputs=args, outputs=[out_first, out_second], device=device)
    else:
        wp.launch(
            k.deform_rows_cubic,
            dim=shape[0],
            inputs=[*args, int(interpolator == "keys")],
            outputs=[out_first, out_second],
            device=device,
        )
    return out_first.numpy(), out_second.numpy()


def spline_weights(nodes, points):
    """Weights of 1-D not-a-knot cubic spline interpolation from ``nodes`` to ``points``.

    Parameters
    ----------
    nodes : (n,) increasing array
    points : (m,) array

    Returns
    -------
    (m, n) float array
        ``W`` such that ``W @ f`` is the spline through ``(nodes, f)`` evaluated at ``points``;
        beyond the end nodes the spline continues along its end tangent, so a linear field is
        reproduced exactly everywhere while the end cubic of a rough field does not overshoot (in
        the half window beyond the outermost vectors it did, by up to a pixel on the benchmark's
        random-phase fields). With fewer than four nodes the spline is the interpolating polynomial
        (constant, linear, quadratic).
    """
    nodes = np.asarray(nodes, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    n = len(nodes)
    if n == 1:
        return np.ones((len(points), 1))
    if n == 2:
        t = (points - nodes[0]) / (nodes[1] - nodes[0])
        return np.stack([1.0 - t, t], axis=1)
    spline = CubicSpline(nodes, np.eye(n), bc_type="not-a-knot", extrapolate=True)
    inside = np.clip(points, nodes[0], nodes[-1])
    beyond = (points - inside)[:, None]
    return spline(inside) + beyond * spline(inside, 1)


def grid_to_pixels(fields, node_y, node_x, rows, cols):
    """Interpolate fields on a rectilinear node grid to a rectilinear set of pixels.

    Parameters
    ----------
    fields : (..., ny, nx) array
        Values at the nodes ``(node_y[i], node_x[j])``; leading axes are separate fields.
    node_y, node_x : 1-D arrays
        Node coordinates (row and column).
    rows, cols : 1-D arrays
        Target coordinates.

    Returns
    -------
    (..., len(rows), len(cols)) float32 array
        The separable not-a-knot cubic spline of :func:`spline_weights`, ``Wy @ field @ Wx.T``.
    """
    wy = spline_weights(node_y, rows).astype(np.float32)
    wx = spline_weights(node_x, cols).astype(np.float32)
    return (wy @ np.asarray(fields, dtype=np.float32)) @ wx.T
