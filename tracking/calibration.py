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
    "POLARITIES",
    "GridCalibration",
    "SoloffMapping",
    "calibrate_grid",
    "detect_dots",
    "dot_polarity",
    "fit_soloff",
    "index_lattice",
    "lattice_vectors",
    "local_contrast",
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

#: Dot polarities of a grid image: found from the image, bright dots on dark, dark dots on bright.
POLARITIES = ("auto", "bright", "dark")
#: Side of the local contrast window, in grid pitches: each window holds dots and background.
WINDOW_PITCHES = 4.0
#: Floor of the local standard deviation, in units of the pixel noise (:func:`local_contrast`).
NOISE_FLOOR = 2.0
#: Largest |cosine| of the angle between the grid's two directions in the image (72.5 to 107.5 degrees).
SQUARE_COS = 0.3
#: Largest ratio of the image steps along the grid's two directions.
SQUARE_RATIO = 2.0
#: Most rounds of fitting the mapping and re-assigning the blobs (:func:`calibrate_grid`).
MAX_REFITS = 60
#: Fewest dots a grid calibration accepts on one lattice.
MIN_LATTICE_DOTS = 16
#: Dots nearest the origin whose neighbour vectors give the first lattice vectors (:func:`index_lattice`).
CENTRAL_DOTS = 1000
#: Smallest share of the detected blobs (away from the image edge) that the lattice must hold.
MIN_LATTICE_SHARE = 0.3


def _sample(a, n=512):
    """Every k-th row and column of an image, so that about ``n`` x ``n`` pixels are left (for statistics)."""
    return a[:: max(1, a.shape[0] // n), :: max(1, a.shape[1] // n)]


def _noise(a):
    """Standard deviation of the pixel noise, from the lower quartile of the differences of horizontal and
    vertical neighbours (dots' slopes sit in the upper quantiles)."""
    d = np.concatenate([np.abs(np.diff(_sample(a, 1024), axis=k)).ravel() for k in (0, 1)])
    # |difference| of two N(0, s^2) pixels: its quartile is 0.3186 sqrt(2) s
    return float(np.percentile(d, 25)) / (0.3186 * np.sqrt(2.0))


def local_contrast(image, window, *, with_texture=False):
    """The image in units of its local contrast: ``(a - local mean) / local standard deviation``.

    Parameters
    ----------
    image : (H, W) array
    window : int
        Side (px) of the square window of the local mean and standard deviation: a few dot pitches.
    with_texture : bool, keyword-only
        Also return where the local standard deviation is above its floor (the textured part).

    Returns
    -------
    (H, W) float array, or None for an image without contrast (every pixel alike)
        With ``with_texture``, a pair: that array and an (H, W) bool array.

    Notes
    -----
    Both moments come from box filters (:func:`scipy.ndimage.uniform_filter`), so illumination that
    changes over more than a window (a dim centre, vignetting) and a contrast that changes with it are
    taken out. The standard deviation is floored at ``NOISE_FLOOR`` times the pixel noise (from the
    differences of neighbouring pixels), so that flat parts of the image, beyond the grid, keep their
    noise well below the dots' contrast.

    Examples
    --------
    >>> z = local_contrast(np.tile([0.0, 0.0, 0.0, 4.0], (8, 2)), 4)
    >>> bool(z[0, 3] > 1.5 and z[0, 4] < -0.5)
    True
    """
    a = np.asarray(image, dtype=np.float64)
    if a.size == 0 or a.min() == a.max():
        return None
    a = a - np.median(_sample(a))
    mean = ndimage.uniform_filter(a, window, mode="reflect")
    var = ndimage.uniform_filter(a * a, window, mode="reflect")
    var -= mean * mean
    # a flat part of the image (beyond the grid) stays flat: its noise is not blown up to unit contrast
    floor = max(NOISE_FLOOR * _noise(a), 0.01 * float(np.sqrt(np.percentile(_sample(var), 90))), 1e-6 * np.ptp(a))
    textured = var > floor**2
    np.maximum(var, floor**2, out=var)
    a -= mean
    del mean
    a /= np.sqrt(var, out=var)
    return (a, textured) if with_texture else a


def _otsu(values, bins=256):
    """The level that best splits ``values`` into two classes (Otsu 1979), between the 0.5 and 99.9 % points."""
    lo, hi = np.percentile(values, [0.5, 99.9])
    if not hi > lo:
        return float(hi)
    hist, edges = np.histogram(values, bins, range=(lo, hi))
    centre = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist, dtype=np.float64)
    m0 = np.cumsum(hist * centre)
    w1, m1 = w0[-1] - w0, m0[-1] - m0
    with np.errstate(divide="ignore", invalid="ignore"):
        between = w0 * w1 * (m0 / w0 - m1 / w1) ** 2
    return float(centre[np.nanargmax(np.where(np.isfinite(between), between, np.nan))])


def _blobs(z, threshold, min_area):
    """Centroids and edge flags of the blobs of ``z`` above ``threshold`` (see :func:`detect_dots`)."""
    above = z > threshold
    labels, n = ndimage.label(above)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    index = np.arange(1, n + 1)
    area = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    base = float(np.median(_sample(z)[~_sample(above)])) if not above.all() else float(z.min())
    del above
    # each blob grown by two pixels (the dot's tails) where no other blob is nearer; weights are the
    # contrast above the background's, which takes out pixel locking of thresholded centroids
    dist, near = ndimage.distance_transform_edt(labels == 0, return_distances=True, return_indices=True)
    grown = labels[near[0], near[1]]
    del near
    grown[dist > 2.0] = 0
    del dist, labels
    w = np.where(grown > 0, np.maximum(z - base, 0.0), 0.0)
    mass = ndimage.sum_labels(w, grown, index)
    com = np.array(ndimage.center_of_mass(w, grown, index), dtype=np.float64).reshape(-1, 2)
    edge = np.zeros(n + 1, dtype=bool)
    for side in (grown[0], grown[-1], grown[:, 0], grown[:, -1]):
        edge[side] = True
    keep = (area >= min_area) & (mass > 0)
    return com[keep][:, ::-1].copy(), edge[1:][keep]


def _pitch(xy):
    """Median nearest-neighbour distance of points (0 for fewer than two)."""
    if len(xy) < 2:
        return 0.0
    return float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1]))


