"""Dot identification: thresholds, blob segmentation and blob scoring.

Whole-image identification (standard tracking) uses a static intensity threshold or the dynamic
threshold segmentation of Cardwell, Vlachos and Thole (2011), which raises the threshold step by step
and splits a blob wherever it breaks into several at a higher level. Identification with prior
information works on small windows around predicted positions: :func:`segment_windows` splits each
window's above-threshold pixels into blobs for a whole stack of windows at once, and :func:`blob_score`
ranks the blobs of a window with Eq. 1 of Rajendran, Bane and Vlachos (2019).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = [
    "blob_properties",
    "blob_score",
    "dynamic_threshold_identification",
    "estimate_noise",
    "segment_windows",
    "static_threshold_identification",
]

BLOB_DTYPE = np.dtype([("x", "f8"), ("y", "f8"), ("area", "i8"), ("peak", "f8")])

_EIGHT = np.ones((3, 3), dtype=bool)


def estimate_noise(image):
    """Standard deviation of the pixel noise, estimated robustly from neighbour differences.

    Parameters
    ----------
    image : (H, W) array

    Returns
    -------
    float
        ``q25(|I[i, j+1] - I[i, j]|) / (0.3186 sqrt(2))``: the lower quartile of the absolute horizontal
        differences, scaled so that it is the noise sigma for Gaussian noise (a difference of two pixels
        has sigma ``sqrt(2) sigma_n``, and 0.3186 is the lower quartile of a unit half-normal). The dots
        produce the large differences, so the lower quartile mostly sees the background; in dense
        patterns the dots' tails still lift it (by ~30-60 % at 20 dots of 3 px per 32x32 px), which is
        harmless for its use as a detection floor. Images of more than 256 rows use every
        ``rows // 256``-th row.
    """
    image = np.asarray(image, dtype=np.float64)
    image = image[:: max(1, image.shape[0] // 256)]
    d = np.diff(image, axis=1)
    d = np.abs(d, out=d).ravel()
    if d.size == 0:
        return 0.0
    return float(_lower_quartile(d) / (0.31864 * np.sqrt(2.0)))


def _lower_quartile(d):
    """``np.percentile(d, 25)`` (linear interpolation), by one partial sort of ``d`` in place.

    The quartile lies between the order statistics ``lo = floor(0.25 (n - 1))`` and ``lo + 1`` (the
    smallest value after the partition point), interpolated as NumPy does; NaN input goes to NumPy (the
    partition sorts NaN last, so one shows in ``a`` or in the minimum ``b`` of the rest).
    """
    pos = 0.25 * (d.size - 1)  # exact: 0.25 is a power of two
    lo = int(pos)
    t = pos - lo
    d.partition(lo)
    a = d[lo]
    b = d[lo + 1 :].min() if lo + 1 < d.size else a
    if np.isnan(a) or np.isnan(b):
        return np.percentile(d, 25)
    return b - (b - a) * (1.0 - t) if t >= 0.5 else a + (b - a) * t


def static_threshold_identification(image, *, threshold):
    """Label the 8-connected blobs of pixels above a fixed intensity threshold.

    Parameters
    ----------
    image : (H, W) array
    threshold : float, keyword-only
        Intensity above which a pixel belongs to a dot.

    Returns
    -------
    labels : (H, W) int array
        0 for background, 1..n for the blobs.
    n : int
        Number of blobs.
    """
    image = np.asarray(image, dtype=np.float64)
    labels, n = ndimage.label(image > threshold, structure=_EIGHT)
    return labels, int(n)


def dynamic_threshold_identification(image, *, threshold, n_levels=8, top=None):
    """Dynamic threshold segmentation: split overlapping dots by raising the threshold step by step.

    Parameters
    ----------
    image : (H, W) array
    threshold : float, keyword-only
        Lowest level (the static threshold).
    n_levels : int, keyword-only
        Number of threshold levels between ``threshold`` and ``top``.
    top : float, optional
        Highest level; the 99.9th percentile of the image by default.

    Returns
    -------
    labels : (H, W) int array
        0 for background, 1..n for the blobs.
    n : int
        Number of blobs.

    Notes
    -----
    Cardwell, Vlachos and Thole (2011), section 2.1: blobs are first labelled at ``threshold``; at each
    higher level a blob that contains two or more separate components is split, each of its pixels going
    to the nearest of those components; a blob that stays whole (or vanishes) keeps its pixels.
    """
    image = np.asarray(image, dtype=np.float64)
    labels, n = static_threshold_identification(image, threshold=threshold)
    if n == 0:
        return labels, 0
    if top is None:
        top = float(np.percentile(image, 99.9))
    for level in np.linspace(threshold, top, n_levels + 1)[1:]:
        comp, m = ndimage.label(image > level, structure=_EIGHT)
        if m < 2:
            continue
        parent = labels.ravel()[_first_pixels(comp, m)]  # region of each component (sets nest)
        counts = np.bincount(parent, minlength=n + 1)
        splits = counts[parent] >= 2  # components whose region breaks apart
        if not splits.any():
            continue
        seed_of = np.zeros(m + 1, dtype=np.int64)
        seed_of[1:][splits] = np.arange(1, splits.sum() + 1)
        lab = labels.ravel()
        pix = np.flatnonzero((counts[lab] >= 2) & (lab > 0))  # the pixels of the regions that split
        not_seed = ~np.r_[False, splits][comp]
        ri, ci = ndimage.distance_transform_edt(not_seed, return_distances=False, return_indices=True)
        nearest = seed_of[comp.ravel()[ri.ravel()[pix].astype(np.int64) * comp.shape[1] + ci.ravel()[pix]]]
        # A nearest seed from a neighbouring region (rare) cannot steal pixels: keep them in their region.
        seed_parent = np.zeros(splits.sum() + 1, dtype=np.int64)
        seed_parent[1:] = parent[splits]
        own = seed_parent[nearest] == lab[pix]
        new = lab.copy()
        new[pix[own]] = n + nearest[own]
        labels = _ranks(new).reshape(image.shape)
        if new.min() > 0:  # no background pixel: the rank 0 is a blob
            labels += 1
        n = int(labels.max())
    return labels, n


def _first_pixels(comp, m):
    """Flat index of the first pixel (in raster order) of each of the components 1..m of ``comp``.

    ``ndimage.minimum_position(comp, comp, range(1, m + 1))`` without its sort of the whole image: an
    assignment through repeated indices keeps the last value written, so writing the pixels backwards
    leaves each component's first one.
    """
    flat = comp.ravel()
    pix = np.flatnonzero(flat)[::-1]
    first = np.zeros(m + 1, dtype=np.int64)
    first[flat[pix]] = pix
    return first[1:]


def _ranks(values):
    """Rank of each value among the distinct values of a non-negative int array (its shape kept):
    ``np.unique(values, return_inverse=True)[1]`` by a table of the values present instead of a sort."""
    present = np.zeros(int(values.max()) + 1, dtype=np.int64)
    present[values.ravel()] = 1
    rank = np.cumsum(present) - 1
    return rank[values]


def blob_properties(image, labels):
    """Peak pixel, area and peak intensity of each labelled blob.

    Parameters
    ----------
    image : (H, W) array
    labels : (H, W) int array
        0 background, 1..n blobs.

    Returns
    -------
    structured array, one row per blob, fields ``x, y`` (the blob's brightest pixel, x = column; of
    equal brightest pixels the last in raster order, the one :func:`segment_windows` makes the peak),
    ``area`` (pixels) and ``peak`` (its intensity).
    """
    image = np.asarray(image, dtype=np.float64)
    n = int(labels.max()) if labels.size else 0
    out = np.zeros(n, dtype=BLOB_DTYPE)
    if n == 0:
        return out
    flat = labels.ravel()
    pix = np.flatnonzero(flat)
    lab, val = flat[pix], image.ravel()[pix]
    top = np.full(n + 1, -np.inf)
    np.maximum.at(top, lab, val)
    at_top = val == top[lab]
    peak_pixel = np.zeros(n + 1, dtype=np.int64)
    peak_pixel[lab[at_top]] = pix[at_top]  # repeated indices keep the last value: ties go to the last pixel
    rows, cols = np.divmod(peak_pixel[1:], image.shape[1])
    out["y"], out["x"] = rows, cols
    out["area"] = np.bincount(flat, minlength=n + 1)[1:]
    out["peak"] = top[1:]
    return out


def segment_windows(windows, threshold):
    """Split the above-threshold pixels of each window into blobs, for a stack of windows at once.

    Parameters
    ----------
    windows : (N, h, w) array
        Image windows (``h * w <= 65536``).
    threshold : (N,) array
        Intensity threshold of each window.

    Returns
    -------
    (N, h * w) int array
        For each pixel the flat index (in its window) of the peak pixel of its blob; -1 for pixels at or
        below the threshold. A blob's pixels therefore share one label, its peak pixel.

    Notes
    -----
    This is the dynamic threshold segmentation (Cardwell, Vlachos and Thole 2011) in the limit of fine
    threshold steps: raising the threshold splits a blob at every saddle, which is where the basins of
    steepest ascent meet. Each pixel points to the brightest of its 8 neighbours and itself (ties broken
    by pixel index, so plateaus stay whole) and the pointers are followed to their end by pointer jumping;
    the whole stack is done with array operations, no loop over windows.
    """
    windows = np.asarray(windows)
    n, h, w = windows.shape
    if h * w > 65536:
        raise ValueError(f"windows of {h}x{w} pixels are larger than the 65536-pixel limit")
    fg = windows > np.asarray(threshold)[:, None, None]
    vmin = windows.min()
    span = float(windows.max() - vmin)
    scale = (2.0**40) / span if span > 0 else 0.0
    # Order key: quantised intensity in the high bits, pixel index in the low 16 bits (unique, ties broken).
    q = ((windows - vmin) * scale).astype(np.int64) + 1
    key = np.where(fg, q, 0) << 16
    key |= np.arange(h * w, dtype=np.int64).reshape(h, w)
    # 3x3 maximum of the keys, separably; outside the window counts as lowest.
    best = key.copy()
    np.maximum(best[:, :, 1:], key[:, :, :-1], out=best[:, :, 1:])
    np.maximum(best[:, :, :-1], key[:, :, 1:], out=best[:, :, :-1])
    row = best.copy()
    np.maximum(best[:, 1:, :], row[:, :-1, :], out=best[:, 1:, :])
    np.maximum(best[:, :-1, :], row[:, 1:, :], out=best[:, :-1, :])
    parent = (best & 0xFFFF).reshape(n, h * w)
    steps = int(np.ceil(np.log2(h * w))) + 1
    for _ in range(steps):
        parent = np.take_along_axis(parent, parent, axis=1)
    return np.where(fg.reshape(n, h * w), parent, -1)


def blob_score(area, peak, distance, *, weights=(1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0)):
    """Score the candidate blobs of each window (Eq. 1 of Rajendran, Bane and Vlachos 2019).

    Parameters
    ----------
    area, peak, distance : (N, K) arrays
        Area ``A_p``, peak intensity ``I_p`` and distance ``dx_p`` of the blob's peak from the predicted
        position, for up to K candidate blobs per window; NaN marks a slot without a blob.
    weights : (W_A, W_I, W_dx), keyword-only
        The paper's weights are 1/3 each.

    Returns
    -------
    (N, K) array
        ``C_p = [W_A A_p / max A + W_I I_p / max I + W_dx (1 - dx_p / max dx)] / (W_A + W_I + W_dx)``,
        the maxima taken over the window's blobs; NaN where there is no blob. A window with one blob
        scores it ``(W_A + W_I) / sum W`` (or 1 if it lies exactly on the prediction).
    """
    area, peak, distance = (np.asarray(a, dtype=np.float64) for a in (area, peak, distance))
    wa, wi, wd = (float(v) for v in weights)
    with np.errstate(invalid="ignore", divide="ignore"):
        ma = np.nanmax(np.where(np.isnan(area), -np.inf, area), axis=-1, keepdims=True)
        mi = np.nanmax(np.where(np.isnan(peak), -np.inf, peak), axis=-1, keepdims=True)
        md = np.nanmax(np.where(np.isnan(distance), -np.inf, distance), axis=-1, keepdims=True)
        ta = np.where(ma > 0, area / ma, 1.0)
        ti = np.where(mi > 0, peak / mi, 1.0)
        td = np.where(md > 0, 1.0 - distance / md, 1.0)
    score = (wa * ta + wi * ti + wd * td) / (wa + wi + wd)
    return np.where(np.isnan(area) | np.isnan(peak) | np.isnan(distance), np.nan, score)
