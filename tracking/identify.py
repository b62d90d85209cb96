"""Dot identification: thresholds, blob segmentation and blob scoring.

Whole-image identification (standard tracking) uses a static intensity threshold or the dynamic
threshold segmentation of Cardwell, Vlachos and Thole (2011), which raises the threshold step by step
and splits a blob wherever it breaks into several at a higher level. Identification with prior
information works on small windows around predicted positions: :func:`segment_windows` splits each
window's above-threshold pixels into blobs for a whole stack of windows at once, and :func:`blob_score`
ranks the blobs of a window with Eq. 1 of Rajendran, Bane and Vlachos (2019);
:func:`identify_near_predictions` is the step itself: one dot near each predicted position, the window
measurement (:func:`tracking.windows.measure_windows`, a Warp kernel) iterated on the residual image.
"""

from __future__ import annotations

import numpy as np
import warp as wp
from scipy import ndimage
from scipy.spatial import cKDTree

from . import claim_kernels as ck
from .centroid import fit_centroids, gaussian3_from_samples
from .frame_stats import partial_median, segment_medians
from .identify_kernels import measure_stack
from .mask import touches
from .residual import subtract_gaussians
from .settings import (
    DIAMETER_PER_WIDTH,
    RESIDUAL_STAMP_WIDTHS,
    RESIDUAL_WIDTH_CLIP,
    SMALL_WINDOW,
    THREE_POINT_WIDTH_RANGE,
    WILD_FIT_PX,
    DotStatus,
    residual_reach,
    search_reach,
)
from .sorting import median_network
from .windows import measure_windows

__all__ = [
    "StackIdentification",
    "blob_properties",
    "blob_score",
    "dynamic_threshold_identification",
    "estimate_noise",
    "identify_near_predictions",
    "kernels_measure",
    "segment_windows",
    "standard_candidates",
    "static_threshold_identification",
]

BLOB_DTYPE = np.dtype([("x", "f8"), ("y", "f8"), ("area", "i8"), ("peak", "f8")])

_EIGHT = np.ones((3, 3), dtype=bool)