def _first_window(shape):
    return int(np.clip(min(shape) // 16, 9, 129)) | 1


def detect_dots(image, *, dark=False, window=None, threshold=None, min_area=3):
    """Centroids of the dots of a calibration grid image, found against the local contrast.

    Parameters
    ----------
    image : (H, W) array
    dark : bool, keyword-only
        The dots are darker than the background (the image is searched upside down).
    window : int, optional
        Side (px) of the local contrast window (:func:`local_contrast`); by default ``WINDOW_PITCHES``
        times the dot pitch, found by detecting with a first window of a sixteenth of the image and
        measuring the dots' nearest-neighbour distance (repeated until the window settles).
    threshold : float, optional
        Level in local contrast units (standard deviations above the local mean) above which a pixel
        belongs to a dot; by default Otsu's level of the contrast image where it is textured (its local
        standard deviation above the floor of :func:`local_contrast`).
    min_area : int, keyword-only
        Smaller blobs (noise) are dropped.

    Returns
    -------
    xy : (N, 2) float array
        Centroids (x = column, y = row) of the contrast above the background's over each blob grown by
        two pixels.
    touches_edge : (N,) bool array
        The blob reaches the image's outer pixels (its centroid is then biased).

    Examples
    --------
    >>> from synthbos.raytrace.dots import draw_dots
    >>> truth = np.stack(np.meshgrid(np.arange(8.0, 120, 10), np.arange(8.0, 90, 10)), -1).reshape(-1, 2)
    >>> xy, edge = detect_dots(draw_dots((96, 128), truth, 3.0))
    >>> len(xy), float(np.abs(np.sort(xy, axis=0) - np.sort(truth, axis=0)).max()) < 0.1
    (108, True)
    """
    a = np.asarray(image, dtype=np.float64)
    windows = [window] if window is not None else [_first_window(a.shape)]
    xy, edge = np.zeros((0, 2)), np.zeros(0, dtype=bool)
    while len(windows) <= 3:
        if a.min() == a.max():
            break
        z, textured = local_contrast(a, windows[-1], with_texture=True)
        if dark:
            np.negative(z, out=z)
        if threshold is None:  # Otsu's level of the textured part: the flat part holds only noise
            level = _otsu(_sample(z)[_sample(textured)]) if _sample(textured).any() else np.inf
        else:
            level = threshold
        del textured
        xy, edge = _blobs(z, level, min_area)
        del z
        if window is not None:
            break
        pitch = _pitch(xy[~edge])
        new = int(np.clip(round(WINDOW_PITCHES * pitch), 7, min(a.shape))) | 1
        if pitch == 0 or abs(new - windows[-1]) <= 0.2 * windows[-1] or new in windows:
            break
        windows.append(new)
    return xy, edge


def dot_polarity(image, *, window=None):
    """Whether a grid image's dots are dark, from the skewness of its local contrast.

    Parameters
    ----------
    image : (H, W) array
    window : int, optional
        Local contrast window (px); a sixteenth of the image by default.

    Returns
    -------
    dark : bool
        True when the contrast is skewed to the dark side (small dark dots on a bright background).
    skewness : float
        Third moment of the local contrast (0 for a blank image).

    Examples
    --------
    >>> from synthbos.raytrace.dots import draw_dots
    >>> truth = np.stack(np.meshgrid(np.arange(8.0, 120, 10), np.arange(8.0, 90, 10)), -1).reshape(-1, 2)
    >>> dot_polarity(1.0 - draw_dots((96, 128), truth, 3.0))[0]
    True
    """
    a = np.asarray(image, dtype=np.float64)
    z = local_contrast(a, window or _first_window(a.shape))
    if z is None:
        return False, 0.0
    z = _sample(z)
    skew = float(np.mean(z * z * z))
    return skew < 0, skew


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
        (``b``, with positive y); None, None if the points show no lattice (fewer than half of the
        neighbour vectors near one of ``+-a``, ``+-b``).

    Notes
    -----
    The neighbour vectors (and their negatives) are binned in a 2-D histogram a twentieth of the
    spacing fine, smoothed; its highest bin, and the highest at more than 45 degrees from it, are
    refined to the median of the vectors within a quarter spacing. Memory and time are linear in N.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 5:
        return None, None
    dist, idx = cKDTree(xy).query(xy, k=5)
    spacing = float(np.median(dist[:, 1]))
    if not spacing > 0:
        return None, None
    vec = (xy[idx[:, 1:]] - xy[:, None, :]).reshape(-1, 2)
    vec = vec[(np.hypot(*vec.T) < 1.6 * spacing) & (np.hypot(*vec.T) > 0.4 * spacing)]
    vec = np.concatenate([vec, -vec])
    half, bins = 1.6 * spacing, 64
    hist, edges, _ = np.histogram2d(vec[:, 0], vec[:, 1], bins=bins, range=[[-half, half], [-half, half]])
    hist = ndimage.gaussian_filter(hist, 1.0)
    centre = 0.5 * (edges[1:] + edges[:-1])
    cx, cy = np.meshgrid(centre, centre, indexing="ij")
    tol = 0.25 * spacing

    def refine(i):
        peak = np.array([cx.ravel()[i], cy.ravel()[i]])
        near = np.hypot(*(vec - peak).T) < tol
        return np.median(vec[near], axis=0), int(near.sum())

    a, n_a = refine(int(np.argmax(hist)))
    sine = np.abs(a[0] * cy - a[1] * cx) / (np.hypot(*a) * np.hypot(cx, cy) + 1e-300)
    b, n_b = refine(int(np.argmax(np.where(sine > 0.7, hist, -1.0))))
    if 2 * (n_a + n_b) < 0.5 * len(vec) or abs(a[0] * b[1] - a[1] * b[0]) < 0.5 * spacing**2:
        return None, None
    if abs(b[0]) / np.hypot(*b) > abs(a[0]) / np.hypot(*a):
        a, b = b, a
    a = a if a[0] > 0 else -a
    b = b if b[1] > 0 else -b
    return a, b


_STEPS = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [2, 0], [-2, 0], [0, 2], [0, -2]])


