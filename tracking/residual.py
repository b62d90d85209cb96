"""The residual image of iterative identification (Eq. 2 of Rajendran, Bane and Vlachos 2019)."""

from __future__ import annotations

import numpy as np

__all__ = ["render_gaussians", "subtract_gaussians"]


def render_gaussians(shape, xy, i0, eta, *, radius=None):
    """Sum of sampled Gaussians ``I0_p exp(-((X - X_p)^2 + (Y - Y_p)^2) / (2 eta_p^2))``.

    Parameters
    ----------
    shape : (H, W)
    xy : (N, 2) array
        Centres in pixels (x = column).
    i0, eta : (N,) arrays
        Peaks and standard deviations.
    radius : int, optional
        Half-width of each dot's stamp; ``ceil(3.5 max eta)`` by default.

    Returns
    -------
    (H, W) float64 array
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    i0 = np.broadcast_to(np.asarray(i0, dtype=np.float64), (len(xy),))
    eta = np.broadcast_to(np.asarray(eta, dtype=np.float64), (len(xy),))
    h, w = shape
    if len(xy) == 0:
        return np.zeros(shape)
    if radius is None:
        radius = int(np.ceil(3.5 * eta.max()))
    offs = np.arange(-radius, radius + 1)
    cx = np.rint(xy[:, 0]).astype(np.int64)
    cy = np.rint(xy[:, 1]).astype(np.int64)
    cols = cx[:, None] + offs
    rows = cy[:, None] + offs
    gx = np.exp(-((cols - xy[:, 0:1]) ** 2) / (2 * eta[:, None] ** 2))
    gy = np.exp(-((rows - xy[:, 1:2]) ** 2) / (2 * eta[:, None] ** 2))
    stamp = i0[:, None, None] * gy[:, :, None] * gx[:, None, :]
    inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
    flat = rows[:, :, None] * w + cols[:, None, :]
    return np.bincount(flat[inside], weights=stamp[inside], minlength=h * w).reshape(h, w)


def subtract_gaussians(image, xy, i0, eta, *, radius=None):
    """Residual image: the image minus the Gaussian of every dot identified so far.

    Parameters
    ----------
    image : (H, W) array
    xy : (N, 2) array
        Identified dot centres.
    i0, eta : (N,) arrays
        Their fitted peaks and standard deviations.
    radius : int, optional
        Stamp half-width, see :func:`render_gaussians`.

    Returns
    -------
    (H, W) float64 array

    Notes
    -----
    Eq. 2: ``I^{k+1} = I^k - sum_p I0_p exp(-((X - X_p)^2 + (Y - Y_p)^2) / (2 eta_p^2))``.
    """
    image = np.asarray(image, dtype=np.float64)
    return image - render_gaussians(image.shape, xy, i0, eta, radius=radius)
