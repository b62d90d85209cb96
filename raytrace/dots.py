"""Integrated Gaussian dot images, in NumPy.

This is the one home of the dot-image model: a dot of peak intensity ``I0`` and e^-2 diameter
``d`` (so ``sigma = d / 4``) centred at ``(x, y)`` deposits into pixel ``(i, j)`` the integral of
``I0 exp(-((X-x)^2 + (Y-y)^2) / (2 sigma^2))`` over that pixel's area, which is a product of two
differences of error functions. Pixel centres sit at integer coordinates, x = column, y = row.

It serves as the NumPy reference of the renderer's ``deposit_gaussian`` kernel and as the way the
tests and benchmarks synthesise images with an exactly known answer.
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf

__all__ = ["draw_dots", "pixel_erf_weights", "sigma_from_diameter"]


def sigma_from_diameter(diameter):
    """Standard deviation of the Gaussian whose e^-2 intensity diameter is ``diameter``."""
    return np.asarray(diameter, dtype=np.float64) / 4.0


def pixel_erf_weights(centre, sigma, first_pixel, n_pixels):
    """Fraction of a 1-D unit Gaussian falling in each of ``n_pixels`` consecutive pixels.

    Parameters
    ----------
    centre, sigma : (N,) arrays
        Gaussian centres and standard deviations, in pixels.
    first_pixel : (N,) int array
        Index of the first pixel of each window; pixel ``k`` spans ``[k - 0.5, k + 0.5]``.
    n_pixels : int
        Window length.

    Returns
    -------
    (N, n_pixels) array
        ``0.5 * (erf((k + 0.5 - c) / (sqrt(2) s)) - erf((k - 0.5 - c) / (sqrt(2) s)))``.
    """
    edges = first_pixel[:, None] + np.arange(n_pixels + 1)[None, :] - 0.5
    e = erf((edges - centre[:, None]) / (np.sqrt(2.0) * sigma[:, None]))
    return 0.5 * np.diff(e, axis=1)


def draw_dots(shape, xy, diameter, *, intensity=1.0, radius_sigmas=4.0, out=None):
    """Draw integrated Gaussian dots into an image.

    Parameters
    ----------
    shape : (H, W)
        Image shape.
    xy : (N, 2) array
        Dot centres in pixels, x = column, y = row, pixel centres at integer coordinates.
    diameter : float or (N,) array
        e^-2 intensity diameter of each dot in pixels (``sigma = diameter / 4``).
    intensity : float or (N,) array, keyword-only
        Peak intensity ``I0`` of the continuous Gaussian (a dot centred on a pixel reads a little less).
    radius_sigmas : float, keyword-only
        Half-width of the patch each dot is drawn into, in standard deviations.
    out : (H, W) float array, optional
        Image to add into; a new float64 image is made if omitted.

    Returns
    -------
    (H, W) float64 array
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    n = len(xy)
    image = np.zeros(shape, dtype=np.float64) if out is None else out
    if n == 0:
        return image
    sigma = np.broadcast_to(sigma_from_diameter(diameter), (n,)).astype(np.float64)
    i0 = np.broadcast_to(np.asarray(intensity, dtype=np.float64), (n,))
    half = int(np.ceil(radius_sigmas * sigma.max())) + 1
    size = 2 * half + 1
    x0 = np.round(xy[:, 0]).astype(np.int64) - half
    y0 = np.round(xy[:, 1]).astype(np.int64) - half
    wx = pixel_erf_weights(xy[:, 0], sigma, x0, size)
    wy = pixel_erf_weights(xy[:, 1], sigma, y0, size)
    # Integral of I0 exp(-r^2 / 2 s^2) over the plane is 2 pi s^2 I0.
    patch = (2.0 * np.pi * sigma**2 * i0)[:, None, None] * wy[:, :, None] * wx[:, None, :]
    cols = x0[:, None, None] + np.arange(size)[None, None, :]
    rows = y0[:, None, None] + np.arange(size)[None, :, None]
    cols, rows = np.broadcast_to(cols, patch.shape), np.broadcast_to(rows, patch.shape)
    inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    np.add.at(image, (rows[inside], cols[inside]), patch[inside])
    return image