def estimate_noise(image, *, excluded=None):
    """Standard deviation of the pixel noise, estimated robustly from neighbour differences.

    Parameters
    ----------
    image : (H, W) array
    excluded : (H, W) bool array, optional, keyword-only
        Pixels left out (a mask, filled with one value: differences there would say the noise is 0);
        only differences of two pixels both not excluded count.

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
    step = max(1, image.shape[0] // 256)
    image = image[::step]
    d = np.diff(image, axis=1)
    d = np.abs(d, out=d).ravel()
    if excluded is not None:
        keep = ~np.asarray(excluded, dtype=bool)[::step]
        d = d[(keep[:, 1:] & keep[:, :-1]).ravel()]
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


def standard_candidates(image, settings, noise):
    """Standard tracking's candidates: the (K, 2) centres of the blobs that whole-image identification
    (``settings.identification``: dynamic or static threshold) finds above ``settings.threshold``, or by
    default above the median + ``threshold_fraction`` of the way to the 99.9th percentile, and at least
    ``noise_threshold`` times the ``noise`` above the median.

    Examples
    --------
    >>> from synthbos.raytrace.dots import draw_dots
    >>> from synthbos.tracking.settings import TrackingSettings
    >>> image = draw_dots((32, 32), np.array([[8.0, 8.0], [20.0, 12.0]]), 3.0)
    >>> standard_candidates(image, TrackingSettings(), 0.0).round(1).tolist()
    [[8.0, 8.0], [20.0, 12.0]]
    """
    if settings.threshold is not None:
        thr = float(settings.threshold)
    else:
        med = float(np.median(image))
        top = float(np.percentile(image, 99.9))
        thr = med + max(settings.threshold_fraction * (top - med), settings.noise_threshold * noise)
    if settings.identification == "dynamic":
        labels, _ = dynamic_threshold_identification(image, threshold=thr, n_levels=settings.n_levels)
    else:
        labels, _ = static_threshold_identification(image, threshold=thr)
    props = blob_properties(image, labels)
    return np.stack([props["x"], props["y"]], axis=1)


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


def identify_near_predictions(
    image, pred, *, half, map_half, radius, settings, eta0, max_iterations, noise, sat_level, fill, device
):
    """Find one dot near each predicted position, iterating on the residual image (Eqs. 1 and 2).

    ``fill`` is the value of the pixels outside the image (the median background,
    :func:`tracking.frame_stats.fill_level`). Returns a dict of per-dot arrays: x, y, eta, i0, iteration,
    flags, root (N, 2) = (col, row) of the dot's peak pixel, and, for the paper's correction (the only
    user), dotmap (N, c, c): its background-free pixels centred on the peak, others zero.
    """
    w_img = image.shape[1]
    n = len(pred)
    c = 2 * map_half + 1
    width_lo, width_hi = THREE_POINT_WIDTH_RANGE
    out = {
        "x": np.full(n, np.nan),
        "y": np.full(n, np.nan),
        "eta": np.full(n, np.nan),
        "i0": np.full(n, np.nan),
        "iteration": np.zeros(n, dtype=np.int16),
        "flags": np.zeros(n, dtype=np.int32),
        "root": np.zeros((n, 2), dtype=np.int64),
    }
    keep_maps = settings.correction == "paper"
    if keep_maps:
        out["dotmap"] = np.zeros((n, c, c))
    inside, origin_all = _window_origins(pred, image.shape, half, out["flags"])
    todo = inside.copy()
    subtracted = np.zeros(n, dtype=bool)
    residual = image
    ref_peak = None
    method = "gaussian3" if settings.centroid == "model" else settings.centroid
    # the three-point start needs only the centre of the dot maps
    full_maps = keep_maps or method != "gaussian3"
    for it in range(1, max_iterations + 1):
        sel = np.flatnonzero(todo)
        if sel.size == 0:
            break
        every = sel.size == n  # the first round, all inside (the usual case): no gather
        origin = origin_all if every else origin_all[sel]
        m = measure_windows(
            residual,
            origin,
            pred if every else pred[sel],
            half=half,
            map_half=map_half,
            radius=radius,
            threshold_fraction=settings.threshold_fraction,
            noise_floor=settings.noise_threshold * noise,
            weights=settings.weights,
            use_minimum=settings.background == "minimum",
            saturation=sat_level,
            fill=fill,
            full_maps=full_maps,
            device=device,
        )
        has = m["chosen"] >= 0
        cpeak = m["peak"]
        if ref_peak is None:
            ref_peak = partial_median(cpeak[has]) if has.any() else 0.0
        ok = has & (cpeak > settings.detection_snr * noise) & (cpeak > settings.min_relative_peak * ref_peak)
        ok &= cpeak > 0
        root_r, root_c, win_idx = _claims(m, ok, origin, 2 * half + 1, w_img, sel, out["flags"])
        if win_idx.size == 0:
            break
        xw, yw, eta, i0, fit_ok = _window_centroids(m, win_idx, method, map_half)
        eta_ok = np.isfinite(eta) & (eta > width_lo * eta0) & (eta < width_hi * eta0)
        eta = np.where(eta_ok, eta, eta0)
        i0 = np.where(np.isfinite(i0) & (i0 > 0), i0, cpeak.take(win_idx))
        g = win_idx if every else sel[win_idx]
        rc, rr = root_c.take(win_idx), root_r.take(win_idx)  # take: faster than indexing
        out["x"][g] = rc + (xw - map_half)
        out["y"][g] = rr + (yw - map_half)
        out["eta"][g] = eta
        out["i0"][g] = i0
        out["iteration"][g] = it
        out["root"][g, 0], out["root"][g, 1] = rc, rr
        if keep_maps:
            out["dotmap"][g] = m["dotmap"][win_idx]
        flags = np.where(m["nblobs"].take(win_idx) > 1, np.int32(DotStatus.OVERLAPPED), np.int32(0))
        flags |= np.where(fit_ok, np.int32(0), np.int32(DotStatus.FIT_FALLBACK))
        flags |= np.where(m["nsat"].take(win_idx) >= 2, np.int32(DotStatus.SATURATED), np.int32(0))
        out["flags"][g] = (out["flags"].take(g) & ~np.int32(DotStatus.AMBIGUOUS)) | flags
        todo[g] = False
        if todo.any() and it < max_iterations:
            residual = _subtract_found(residual, out, subtracted, pred[todo], half, eta0)
    return out


def _window_origins(pred, shape, half, flags):
    """Which predictions lie inside the image and each window's first (column, row); ``flags`` gets
    OUTSIDE_IMAGE and NEAR_BORDER."""
    h_img, w_img = shape
    # every comparison with NaN is false and +-inf fails one of the bounds: non-finite rows are outside
    px, py = pred[:, 0], pred[:, 1]
    inside = (px > -0.5) & (px < w_img - 0.5)
    inside &= py > -0.5
    inside &= py < h_img - 0.5
    flags[~inside] |= DotStatus.OUTSIDE_IMAGE
    origin_all = np.rint(np.where(inside[:, None], pred, 0.0)).astype(np.int64)
    origin_all -= half
    ox, oy = origin_all[:, 0], origin_all[:, 1]
    border = (ox < 0) | (oy < 0)
    border |= ox + 2 * half >= w_img
    border |= oy + 2 * half >= h_img
    flags[inside & border] |= DotStatus.NEAR_BORDER
    return inside, origin_all


def _claims(m, ok, origin, w, w_img, sel, flags):
    """The chosen blobs' peak pixels (row, column in the image) and the windows that keep their blob:
    two prior dots may claim one blob, the nearer keeps it, the other (flagged AMBIGUOUS) waits for the
    residual image."""
    root_r, root_c = np.divmod(np.maximum(m["chosen"], 0), w)
    root_c += origin[:, 0]
    root_r += origin[:, 1]
    absroot = (root_r + 2 * w) * (w_img + 4 * w) + (root_c + 2 * w)
    cidx = np.flatnonzero(ok)
    claimed = np.sort(absroot[cidx])
    if cidx.size < 2 or (claimed[1:] != claimed[:-1]).all():
        return root_r, root_c, cidx  # every blob claimed once (the usual case): nothing to resolve
    order = cidx[np.lexsort((m["dist"][cidx], absroot[cidx]))]
    first = np.ones(len(order), dtype=bool)
    first[1:] = absroot[order][1:] != absroot[order][:-1]
    flags[sel[order[~first]]] |= DotStatus.AMBIGUOUS
    return root_r, root_c, order[first]


def _window_centroids(m, win_idx, method, map_half):
    """Each kept window's dot centre (window coordinates), width, peak and whether the fit held. The model
    fit (centroid="model") starts from the three-point estimate, which needs only the peak pixel and its
    four neighbours; a wild fit (beyond the peak pixel's neighbours) falls back to the peak pixel."""
    c = 2 * map_half + 1
    if method == "gaussian3":
        if "cross" in m:  # the kernel cut only the centre cross: peak, left, right, up, down
            cross = m["cross"]
        else:
            k0 = map_half * c + map_half
            cross = m["dotmap"].reshape(len(m["chosen"]), c * c)[:, [k0, k0 - 1, k0 + 1, k0 - c, k0 + c]]
        # the five samples as contiguous rows (the three-point fit's array operations read them often)
        dx, dy, eta, i0, fit_ok = gaussian3_from_samples(*np.take(cross.T, win_idx, axis=1))
        xw, yw = map_half + dx, map_half + dy
    else:
        dotmap = m["dotmap"][win_idx]
        hc = np.full(len(win_idx), map_half)
        xw, yw, eta, i0, fit_ok = fit_centroids(dotmap, method=method, peak_rc=(hc, hc), mask=dotmap != 0)
    wild = ~(np.isfinite(xw) & np.isfinite(yw))
    wild |= (np.abs(xw - map_half) > WILD_FIT_PX) | (np.abs(yw - map_half) > WILD_FIT_PX)
    xw = np.where(wild, map_half, xw)
    yw = np.where(wild, map_half, yw)
    fit_ok &= ~wild
    return xw, yw, eta, i0, fit_ok


def _subtract_found(residual, out, subtracted, missing, half, eta0):
    """Eq. 2, applied where it matters: found dots near a dot still ``missing`` leave the residual image
    (and are marked in ``subtracted``)."""
    clip_lo, clip_hi = RESIDUAL_WIDTH_CLIP
    found = np.flatnonzero(np.isfinite(out["x"]) & ~subtracted)
    if not found.size:
        return residual
    fxy = np.stack([out["x"][found], out["y"][found]], axis=1)
    near = cKDTree(fxy).query_ball_point(missing, residual_reach(half, eta0))
    near = np.unique(np.concatenate([np.asarray(a, dtype=np.int64) for a in near] + [np.zeros(0, np.int64)]))
    if not near.size:
        return residual
    idx = found[near]
    subtracted[idx] = True
    return subtract_gaussians(
        residual,
        fxy[near],
        out["i0"][idx],
        np.clip(out["eta"][idx], clip_lo * eta0, clip_hi * eta0),
        radius=int(np.ceil(RESIDUAL_STAMP_WIDTHS * eta0)),
    )


# --- a stack of pairs on one Warp device ------------------------------------------------------------

#: Frames of the hash grid that finds the dots near those still missing are this far apart along z (px).
_Z_STEP = 1000.0


def kernels_measure(settings) -> bool:
    """Whether :class:`StackIdentification`'s kernels measure what ``settings`` ask of identification: the
    three-point start of the model fit (``centroid="model"``), without the dot maps of the paper's
    correction; other estimators take its host engine on every device.

    Examples
    --------
    >>> from synthbos.tracking.settings import TrackingSettings
    >>> kernels_measure(TrackingSettings()), kernels_measure(TrackingSettings.paper())
    (True, False)
    """
    return settings.centroid == "model" and settings.correction == "model"


class StackIdentification:
    """Identification (Eq. 1, Eq. 2) of a stack of B pairs of one group, N prior dots each, on one Warp
    device: :func:`identify_near_predictions` for the dots of every pair in each launch, its rounds of
    claims on one claim board (kernels in :mod:`tracking.claim_kernels`).

    Parameters
    ----------
    refs : (B, H, W) float64 Warp array
        The reference images (their shape and device; the images searched are given to :meth:`identify`).
    stats : dict
        Per pair and image (index 0 the reference, 1 the gradient image), as Warp arrays of B values:
        ``"noise"``, ``"fill"``, ``"sat"`` and ``"floor"`` (the noise threshold).
    geometry : sequence of objects
        Each pair's ``d`` (dot diameter, px); the first one's window half-sizes ``half_r``, ``half_g`` and
        ``map_half`` are shared by the group.
    settings : TrackingSettings
    per_frame : int, keyword-only
        The prior's dots per pair, N.
    device : str, keyword-only

    Attributes
    ----------
    eta0_host : (B,) float64 array
        Each pair's nominal dot width (px).
    board : tuple
        The claim board ``(hp, wpad, claim_dist, claim_id)`` (padded frame height and width, each blob's
        claimed distance and dot), left released after each call.
    """

    def __init__(self, refs, stats, geometry, settings, *, per_frame, device):
        self.device = device
        self.on_cpu = wp.get_device(device).is_cpu
        self.settings = settings
        self.B, self.H, self.W = refs.shape
        self.N = per_frame
        self.M = self.B * per_frame
        self.stats = stats
        d = np.array([g.d for g in geometry])
        self.eta0_host = d / DIAMETER_PER_WIDTH
        self.eta0 = self.arr(self.eta0_host, wp.float64)
        g0 = geometry[0]
        self.geometry = g0
        w_max = 2 * g0.half_g + 1
        self.hp, self.wpad = self.H + 4 * w_max, self.W + 4 * w_max
        cells = self.B * self.hp * self.wpad
        self.claim_dist = wp.full(cells, np.inf, dtype=wp.float64, device=device)
        self.claim_id = wp.full(cells, np.iinfo(np.int32).max, dtype=wp.int32, device=device)
        self.board = (self.hp, self.wpad, self.claim_dist, self.claim_id)
        self.residual = wp.empty_like(refs)
        self.grid = wp.HashGrid(128, 128, 64, device=device)
        self.on_host = self.on_cpu or not kernels_measure(settings)
        # the fixed-point sums of the stamps taken from the residual (claim_kernels.stamp_near_waiting), all
        # zero between calls of identify (each clears what it used); only the kernels' engine uses them
        self.stamps = None if self.on_host else wp.zeros(refs.shape, dtype=wp.int64, device=device)

    def arr(self, a, dtype):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=self.device)

    def _identify_on_host(self, image, which, pred, ids, n_ids, *, wide):
        """:meth:`identify`'s host engine, for the CPU and for the estimators the kernels do not measure
        (:func:`kernels_measure`): :func:`identify_near_predictions` pair by pair on the arrays where they
        lie (its windows sorted by place, its claims on the host and its rounds stopped when no dot waits
        took 31 ms on the 1024 x 1024 benchmark pair against 82 ms for the rounds of kernels). The paper's
        correction's dot maps stay on the host (``"dotmap"``, an (M, c, c) NumPy array)."""
        s, g, M = self.settings, self.geometry, self.M
        search = search_reach(s)
        out = {k: np.full(M, np.nan) for k in ("x", "y", "eta", "i0")}
        out.update(iteration=np.zeros(M, np.int32), flags=np.zeros(M, np.int32), root=np.zeros((M, 2), np.int32))
        if s.correction == "paper":
            c = 2 * g.map_half + 1
            out["dotmap"] = np.zeros((M, c, c))
        sel = np.sort(ids.numpy()[:n_ids])
        pairs = np.searchsorted(sel, np.arange(self.B + 1) * self.N)
        images, xy = image.numpy(), pred.numpy()
        st = {k: self.stats[k][which].numpy() for k in ("noise", "sat", "fill")}
        for b in np.flatnonzero(np.diff(pairs)):
            rows = sel[pairs[b] : pairs[b + 1]]
            found = identify_near_predictions(
                images[b], xy[rows], half=g.half_g if wide else g.half_r, map_half=g.map_half,
                radius=search if wide else s.prior_radius, settings=s, eta0=self.eta0_host[b],
                max_iterations=s.max_iterations, noise=st["noise"][b], sat_level=st["sat"][b], fill=st["fill"][b],
                device=self.device,
            )  # fmt: skip
            for k, v in out.items():
                v[rows] = found[k]
        maps = out.pop("dotmap", None)
        out = {k: self.arr(v, wp.float64 if v.dtype == np.float64 else wp.int32) for k, v in out.items()}
        if maps is not None:
            out["dotmap"] = maps
        return out

    def standard(self, images, which, excluded=None):
        """Standard tracking's identification in ``images`` (the (B, H, W) NumPy stack; ``which`` 0 the
        reference images, 1 the gradient images), on the host: per pair, the dots found at the
        :func:`standard_candidates` not on its ``excluded`` pixels (one round, within a pixel of the
        candidate), as dicts of per-dot NumPy arrays of the dots found only."""
        s, g = self.settings, self.geometry
        st = {k: self.stats[k][which].numpy() for k in ("noise", "sat", "fill")}
        founds = []
        for b, image in enumerate(images):
            cand = standard_candidates(image, s, st["noise"][b])
            if excluded is not None:
                cand = cand[~touches(excluded[b], cand)]
            found = identify_near_predictions(
                image, cand, half=g.half_r, map_half=g.map_half, radius=1.0, settings=s, eta0=self.eta0_host[b],
                max_iterations=1, noise=st["noise"][b], sat_level=st["sat"][b], fill=st["fill"][b],
                device=self.device,
            )  # fmt: skip
            keep = np.isfinite(found["x"])
            founds.append({k: v[keep] for k, v in found.items()})
        return founds

    def zeros(self, shape, dtype):
        return wp.zeros(shape, dtype=dtype, device=self.device)

    def full(self, shape, value, dtype):
        return wp.full(shape, value, dtype=dtype, device=self.device)

    def launch(self, kernel, dim, inputs):
        if dim:
            wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)

    def identify(self, image, which, pred, ids, n_ids, *, wide):
        """:func:`identify_near_predictions` for the dots ``ids`` (an int32 Warp array, ``n_ids`` of them)
        of every pair, around ``pred`` (``wp.vec2d``, one per prior row), in ``image`` (the reference
        images with ``which`` 0, the gradient images with 1), with the wide window if ``wide``: fresh
        (M,) per-dot Warp arrays ``x``, ``y``, ``eta``, ``i0``, ``iteration``, ``root`` and ``flags``."""
        if self.on_host:
            return self._identify_on_host(image, which, pred, ids, n_ids, wide=wide)
        s, g, M = self.settings, self.geometry, self.M
        half = g.half_g if wide else g.half_r
        search = search_reach(s)
        radius = search if wide else s.prior_radius
        w = 2 * half + 1
        st = self.stats
        out = {
            "x": self.full(M, np.nan, wp.float64),
            "y": self.full(M, np.nan, wp.float64),
            "eta": self.full(M, np.nan, wp.float64),
            "i0": self.full(M, np.nan, wp.float64),
            "iteration": self.zeros(M, wp.int32),
            "flags": self.zeros(M, wp.int32),
            "root": self.zeros((M, 2), wp.int32),
        }
        if n_ids == 0:
            return out
        origin = self.zeros((M, 2), wp.int32)
        todo = self.zeros(M, wp.int32)
        subtracted = self.zeros(M, wp.int32)
        self.launch(ck.start_identification, n_ids, [pred, ids, self.H, self.W, half, origin, todo, out["flags"]])
        wp.copy(self.residual, image)
        active = self.full(self.B, 1, wp.int32)
        won = self.zeros(self.B, wp.int32)
        rows = 1 if wp.get_device(self.device).is_cpu else n_ids
        ww = w * w if w != SMALL_WINDOW else 1  # the 7 x 7 window is measured in registers
        scratch = [
            wp.empty((rows, ww), dtype=wp.float64, device=self.device),
            wp.empty((rows, max(4 * (w - 1), 1)), dtype=wp.float64, device=self.device),
            self.arr(median_network(4 * (w - 1)), wp.int32),
            wp.empty((rows, ww), dtype=wp.int32, device=self.device),
            wp.empty((rows, ww), dtype=wp.int32, device=self.device),
            wp.empty((rows, ww), dtype=wp.int32, device=self.device),
            wp.empty((1, 1, 1), dtype=wp.float64, device=self.device),
        ]
        out_int = wp.empty((n_ids, 3), dtype=wp.int32, device=self.device)
        out_float = wp.empty((n_ids, 3), dtype=wp.float64, device=self.device)
        cross = wp.empty((n_ids, 5), dtype=wp.float64, device=self.device)
        key = wp.empty(n_ids, dtype=wp.int32, device=self.device)
        noise, fill, sat = st["noise"][which], st["fill"][which], st["sat"][which]
        floor = st["floor"][which]
        ref_peak = None
        reach_px = residual_reach(half, self.eta0_host)
        reach = self.arr(reach_px, wp.float64)
        wa, wi, wd = (float(v) for v in s.weights)
        points = wp.empty(M, dtype=wp.vec3, device=self.device)
        for it in range(1, s.max_iterations + 1):
            self.launch(
                measure_stack,
                n_ids,
                [
                    self.residual, ids, self.N, fill, floor, sat, active, origin, pred, todo, half, g.map_half,
                    float(radius), float(s.threshold_fraction), wa, wi, wd, int(s.background == "minimum"),
                    *scratch, out_int, out_float, cross, 0,
                ],
            )  # fmt: skip
            if ref_peak is None:
                values = self.zeros(M, wp.float64)
                valid = self.zeros(M, wp.int32)
                self.launch(ck.measured_peaks, n_ids, [ids, out_int, out_float, values, valid])
                ref_peak = segment_medians(values, valid, length=self.N, segments=self.B, device=self.device)
            self.launch(
                ck.accept_blobs,
                n_ids,
                [
                    ids, self.N, out_int, out_float, origin, noise, ref_peak, float(s.detection_snr),
                    float(s.min_relative_peak), w, self.hp, self.wpad, key, self.claim_dist,
                ],
            )  # fmt: skip
            self.launch(ck.claim_nearest, n_ids, [ids, out_float, key, self.claim_dist, self.claim_id])
            self.launch(
                ck.take_blobs,
                n_ids,
                [
                    ids, self.N, it, out_int, out_float, cross, origin, key, self.claim_id, self.eta0, w,
                    out["x"], out["y"], out["eta"], out["i0"], out["iteration"], out["root"], out["flags"], todo, won,
                ],
            )  # fmt: skip
            self.launch(ck.release_claims, n_ids, [key, self.claim_dist, self.claim_id])
            self.launch(ck.next_round, self.B, [won, active])
            if it < s.max_iterations:
                self.launch(ck.waiting_points, M, [pred, todo, self.N, _Z_STEP, points])
                self.grid.build(points, float(np.max(reach_px)) + 1.0)
                self.launch(
                    ck.stamp_near_waiting,
                    n_ids,
                    [
                        self.grid.id, ids, self.N, _Z_STEP, it, active, pred, todo, out["x"], out["y"], out["eta"],
                        out["i0"], self.eta0, reach, ref_peak, subtracted, self.stamps,
                    ],
                )  # fmt: skip
                self.launch(
                    ck.apply_stamps,
                    n_ids,
                    [
                        ids, self.N, it, out["x"], out["y"], self.eta0, ref_peak, subtracted, image, self.stamps,
                        self.residual,
                    ],
                )  # fmt: skip
        self.launch(ck.clear_stamps, n_ids, [ids, self.N, out["x"], out["y"], self.eta0, subtracted, self.stamps])
        return out
