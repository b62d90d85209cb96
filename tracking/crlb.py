"""Cramer-Rao lower bound of dot positions and displacements under additive white Gaussian noise."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .dotfit import fit_window_half, integrated_profile

__all__ = ["displacement_crlb", "position_crlb"]


def position_crlb(xy, shape, *, diameter, noise, peak=1.0, nuisance=True):
    """Cramer-Rao bound of each dot's x and y in an image of pixel-integrated Gaussian dots.

    Parameters
    ----------
    xy : (N, 2) array
        True dot centres (x = column), pixels.
    shape : (H, W)
        Image shape (pixels outside carry no information).
    diameter : float, keyword-only
        e^-2 diameter ``d = 4 sigma`` of the (continuous) Gaussian, pixels.
    noise : float, keyword-only
        Standard deviation of the white Gaussian pixel noise (same units as ``peak``).
    peak : float or (N,) array, keyword-only
        Peak ``I0`` of each dot's continuous Gaussian.
    nuisance : bool, keyword-only
        True: every dot's peak and width and a local constant background are unknown too, as they are
        to an estimator of real images; False: only the positions are unknown (a lower bound).

    Returns
    -------
    (N, 2) array
        Standard deviations ``sqrt([F^-1]_xx)``, ``sqrt([F^-1]_yy)`` in pixels (0 where ``noise`` is 0).

    Notes
    -----
    The Fisher information of the model ``mu = b + sum_j I0_j p_x(x_j, sigma) p_y(y_j, sigma)``
    (:func:`tracking.dotfit.integrated_profile`) is ``F = J^T J / noise^2``, J the model's Jacobian over
    the pixels. It is evaluated locally: for each dot, the dot and every neighbour whose drawing stamp
    (4 sigma) overlaps its own take part with all their parameters, on the pixels within two stamp
    radii. An isolated 3 px dot of peak 1 gets about ``0.87 noise`` (nuisance) per axis; pixel
    integration flattens the dot (the bound of a sampled Gaussian is ``sqrt(2 / pi) noise / I0 = 0.80
    noise``), and overlapping neighbours raise it.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    n = len(xy)
    out = np.zeros((n, 2))
    if n == 0 or noise == 0:
        return out
    sigma = diameter / 4.0
    peaks = np.broadcast_to(np.asarray(peak, dtype=np.float64), (n,))
    _, half = fit_window_half(sigma)
    box = 2 * half
    m = 2 * box + 1
    tree = cKDTree(xy)
    h, w = shape
    for i, group in enumerate(tree.query_ball_point(xy, 2 * half + 1.0)):
        group = np.asarray(sorted(group, key=lambda j: j != i))  # the dot itself first
        ox, oy = np.rint(xy[i]).astype(np.int64) - box
        px, dpx, spx = integrated_profile(xy[group, 0], np.full(len(group), sigma), np.full(len(group), ox), m)
        py, dpy, spy = integrated_profile(xy[group, 1], np.full(len(group), sigma), np.full(len(group), oy), m)
        a = peaks[group][:, None, None]
        cols = [a * py[:, :, None] * dpx[:, None, :], a * dpy[:, :, None] * px[:, None, :]]
        if nuisance:
            cols += [
                py[:, :, None] * px[:, None, :],
                a * (spy[:, :, None] * px[:, None, :] + py[:, :, None] * spx[:, None, :]),
            ]
        jac = np.stack(cols, axis=1).reshape(len(group) * len(cols), m * m)
        if nuisance:
            jac = np.vstack([jac, np.ones((1, m * m))])
        rows = oy + np.arange(m)
        colsi = ox + np.arange(m)
        inside = (((rows >= 0) & (rows < h))[:, None] & ((colsi >= 0) & (colsi < w))[None, :]).ravel()
        jac = jac[:, inside]
        cov = np.linalg.inv(jac @ jac.T)
        out[i] = np.sqrt(np.diag(cov)[:2]) * noise
    return out


def displacement_crlb(reference_xy, gradient_xy, shape, *, diameter, noise, peak=1.0, nuisance=True):
    """Cramer-Rao bound of each dot's displacement (u, v) measured from two independent noisy images.

    Parameters
    ----------
    reference_xy, gradient_xy : (N, 2) arrays
        True centres in the reference and in the gradient image.
    shape, diameter, noise, peak, nuisance
        As for :func:`position_crlb`.

    Returns
    -------
    (N, 2) array
        ``sqrt(crlb_ref^2 + crlb_grad^2)`` per axis: the noise of the two images is independent, so a
        displacement's variance bound is the sum of the two positions' (about ``sqrt 2`` times one
        position's). The RMS error of an efficient estimator over many dots is
        ``sqrt(mean(bound^2))``.
    """
    kw = {"diameter": diameter, "noise": noise, "peak": peak, "nuisance": nuisance}
    a = position_crlb(reference_xy, shape, **kw)
    b = position_crlb(gradient_xy, shape, **kw)
    return np.sqrt(a**2 + b**2)
