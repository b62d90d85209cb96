"""Calibration: Soloff-type polynomial mapping from target coordinates to image positions, and the
lattice finding that fits it from one image of a regular square dot grid. Arrays in, arrays out (the
mapping file is plain data, :func:`mapping_to_dict`; reading and writing it is the CLI's)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from synthbos import SynthbosError

__all__ = [
    "MAPPING_FORMAT",
    "GridCalibration",
    "SoloffMapping",
    "calibrate_grid",
    "detect_dots",
    "fit_soloff",
    "index_lattice",
    "lattice_vectors",
    "mapping_from_dict",
    "mapping_to_dict",
]


#: Highest polynomial degree of a mapping (a cubic is the usual one; higher ones only fit noise).
MAX_ORDER = 5


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
        raise SynthbosError(f"calibration needs two Nx2 position arrays of one shape, got {t.shape} and {p.shape}")
    if not (np.isfinite(t).all() and np.isfinite(p).all()):
        raise SynthbosError("calibration correspondences contain non-finite values")
    n_terms = len(_terms(order))
    if len(t) < n_terms:
        raise SynthbosError(f"an order-{order} calibration needs at least {n_terms} correspondences, got {len(t)}")
    centre = 0.5 * (t.min(axis=0) + t.max(axis=0))
    scale = 0.5 * (t.max(axis=0) - t.min(axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    A = _design(t, centre, scale, order)
    coef, *_ = np.linalg.lstsq(A, p, rcond=None)
    rms = float(np.sqrt(np.mean(np.sum((A @ coef - p) ** 2, axis=1))))
    return SoloffMapping(order=order, coef=coef, centre=centre, scale=scale, rms=rms)


# --- mapping as plain data ---------------------------------------------------------------------------

MAPPING_FORMAT = "synthbos-soloff-mapping"


def mapping_to_dict(mapping, **extra):
    """A :class:`SoloffMapping` as JSON-ready plain data (the mapping file's content).

    Layout: ``{"format": "synthbos-soloff-mapping", "version": 1, "order": n, "terms": [[i, j], ...],
    "coef_x": [...], "coef_y": [...], "centre": [cx, cy], "scale": [sx, sy], "rms_px": r, ...extra}``:
    image ``x = sum_k coef_x[k] u^i_k v^j_k`` (``y`` likewise) with ``u = (X - cx) / sx``,
    ``v = (Y - cy) / sy`` for target coordinates ``(X, Y)``; ``extra`` keys (units, spacing, residuals)
    are stored alongside.
    """
    return {
        "format": MAPPING_FORMAT,
        "version": 1,
        "order": int(mapping.order),
        "terms": [list(t) for t in _terms(mapping.order)],
        "coef_x": [float(c) for c in mapping.coef[:, 0]],
        "coef_y": [float(c) for c in mapping.coef[:, 1]],
        "centre": [float(c) for c in mapping.centre],
        "scale": [float(c) for c in mapping.scale],
        "rms_px": float(mapping.rms),
        **extra,
    }


def mapping_from_dict(data):
    """Inverse of :func:`mapping_to_dict`; raises :class:`synthbos.SynthbosError` on anything malformed."""
    if not isinstance(data, dict) or data.get("format") != MAPPING_FORMAT:
        raise SynthbosError(f'not a calibration mapping (expected "format": "{MAPPING_FORMAT}")')
    try:
        order = int(data["order"])
        cx = np.asarray(data["coef_x"], dtype=np.float64).ravel()
        cy = np.asarray(data["coef_y"], dtype=np.float64).ravel()
        centre = np.array(data["centre"], dtype=np.float64).reshape(2)
        scale = np.array(data["scale"], dtype=np.float64).reshape(2)
        rms = float(data.get("rms_px", np.nan))
    except (KeyError, TypeError, ValueError, OverflowError) as err:
        raise SynthbosError(f"calibration mapping is malformed: {err!s}") from None
    if not 1 <= order <= MAX_ORDER:
        raise SynthbosError(f"calibration mapping order must be 1 to {MAX_ORDER}, got {order}")
    if not (len(cx) == len(cy) == len(_terms(order))):
        raise SynthbosError(f"calibration mapping of order {order} needs {len(_terms(order))} coefficients per axis")
    try:
        terms = [list(t) for t in data.get("terms", _terms(order))]
    except TypeError:
        terms = None
    if terms != [list(t) for t in _terms(order)]:
        raise SynthbosError("calibration mapping lists its polynomial terms in an unknown order")
    coef = np.stack([cx, cy], axis=1)
    if not (np.isfinite(coef).all() and np.isfinite(centre).all() and np.isfinite(scale).all() and (scale > 0).all()):
        raise SynthbosError("calibration mapping holds non-finite coefficients or a non-positive scale")
    return SoloffMapping(order=order, coef=coef, centre=centre, scale=scale, rms=rms)


# --- regular grid targets ----------------------------------------------------------------------------


def detect_dots(image, *, threshold=None, min_area=3):
    """Centroids of the bright blobs of an image (calibration dots).

    Parameters
    ----------
    image : (H, W) array
    threshold : float, optional
        Intensity above which a pixel belongs to a dot; by default half way from the median (background)
        to the 99.5th percentile.
    min_area : int, keyword-only
        Smaller blobs (noise) are dropped.

    Returns
    -------
    xy : (N, 2) float array
        Centroids (x = column, y = row) of the intensity above the background (the median of the pixels
        more than two pixels from any blob) over each blob grown by two pixels.
    touches_edge : (N,) bool array
        The blob reaches the image's outer pixels (its centroid is then biased).
    """
    a = np.asarray(image, dtype=np.float64)
    if threshold is None:
        med = float(np.median(a))
        threshold = med + 0.5 * (float(np.percentile(a, 99.5)) - med)
    labels, n = ndimage.label(a > threshold, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    index = np.arange(1, n + 1)
    area = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    # Weight the intensity above the background over each blob grown by two pixels (the dot's tails),
    # where no other blob is nearer: far less pixel-locking than a centroid of the thresholded pixels.
    dist, (ir, ic) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    grown = np.where(dist <= 2.0, labels[ir, ic], 0)
    background = float(np.median(a[grown == 0])) if (grown == 0).any() else float(np.median(a))
    w = np.where(grown > 0, np.maximum(a - background, 0.0), 0.0)
    mass = ndimage.sum_labels(w, grown, index)
    rr, cc = np.indices(a.shape)
    x = ndimage.sum_labels(w * cc, grown, index) / np.where(mass > 0, mass, 1.0)
    y = ndimage.sum_labels(w * rr, grown, index) / np.where(mass > 0, mass, 1.0)
    area = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    border = np.zeros_like(labels, dtype=bool)
    border[[0, -1], :] = True
    border[:, [0, -1]] = True
    edge = np.zeros(n + 1, dtype=bool)
    edge[np.unique(grown[border])] = True
    keep = (area >= min_area) & (mass > 0)
    return np.stack([x, y], axis=1)[keep], edge[1:][keep]


def lattice_vectors(xy):
    """The two primitive vectors of a (distorted) square lattice of points, from their neighbours.

    Parameters
    ----------
    xy : (N, 2) array
        Dot positions, N >= 5.

    Returns
    -------
    a, b : (2,) arrays
        The most common vector from a dot to one of its four nearest neighbours (``a``, the one closer
        to the image's +x direction, with positive x) and the most common one not parallel to it
        (``b``, with positive y); None, None if the points show no lattice.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 5:
        return None, None
    dist, idx = cKDTree(xy).query(xy, k=5)
    vec = (xy[idx[:, 1:]] - xy[:, None, :]).reshape(-1, 2)
    spacing = float(np.median(dist[:, 1]))
    vec = vec[np.hypot(*vec.T) < 1.5 * spacing]
    tol = 0.2 * spacing
    tree = cKDTree(vec)
    count = np.array([len(c) for c in tree.query_ball_point(vec, tol)])

    def mode(cand):
        if not cand.any():
            return None
        i = np.flatnonzero(cand)[np.argmax(count[cand])]
        near = np.hypot(*(vec - vec[i]).T) < tol
        return np.median(vec[near], axis=0)

    a = mode(np.ones(len(vec), dtype=bool))
    if a is None:
        return None, None
    cross = np.abs(a[0] * vec[:, 1] - a[1] * vec[:, 0]) / (np.hypot(*a) * np.hypot(*vec.T) + 1e-300)
    b = mode(cross > 0.7)  # more than ~45 degrees from a
    if b is None:
        return None, None
    if abs(b[0]) / np.hypot(*b) > abs(a[0]) / np.hypot(*a):
        a, b = b, a
    a = a if a[0] > 0 else -a
    b = b if b[1] > 0 else -b
    return a, b


def index_lattice(xy, *, origin_xy=None, tolerance=0.3):
    """Integer lattice coordinates of the dots of a (distorted) square grid, grown from the centre.

    Parameters
    ----------
    xy : (N, 2) array
        Dot positions in the image.
    origin_xy : (2,) array, optional
        The dot nearest this point gets index (0, 0); default: the centroid of all dots.
    tolerance : float
        A neighbour is accepted within this fraction of the lattice spacing of where the grid predicts it.

    Returns
    -------
    ij : (N, 2) int array
        Lattice coordinates along ``a`` (i) and ``b`` (j) of :func:`lattice_vectors`.
    indexed : (N,) bool array
        False for dots the growth did not reach or found inconsistent (spurious blobs, stray dots).

    Notes
    -----
    Breadth-first growth: from each indexed dot, its four lattice neighbours are predicted with the
    local lattice vector (the vector from the opposite neighbour where that one is indexed, else the
    global one), so smooth distortions are followed; a blob claimed with two different indices is left
    out.
    """
    xy = np.asarray(xy, dtype=np.float64)
    n = len(xy)
    ij = np.zeros((n, 2), dtype=np.int64)
    indexed = np.zeros(n, dtype=bool)
    a, b = lattice_vectors(xy)
    if a is None:
        return ij, indexed
    spacing = min(np.hypot(*a), np.hypot(*b))
    origin = xy.mean(axis=0) if origin_xy is None else np.asarray(origin_xy, dtype=np.float64)
    tree = cKDTree(xy)
    start = int(tree.query(origin)[1])
    r = int(np.ptp(xy, axis=0).max() / spacing * 1.5) + 3  # index range -r..r
    node = np.full((2 * r + 1, 2 * r + 1), -1, dtype=np.int64)
    node[r, r] = start
    indexed[start] = True
    frontier = np.array([start])
    steps = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]])
    glob = np.array([a, -a, b, -b])
    while frontier.size:
        src = np.repeat(frontier, 4)
        step = np.tile(steps, (len(frontier), 1))
        gvec = np.tile(glob, (len(frontier), 1))
        back = ij[src] - step + r
        prev = node[back[:, 0], back[:, 1]]
        local = np.where((prev >= 0)[:, None], xy[src] - xy[np.maximum(prev, 0)], gvec)
        dist, hit = tree.query(xy[src] + local)
        target = ij[src] + step
        ok = (dist < tolerance * spacing) & (hit < n)
        ok &= (np.abs(target) < r).all(axis=1)
        src, hit, target = src[ok], hit[ok], target[ok]
        # a blob already indexed elsewhere, or claimed with two indices now, is inconsistent: skip it
        fresh = ~indexed[hit]
        hit, target = hit[fresh], target[fresh]
        key = target[:, 0] * (2 * r + 1) + target[:, 1]
        order = np.lexsort((key, hit))
        hit, key, target = hit[order], key[order], target[order]
        first = np.r_[True, hit[1:] != hit[:-1]]
        start_of = np.flatnonzero(first)
        groups = np.split(np.arange(len(hit)), start_of[1:]) if len(hit) else []
        good = [g[0] for g in groups if (key[g] == key[g[0]]).all()]
        good = np.array(good, dtype=np.int64)
        if good.size:
            # a lattice node claimed by two blobs keeps neither
            nk, nc = np.unique(key[good], return_counts=True)
            good = good[np.isin(key[good], nk[nc == 1])]
            good = good[node[target[good, 0] + r, target[good, 1] + r] < 0]
        if not good.size:
            break
        new = hit[good]
        ij[new] = target[good]
        indexed[new] = True
        node[target[good, 0] + r, target[good, 1] + r] = new
        frontier = new
    return ij, indexed


