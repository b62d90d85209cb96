"""Pairing dots identified independently in the two images (standard tracking)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .settings import DIAMETER_PER_WIDTH, MATCH_METHODS, search_reach

__all__ = ["MATCH_METHODS", "match_multiparametric", "match_nearest", "pair_dots", "paired_rows"]


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


def pair_dots(ref_xy, r, g, settings):
    """Standard tracking's pairing of the reference dots ``r`` (their positions moved to ``ref_xy``, the
    predicted gradient-image positions) with the gradient dots ``g`` (dicts of per-dot arrays ``x``, ``y``,
    ``eta``, ``i0``) by ``settings.matching`` within :func:`tracking.settings.search_reach`: each reference
    dot's partner index, -1 where there is none.

    Examples
    --------
    >>> from synthbos.tracking.settings import TrackingSettings
    >>> r = {"x": np.array([5.0, 20.0]), "y": np.array([5.0, 5.0]), "eta": np.ones(2), "i0": np.ones(2)}
    >>> g = {"x": np.array([20.5, 5.4]), "y": np.array([5.0, 5.0]), "eta": np.ones(2), "i0": np.ones(2)}
    >>> pair_dots(np.stack([r["x"], r["y"]], axis=1), r, g, TrackingSettings(max_displacement=2.0)).tolist()
    [1, 0]
    """
    radius = search_reach(settings)
    gxy = np.stack([g["x"], g["y"]], axis=1)
    if settings.matching == "nearest":
        return match_nearest(ref_xy, gxy, radius=radius)
    sizes = (DIAMETER_PER_WIDTH * r["eta"], DIAMETER_PER_WIDTH * g["eta"])
    return match_multiparametric(ref_xy, gxy, r["i0"], g["i0"], *sizes, radius=radius, weights=settings.match_weights)


def paired_rows(r, g, partner, rows):
    """One pair's paired dots laid out in ``rows`` rows of a stack, as the prior's rows are: row i < n (the
    n reference dots) holds reference dot i and its partner, the next rows the gradient dots without
    one, the rest nothing (x NaN, everything else 0). Returns the two images' row dicts.

    Examples
    --------
    >>> r = {"x": np.array([1.0, 2.0]), "flags": np.array([4, 8])}
    >>> g = {"x": np.array([7.0, 8.0, 9.0]), "flags": np.array([1, 2, 3])}
    >>> rr, gg = paired_rows(r, g, np.array([2, -1]), 4)
    >>> rr["x"].tolist(), gg["x"].tolist(), gg["flags"].tolist()
    ([1.0, 2.0, nan, nan], [9.0, nan, 7.0, 8.0], [3, 0, 1, 2])
    """
    n = len(r["x"])
    alone = np.setdiff1d(np.arange(len(g["x"])), partner[partner >= 0])
    g_rows = np.full(rows, -1)
    g_rows[:n] = partner
    g_rows[n : n + alone.size] = alone
    out = []
    for found, at in ((r, np.where(np.arange(rows) < n, np.arange(rows), -1)), (g, g_rows)):
        has = at >= 0
        laid = {}
        for key, v in found.items():
            shape = (rows, *v.shape[1:])
            a = np.full(shape, np.nan) if key in ("x", "y", "eta", "i0") else np.zeros(shape, v.dtype)
            a[has] = v[at[has]]
            laid[key] = a
        out.append(laid)
    return out[0], out[1]