class _Lattice:
    """Lattice indices grown from one seed dot; ``node`` maps index + ``r`` to the dot (-1: none)."""

    def __init__(self, xy, tree, a, b, r):
        n = len(xy)
        self.xy, self.tree, self.r = xy, tree, r
        self.ij = np.zeros((n, 2), dtype=np.int64)
        self.indexed = np.zeros(n, dtype=bool)
        self.local = np.empty((n, 2, 2))  # the lattice vectors a, b at each dot
        self.local[:] = [a, b]
        self.node = np.full((2 * r + 1, 2 * r + 1), -1, dtype=np.int64)

    def at(self, ij):
        return self.node[ij[:, 0] + self.r, ij[:, 1] + self.r]

    def add(self, new, ij, src):
        self.ij[new] = ij
        self.indexed[new] = True
        self.node[ij[:, 0] + self.r, ij[:, 1] + self.r] = new
        if src is not None:
            self.local[new] = self.local[src]
        # the local vectors measured from indexed neighbours, where there are any
        for k, step in enumerate(np.eye(2, dtype=np.int64)):
            fwd, back = self.at(ij + step), self.at(ij - step)
            est = np.zeros((len(new), 2))
            cnt = (fwd >= 0).astype(float) + (back >= 0)
            est += np.where((fwd >= 0)[:, None], self.xy[np.maximum(fwd, 0)] - self.xy[new], 0.0)
            est += np.where((back >= 0)[:, None], self.xy[new] - self.xy[np.maximum(back, 0)], 0.0)
            have = cnt > 0
            self.local[new[have], k] = est[have] / cnt[have, None]

    def wave(self, frontier, tolerance):
        """Index the dots one or two lattice steps from ``frontier``; returns the new ones."""
        src = np.repeat(frontier, len(_STEPS))
        step = np.tile(_STEPS, (len(frontier), 1))
        target = self.ij[src] + step
        ok = (np.abs(target) < self.r - 1).all(axis=1)
        src, step, target = src[ok], step[ok], target[ok]
        ok = self.at(target) < 0
        src, step, target = src[ok], step[ok], target[ok]
        loc = self.local[src]
        pred = self.xy[src] + step[:, :1] * loc[:, 0] + step[:, 1:] * loc[:, 1]
        tol = tolerance * np.minimum(np.hypot(*loc[:, 0].T), np.hypot(*loc[:, 1].T))
        dist, hit = self.tree.query(pred, distance_upper_bound=float(tol.max(initial=0.0)))
        ok = dist < tol
        src, target, hit = src[ok], target[ok], hit[ok]
        ok = ~self.indexed[hit]
        src, target, hit = src[ok], target[ok], hit[ok]
        if not len(hit):
            return hit
        # a blob claimed as two nodes, or a node claimed by two blobs: neither is taken
        key = (target[:, 0] + self.r) * (2 * self.r + 1) + target[:, 1] + self.r
        pairs = np.unique(np.stack([hit, key], axis=1), axis=0)
        bad_hit = np.unique(pairs[:, 0], return_counts=True)
        bad_key = np.unique(pairs[:, 1], return_counts=True)
        ok = ~np.isin(hit, bad_hit[0][bad_hit[1] > 1]) & ~np.isin(key, bad_key[0][bad_key[1] > 1])
        src, target, hit = src[ok], target[ok], hit[ok]
        hit, first = np.unique(hit, return_index=True)
        self.add(hit, target[first], src[first])
        return hit

    def grow(self, seed, tolerance):
        self.add(np.array([seed]), np.zeros((1, 2), dtype=np.int64), None)
        frontier = np.array([seed])
        while frontier.size:
            frontier = self.wave(frontier, tolerance)
        return self