@dataclass(frozen=True)
class GridCalibration:
    """Result of :func:`calibrate_grid`.

    Attributes
    ----------
    mapping : SoloffMapping
        Target (mm) -> image (px).
    target_xy : (M, 2) array
        Target positions (mm) of every grid node predicted inside the image: ``spacing`` times its lattice
        coordinates, node (0, 0) being the dot nearest the image centre (or ``origin_xy``), x along the
        lattice direction nearest the image's +x (columns), y along the one nearest +y (rows, downwards).
    image_xy : (M, 2) array
        Their predicted image positions (px).
    detected : (M,) bool array
        The node's dot was detected and used in the fit.
    residual_rms, residual_max : float
        Distance (px) between the detected dots used in the fit and the mapping.
    n_detected : int
        Dots detected in the image.
    """

    mapping: SoloffMapping
    target_xy: np.ndarray
    image_xy: np.ndarray
    detected: np.ndarray
    residual_rms: float
    residual_max: float
    n_detected: int


def calibrate_grid(image, spacing, *, order=3, origin_xy=None, threshold=None, extrapolate=1):
    """Calibrate from an image of a regular square dot grid: find the lattice, fit the mapping, predict
    every dot.

    Parameters
    ----------
    image : (H, W) array
        Bright dots on a dark background (invert dark-dot images first).
    spacing : float
        Grid spacing on the target (mm, or any unit: the mapping's target unit).
    order : int, keyword-only
        Soloff polynomial degree (:func:`fit_soloff`).
    origin_xy : (2,) array, optional
        Image point whose nearest dot is the target origin; the image centre by default.
    threshold : float, optional
        Dot detection threshold (:func:`detect_dots`).
    extrapolate : int, keyword-only
        Nodes up to this many rows/columns beyond the indexed ones are predicted too (dots cut by the
        image edge, or too faint to detect), if they fall inside the image.

    Returns
    -------
    GridCalibration

    Raises
    ------
    synthbos.SynthbosError
        No lattice found (too few dots, or fewer than half of them on one regular grid).

    Notes
    -----
    Dots are found by thresholding (:func:`detect_dots`), the lattice vectors from the nearest-neighbour
    vectors (:func:`lattice_vectors`), the dots indexed by growing the lattice from the centre
    (:func:`index_lattice`); then the mapping is fitted by least squares (Soloff, Adrian and Liu 1997),
    every detected dot is re-assigned to its nearest predicted node, dots further than a quarter spacing
    from it or more than 4 robust standard deviations off the fit are dropped, and the fit is repeated.
    Blobs touching the image's outer pixels are not used (their centroids are biased).
    """
    a = np.asarray(image, dtype=np.float64)
    if a.ndim != 2:
        raise SynthbosError(f"calibration image must be 2-D, got shape {a.shape}")
    if not (np.isfinite(spacing) and spacing > 0):
        raise SynthbosError(f"grid spacing must be a positive number, got {spacing!r}")
    h, w = a.shape
    xy, edge = detect_dots(a, threshold=threshold)
    n_det = len(xy)
    n_terms = len(_terms(order))
    origin = np.array([(w - 1) / 2.0, (h - 1) / 2.0]) if origin_xy is None else np.asarray(origin_xy, float)
    use = xy[~edge]
    ij, ok = index_lattice(use, origin_xy=origin)
    if ok.sum() < max(n_terms + 4, 16) or ok.sum() < 0.5 * len(use):
        raise SynthbosError(
            f"no regular dot grid found in the calibration image ({n_det} blobs detected, "
            f"{int(ok.sum())} on one lattice)"
        )
    ij, pts = ij[ok], use[ok]
    lo, hi = ij.min(axis=0) - extrapolate, ij.max(axis=0) + extrapolate
    gi, gj = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    nodes = np.stack([gi.ravel(), gj.ravel()], axis=1)
    for _ in range(3):
        mapping = fit_soloff(ij * float(spacing), pts, order=order)
        pred = mapping(nodes * float(spacing))
        step = float(np.median(np.hypot(*np.diff(mapping(np.array([[0.0, 0.0], [spacing, 0.0]])), axis=0).T)))
        dist, k = cKDTree(pred).query(use)
        near = dist < 0.25 * step
        # one blob per node: the nearest
        order_ = np.lexsort((dist, k))
        first = np.r_[True, k[order_][1:] != k[order_][:-1]]
        keep = np.zeros(len(use), dtype=bool)
        keep[order_[first]] = True
        near &= keep
        robust = 1.4826 * np.median(dist[near]) + 1e-3
        near &= dist < max(4.0 * robust, 0.05)
        ij, pts = nodes[k[near]], use[near]
        if len(pts) < n_terms:
            raise SynthbosError("no regular dot grid found in the calibration image (the mapping fit failed)")
    mapping = fit_soloff(ij * float(spacing), pts, order=order)
    res = np.hypot(*(mapping(ij * float(spacing)) - pts).T)
    pred = mapping(nodes * float(spacing))
    inside = (pred[:, 0] >= 0) & (pred[:, 0] <= w - 1) & (pred[:, 1] >= 0) & (pred[:, 1] <= h - 1)
    used = np.zeros(len(nodes), dtype=bool)
    used[np.ravel_multi_index((ij - lo).T, (hi - lo + 1))] = True
    return GridCalibration(
        mapping=mapping,
        target_xy=nodes[inside] * float(spacing),
        image_xy=pred[inside],
        detected=used[inside],
        residual_rms=float(np.sqrt(np.mean(res**2))),
        residual_max=float(res.max()),
        n_detected=n_det,
    )
