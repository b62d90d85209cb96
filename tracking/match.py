"""Pairing dots identified independently in the two images (standard tracking)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .settings import MATCH_METHODS

__all__ = ["MATCH_METHODS", "match_multiparametric", "match_nearest"]


def _one_to_one(cost, ref_idx, grad_idx, n_ref):
    """Greedy one-to-one assignment of candidate pairs in order of increasing cost."""
    order = np.argsort(cost, kind="stable")
    ref_idx, grad_idx = ref_idx[order], grad_idx[order]
    out = np.full(n_ref, -1, dtype=np.int64)
    # Keep the cheapest pair per gradient dot, then the cheapest per reference dot, until stable.
    while len(ref_idx):
        _, first_g = np.unique(grad_idx, return_index=True)
        keep = np.zeros(len(grad_idx), dtype=bool)
        keep[first_g] = True
        _, first_r = np.unique(ref_idx, return_index=True)
        best_r = np.zeros(len(ref_idx), dtype=bool)
        best_r[first_r] = True
        take = keep & best_r
        if not take.any():
            break
        out[ref_idx[take]] = grad_idx[take]
        used_r = np.zeros(n_ref, dtype=bool)
        used_r[ref_idx[take]] = True
        used_g = np.zeros(grad_idx.max() + 1, dtype=bool)
        used_g[grad_idx[take]] = True
        rest = ~used_r[ref_idx] & ~used_g[grad_idx]
        ref_idx, grad_idx = ref_idx[rest], grad_idx[rest]
    return out


def _candidates(ref_xy, grad_xy, radius, k):
    tree = cKDTree(grad_xy)
    k = min(k, len(grad_xy))
    dist, idx = tree.query(ref_xy, k=k, distance_upper_bound=radius)
    dist, idx = dist.reshape(len(ref_xy), k), idx.reshape(len(ref_xy), k)
    valid = np.isfinite(dist)
    ref_idx = np.broadcast_to(np.arange(len(ref_xy))[:, None], dist.shape)[valid]
    return ref_idx, idx[valid], dist[valid]


def match_nearest(ref_xy, grad_xy, *, radius):
    """Pair each reference dot with the nearest gradient dot within a search radius, one to one.

    Parameters
    ----------
    ref_xy, grad_xy : (N, 2), (M, 2) arrays
        Dot positions in the two images.
    radius : float, keyword-only
        Search radius in pixels.

    Returns
    -------
    (N,) int array
        Index into ``grad_xy`` of each reference dot's partner, -1 where there is none.
    """
    ref_xy = np.asarray(ref_xy, dtype=np.float64).reshape(-1, 2)
    grad_xy = np.asarray(grad_xy, dtype=np.float64).reshape(-1, 2)
    if len(ref_xy) == 0 or len(grad_xy) == 0:
        return np.full(len(ref_xy), -1, dtype=np.int64)
    r, g, d = _candidates(ref_xy, grad_xy, radius, 4)
    return _one_to_one(d, r, g, len(ref_xy))


def match_multiparametric(
    ref_xy, grad_xy, ref_peak, grad_peak, ref_diameter, grad_diameter, *, radius, weights=(1.0, 1.0, 1.0)
):
    """Multi-parametric pairing: minimise a weighted residual of distance, peak intensity and diameter.

    Parameters
    ----------
    ref_xy, grad_xy : (N, 2), (M, 2) arrays
        Dot positions.
    ref_peak, grad_peak : (N,), (M,) arrays
        Peak intensities.
    ref_diameter, grad_diameter : (N,), (M,) arrays
        Diameters.
    radius : float, keyword-only
        Search radius in pixels.
    weights : (w_distance, w_intensity, w_diameter), keyword-only

    Returns
    -------
    (N,) int array
        Index into ``grad_xy`` of each reference dot's partner, -1 where there is none.

    Notes
    -----
    After Cardwell, Vlachos and Thole (2011): for every candidate within the radius the residual
    ``R = w_d |dx| / radius + w_I |I_g - I_r| / max(I_g, I_r) + w_D |D_g - D_r| / max(D_g, D_r)``; pairs
    are taken in order of increasing R, each dot at most once.
    """
    ref_xy = np.asarray(ref_xy, dtype=np.float64).reshape(-1, 2)
    grad_xy = np.asarray(grad_xy, dtype=np.float64).reshape(-1, 2)
    if len(ref_xy) == 0 or len(grad_xy) == 0:
        return np.full(len(ref_xy), -1, dtype=np.int64)
    r, g, d = _candidates(ref_xy, grad_xy, radius, 8)
    ip, gp = np.asarray(ref_peak, dtype=np.float64)[r], np.asarray(grad_peak, dtype=np.float64)[g]
    idm, gdm = np.asarray(ref_diameter, dtype=np.float64)[r], np.asarray(grad_diameter, dtype=np.float64)[g]
    with np.errstate(invalid="ignore", divide="ignore"):
        ti = np.nan_to_num(np.abs(gp - ip) / np.maximum(np.abs(gp), np.abs(ip)), nan=1.0)
        td = np.nan_to_num(np.abs(gdm - idm) / np.maximum(np.abs(gdm), np.abs(idm)), nan=1.0)
    wd, wi, wD = weights
    cost = wd * d / radius + wi * ti + wD * td
    return _one_to_one(cost, r, g, len(ref_xy))