def _seeds(xy, tree, a, b, tolerance, origin, rng):
    """Seed dots for the growth: those with all four lattice neighbours where ``a``, ``b`` put them, the
    one nearest ``origin`` first, then the others in random order."""
    tol = tolerance * min(np.hypot(*a), np.hypot(*b))
    good = np.ones(len(xy), dtype=bool)
    for d in (a, -a, b, -b):
        good &= tree.query(xy + d, distance_upper_bound=tol)[0] < tol
    cand = np.flatnonzero(good) if good.any() else np.arange(len(xy))
    first = cand[np.argmin(np.hypot(*(xy[cand] - origin).T))]
    rest = rng.permutation(cand[cand != first])
    return np.r_[first, rest], int(good.sum())


def index_lattice(xy, *, origin_xy=None, tolerance=0.3, max_seeds=8, seed=0):
    """Integer lattice coordinates of the dots of a (distorted) square grid, grown from several seeds.

    Parameters
    ----------
    xy : (N, 2) array
        Dot positions in the image.
    origin_xy : (2,) array, optional
        The indexed dot nearest this point gets index (0, 0); default: the centroid of all dots.
    tolerance : float
        A neighbour is accepted within this fraction of the local lattice spacing of where the grid
        predicts it.
    max_seeds : int, keyword-only
        Growths tried, each from a dot not reached by the earlier ones, until one reaches half of the
        dots whose four neighbours sit where the lattice vectors put them.
    seed : int, keyword-only
        Seeds the random order of the seed dots after the first (the one nearest ``origin_xy``).

    Returns
    -------
    ij : (N, 2) int array
        Lattice coordinates along ``a`` (i) and ``b`` (j) of :func:`lattice_vectors`.
    indexed : (N,) bool array
        False for dots the largest growth did not reach or found inconsistent (spurious blobs).

    Notes
    -----
    The lattice vectors are first measured (:func:`lattice_vectors`) on the ``CENTRAL_DOTS`` dots nearest
    ``origin_xy``, where a lens distorts least, else on all. Each growth proceeds in waves: from each dot
    indexed in the last wave, the dots one and two lattice steps away are predicted with the lattice
    vectors at that dot (measured from its indexed neighbours, else inherited from the dot it was reached
    from), so lens distortion and perspective are followed and single missing dots are stepped over; a
    blob claimed as two nodes, or a node claimed by two blobs, is left out. Memory and time are linear in
    the number of dots.

    Examples
    --------
    >>> ij = np.stack(np.meshgrid(np.arange(6), np.arange(5), indexing="ij"), -1).reshape(-1, 2)
    >>> got, ok = index_lattice(ij * 10.0 + 3.0, origin_xy=(3.0, 3.0))
    >>> bool(ok.all() and (got == ij).all())
    True
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    n = len(xy)
    best = _Lattice(xy, None, np.zeros(2), np.zeros(2), 1)
    if n < 5:
        return best.ij, best.indexed
    tree = cKDTree(xy)
    origin = xy.mean(axis=0) if origin_xy is None else np.asarray(origin_xy, dtype=np.float64)
    # the lattice vectors where distortion has changed them least: near the origin, then over all dots
    a, b = lattice_vectors(xy[tree.query(origin, k=min(n, CENTRAL_DOTS))[1]])
    if a is None and n > CENTRAL_DOTS:
        a, b = lattice_vectors(xy)
    if a is None:
        return best.ij, best.indexed
    spacing = min(np.hypot(*a), np.hypot(*b))
    r = int(np.ptp(xy, axis=0).max() / spacing * 1.5) + 4
    seeds, n_good = _seeds(xy, tree, a, b, tolerance, origin, np.random.default_rng(seed))
    reached = np.zeros(n, dtype=bool)
    tries = 0
    for s in seeds:
        if reached[s]:
            continue
        grown = _Lattice(xy, tree, a, b, r).grow(s, tolerance)
        reached |= grown.indexed
        if grown.indexed.sum() > best.indexed.sum():
            best = grown
        tries += 1
        if best.indexed.sum() >= 0.5 * n_good or tries >= max_seeds:
            break
    ij, ok = best.ij, best.indexed
    zero = np.flatnonzero(ok)[np.argmin(np.hypot(*(xy[ok] - origin).T))]
    return np.where(ok[:, None], ij - ij[zero], 0), ok


@dataclass(frozen=True)
class GridCalibration:
    """Result of :func:`calibrate_grid`.

    Attributes
    ----------
    mapping : SoloffMapping
        Target (mm) -> image (px).
    target_xy : (M, 2) array
        Target positions (mm) of every grid node predicted inside the image: ``spacing`` times its lattice
        coordinates, node (0, 0) being the grid node nearest the image centre (or ``origin_xy``), x along
        the lattice direction nearest the image's +x (columns), y along the one nearest +y (rows, downwards).
    image_xy : (M, 2) array
        Their predicted image positions (px).
    detected : (M,) bool array
        The node's dot was detected and used in the fit.
    residual_rms, residual_max : float
        Distance (px) between the detected dots used in the fit and the mapping.
    n_detected : int
        Blobs detected in the image (of the polarity used).
    dots_xy : (K, 2) array
        The detected dots used in the fit (px).
    dots_ij : (K, 2) int array
        Their lattice coordinates (``target = spacing * ij``).
    dark : bool
        The dots were found dark on a bright background.
    """

    mapping: SoloffMapping
    target_xy: np.ndarray
    image_xy: np.ndarray
    detected: np.ndarray
    residual_rms: float
    residual_max: float
    n_detected: int
    dots_xy: np.ndarray
    dots_ij: np.ndarray
    dark: bool


def _polarities(image, polarity):
    if polarity not in POLARITIES:
        raise SynthbosError(f"grid dot polarity must be one of {', '.join(POLARITIES)}, got {polarity!r}")
    if polarity != "auto":
        return [polarity == "dark"]
    dark, _ = dot_polarity(image)
    return [dark, not dark]


def _find_lattice(image, polarity, threshold, origin, n_min, seed):
    """Dots of the polarity (or polarities) asked for and their lattice indices: the first that holds a grid."""
    tried = []
    for dark in _polarities(image, polarity):
        xy, edge = detect_dots(image, dark=dark, threshold=threshold)
        use = xy[~edge]
        ij, ok = index_lattice(use, origin_xy=origin, seed=seed)
        n_ok = int(ok.sum())
        tried.append(f"{len(xy)} {'dark' if dark else 'bright'} blob{'s' * (len(xy) != 1)}, {n_ok} on one lattice")
        if n_ok >= n_min and n_ok >= MIN_LATTICE_SHARE * len(use):
            return dark, use, ij[ok], use[ok], len(xy)
    raise SynthbosError(f"no regular dot grid found in the calibration image ({'; '.join(tried)}; "
                        f"{n_min}+ needed)")


def _assign(mapping, use, ij, spacing, shape, margin):
    """Every detected dot re-assigned to its nearest node of the fitted grid, over the indexed range
    grown by ``margin`` nodes: dots more than a quarter spacing from their node, or more than 4 robust
    standard deviations off, are left out; one dot per node."""
    lo, hi = ij.min(axis=0) - margin, ij.max(axis=0) + margin
    gi, gj = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    nodes = np.stack([gi.ravel(), gj.ravel()], axis=1)
    pred = mapping(nodes * spacing)
    h, w = shape
    step = float(np.median(cKDTree(pred).query(pred, k=2)[0][:, 1]))
    pad = 2.0 * step
    inside = (pred[:, 0] > -pad) & (pred[:, 0] < w + pad) & (pred[:, 1] > -pad) & (pred[:, 1] < h + pad)
    nodes, pred = nodes[inside], pred[inside]
    dist, k = cKDTree(pred).query(use)
    order_ = np.lexsort((dist, k))
    first = np.zeros(len(use), dtype=bool)
    first[order_[np.r_[True, k[order_][1:] != k[order_][:-1]]]] = True
    near = first & (dist < 0.25 * step)
    if not near.any():
        return ij[:0], use[:0]
    robust = 1.4826 * np.median(dist[near]) + 1e-3
    near &= dist < max(4.0 * robust, 0.05)
    return nodes[k[near]], use[near]


def _refit(use, ij, pts, spacing, order, shape):
    """Fit, re-assign every blob (:func:`_assign`) and fit again until the set settles; where it settles,
    nodes four rows beyond are tried once, to join parts of the grid beyond a gap."""
    margin = 2
    for _ in range(MAX_REFITS):
        mapping = fit_soloff(ij * spacing, pts, order=order)
        new_ij, new_pts = _assign(mapping, use, ij, spacing, shape, margin)
        if len(new_pts) < len(_terms(order)):
            raise SynthbosError("no regular dot grid found in the calibration image (the mapping fit failed)")
        same = len(new_ij) == len(ij) and (new_ij == ij).all() and (new_pts == pts).all()
        ij, pts = new_ij, new_pts
        if same and margin == 4:
            break
        margin = 4 if same else 2
    return ij, pts


def _check_square(mapping, spacing):
    """Refuse a lattice that is no square grid seen by a camera (a hexagonal or a rectangular one): the
    image steps of the two grid directions at node (0, 0) must be within ``SQUARE_COS`` of square and
    within a factor ``SQUARE_RATIO`` of each other in length (a camera tilted by up to 60 degrees)."""
    o, x, y = mapping(np.array([[0.0, 0.0], [spacing, 0.0], [0.0, spacing]]))
    va, vb = x - o, y - o
    la, lb = float(np.hypot(*va)), float(np.hypot(*vb))
    cos = float(va @ vb) / (la * lb)
    if abs(cos) > SQUARE_COS or not 1.0 / SQUARE_RATIO < la / lb < SQUARE_RATIO:
        raise SynthbosError(f"the dots lie on a lattice of {la:.3g} and {lb:.3g} px steps at "
                            f"{np.degrees(np.arccos(cos)):.0f} degrees: not a square grid")


def calibrate_grid(image, spacing, *, order=3, origin_xy=None, threshold=None, extrapolate=1, polarity="auto",
                   seed=0):
    """Calibrate from an image of a regular square dot grid: find the lattice, fit the mapping, predict
    every dot.

    Parameters
    ----------
    image : (H, W) array
        The grid image, bright dots on a dark background or dark dots on a bright one.
    spacing : float
        Grid spacing on the target (mm, or any unit: the mapping's target unit).
    order : int, keyword-only
        Soloff polynomial degree (:func:`fit_soloff`).
    origin_xy : (2,) array, optional
        Image point whose nearest grid node is the target origin; the image centre by default.
    threshold : float, optional
        Dot detection level in local contrast units (:func:`detect_dots`).
    extrapolate : int, keyword-only
        Nodes up to this many rows/columns beyond the indexed ones are predicted too (dots cut by the
        image edge, or too faint to detect), if they fall inside the image.
    polarity : {"auto", "bright", "dark"}, keyword-only
        The dots' polarity; "auto" tries first the one the image's contrast is skewed to
        (:func:`dot_polarity`), then the other.
    seed : int, keyword-only
        Seeds the order of the growth's seed dots (:func:`index_lattice`).

    Returns
    -------
    GridCalibration

    Raises
    ------
    synthbos.SynthbosError
        A blank image, or no lattice found (fewer than ``MIN_LATTICE_DOTS`` dots, or fewer than
        ``MIN_LATTICE_SHARE`` of the blobs, on one regular grid); the message says how many blobs of each
        polarity tried were found and how many sat on one lattice. A lattice that is not square (a
        hexagonal grid: its directions 60 degrees apart) is refused too.

    Notes
    -----
    Dots are found against the local contrast (:func:`detect_dots`), the lattice vectors from the
    nearest-neighbour vectors (:func:`lattice_vectors`), the dots indexed by growing the lattice from
    several seeds (:func:`index_lattice`); then the mapping is fitted by least squares (Soloff, Adrian
    and Liu 1997), every detected dot is re-assigned to its nearest node of the fitted grid, grown two
    nodes past the indexed ones, dots further than a quarter spacing from it or more than 4 robust
    standard deviations off the fit are dropped, and the fit is repeated until the set settles (then
    once more with nodes four rows past the indexed ones), which also joins parts of the grid that the
    growth did not reach, across gaps of up to three missing rows. Blobs touching the image's outer pixels are
    not used (their centroids are biased).
    """
    a = np.asarray(image, dtype=np.float64)
    if a.ndim != 2:
        raise SynthbosError(f"calibration image must be 2-D, got shape {a.shape}")
    if not (np.isfinite(spacing) and spacing > 0):
        raise SynthbosError(f"grid spacing must be a positive number, got {spacing!r}")
    if a.size == 0 or a.min() == a.max():
        what = f"blank (every pixel {a.flat[0]:g})" if a.size else "empty"
        raise SynthbosError(f"the calibration image is {what}: no dot grid to find")
    h, w = a.shape
    spacing = float(spacing)
    n_terms = len(_terms(order))
    origin = np.array([(w - 1) / 2.0, (h - 1) / 2.0]) if origin_xy is None else np.asarray(origin_xy, float)
    dark, use, ij, pts, n_det = _find_lattice(a, polarity, threshold, origin, max(n_terms + 4, MIN_LATTICE_DOTS),
                                              seed)
    ij, pts = _refit(use, ij, pts, spacing, order, a.shape)
    mapping = fit_soloff(ij * spacing, pts, order=order)
    lo, hi = ij.min(axis=0) - extrapolate, ij.max(axis=0) + extrapolate
    gi, gj = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    nodes = np.stack([gi.ravel(), gj.ravel()], axis=1)
    pred = mapping(nodes * spacing)
    # node (0, 0): the one nearest the origin point
    zero = nodes[np.argmin(np.hypot(*(pred - origin).T))]
    ij, nodes = ij - zero, nodes - zero
    mapping = fit_soloff(ij * spacing, pts, order=order)
    _check_square(mapping, spacing)
    res = np.hypot(*(mapping(ij * spacing) - pts).T)
    pred = mapping(nodes * spacing)
    inside = (pred[:, 0] >= 0) & (pred[:, 0] <= w - 1) & (pred[:, 1] >= 0) & (pred[:, 1] <= h - 1)
    used = np.zeros(len(nodes), dtype=bool)
    used[np.ravel_multi_index((ij - lo + zero).T, (hi - lo + 1))] = True
    return GridCalibration(
        mapping=mapping,
        target_xy=nodes[inside] * spacing,
        image_xy=pred[inside],
        detected=used[inside],
        residual_rms=float(np.sqrt(np.mean(res**2))),
        residual_max=float(res.max()),
        n_detected=n_det,
        dots_xy=pts,
        dots_ij=ij,
        dark=dark,
    )
