"""Soloff-type polynomial calibration mapping from target coordinates to image positions."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synthbos import SynthbosError

__all__ = ["SoloffMapping", "fit_soloff"]


def _terms(order):
    return [(i, j) for i in range(order + 1) for j in range(order + 1 - i)]


def _design(xy, centre, scale, order):
    u = (xy[:, 0] - centre[0]) / scale[0]
    v = (xy[:, 1] - centre[1]) / scale[1]
    return np.stack([u**i * v**j for i, j in _terms(order)], axis=1)


@dataclass(frozen=True)
class SoloffMapping:
    """A fitted polynomial mapping, callable on ``(N, 2)`` target positions; returns image positions.

    Attributes
    ----------
    order : int
        Total polynomial degree in the target coordinates (3: cubic in x and y).
    coef : (n_terms, 2) array
        Coefficients of the terms ``u^i v^j`` (``i + j <= order``) for image x and image y, with the
        target coordinates normalised as ``u = (x - centre_x) / scale_x``.
    centre, scale : (2,) arrays
        Normalisation of the target coordinates.
    rms : float
        Root-mean-square residual of the fit, in image pixels.
    """

    order: int
    coef: np.ndarray
    centre: np.ndarray
    scale: np.ndarray
    rms: float

    def __call__(self, target_xy):
        xy = np.asarray(target_xy, dtype=np.float64).reshape(-1, 2)
        return _design(xy, self.centre, self.scale, self.order) @ self.coef


def fit_soloff(target_xy, image_xy, order=3):
    """Fit a Soloff-type polynomial mapping target -> image by linear least squares.

    Parameters
    ----------
    target_xy : (N, 2) array
        Dot positions on the target (any length unit).
    image_xy : (N, 2) array
        The same dots' positions in the image, in pixels (x = column, y = row).
    order : int
        Total degree of the polynomial in the two target coordinates; 3 (cubic) as in Soloff, Adrian and
        Liu (1997) for the in-plane coordinates.

    Returns
    -------
    SoloffMapping
        Callable mapping ``(M, 2)`` target positions to image positions.

    Raises
    ------
    synthbos.SynthbosError
        Mismatched or non-finite correspondences, or fewer than the number of polynomial terms.
    """
    t = np.asarray(target_xy, dtype=np.float64)
    p = np.asarray(image_xy, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 2 or p.shape != t.shape:
        raise SynthbosError(
            f"calibration needs two Nx2 position arrays of one shape, got {t.shape} and {p.shape}"
        )
    if not (np.isfinite(t).all() and np.isfinite(p).all()):
        raise SynthbosError("calibration correspondences contain non-finite values")
    n_terms = len(_terms(order))
    if len(t) < n_terms:
        raise SynthbosError(
            f"an order-{order} calibration needs at least {n_terms} correspondences, got {len(t)}"
        )
    centre = 0.5 * (t.min(axis=0) + t.max(axis=0))
    scale = 0.5 * (t.max(axis=0) - t.min(axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    A = _design(t, centre, scale, order)
    coef, *_ = np.linalg.lstsq(A, p, rcond=None)
    rms = float(np.sqrt(np.mean(np.sum((A @ coef - p) ** 2, axis=1))))
    return SoloffMapping(order=order, coef=coef, centre=centre, scale=scale, rms=rms)
