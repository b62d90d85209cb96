"""A coarse-to-fine correlation predictor for the gradient image, with a local significance measure.

The tracker pairs a dot with the blob nearest its predicted gradient-image position. Without a predictor
that position is the reference position, so displacements beyond a couple of pixels (the window margin)
are missed or, worse, paired with a neighbouring dot. Here a multigrid window-deformation correlation of
the whole pair (:func:`synthbos.correlation.correlate_pair`, coarse windows first) predicts every dot's
displacement, and the normalised correlation of the pair after undoing that prediction says where the
prediction can be trusted: it is near 1 where the images agree and near 0 where the gradient frame is
unrelated to the reference one (wrong frame, flipped frame, decorrelated region).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from synthbos.correlation import CorrelationSettings, correlate_pair
from synthbos.correlation.deform import spline_weights

from synthbos import SynthbosError

__all__ = ["PREDICTOR_WINDOWS", "local_normalized_correlation", "predict_displacement"]

#: Window sizes (px) of the predictor's passes: 64 px windows find shifts up to about 16 px (a quarter of
#: the window); the 32 and 16 px passes follow fields that vary over a few tens of pixels.
PREDICTOR_WINDOWS = (64, 32, 16)

#: Fixed-point iterations from the correlation's midpoint field to the reference positions.
_MIDPOINT_ITERATIONS = 4


def local_normalized_correlation(a, b, *, size, weights=None):
    """Normalised correlation coefficient of two images in a square box around every pixel.

    Parameters
    ----------
    a, b : (H, W) arrays
        Images sampled on the same pixels.
    size : int
        Side of the box in pixels.
    weights : (H, W) array of 0 and 1, optional
        Pixels that take part (1); others are ignored.

    Returns
    -------
    (H, W) float64 array
        ``cov(a, b) / sqrt(var(a) var(b))`` over the box's pixels with weight 1, in [-1, 1]; 0 where
        either image is flat in the box or fewer than a quarter of its pixels take part.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=np.float64)

    def box(f):
        return ndimage.uniform_filter(f, size=size, mode="constant")

    n = box(w)
    enough = n > 0.25
    n = np.where(enough, n, 1.0)
    ma, mb = box(w * a) / n, box(w * b) / n
    va = box(w * a * a) / n - ma * ma
    vb = box(w * b * b) / n - mb * mb
    cov = box(w * a * b) / n - ma * mb
    den = np.sqrt(np.maximum(va, 0.0) * np.maximum(vb, 0.0))
    ok = enough & (den > 1e-12 * (np.abs(ma) * np.abs(mb) + 1e-300))
    return np.where(ok, np.clip(cov / np.where(ok, den, 1.0), -1.0, 1.0), 0.0)


def _fill_nan(u):
    """Replace NaN nodes (masked windows) by the nearest finite one."""
    bad = ~np.isfinite(u)
    if not bad.any():
        return u
    if bad.all():
        return np.zeros_like(u)
    idx = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
    return u[tuple(idx)]


def predict_displacement(
    reference,
    gradient,
    xy,
    *,
    window_sizes=PREDICTOR_WINDOWS,
    quality_window=32,
    min_dots_per_window=5.0,
    mask=None,
    device=None,
):
    """Predict each dot's displacement by coarse-to-fine correlation, and say how far to trust it.

    Parameters
    ----------
    reference, gradient : (H, W) arrays
        The image pair.
    xy : (N, 2) array
        Reference-image positions (x = column, y = row) at which to predict; non-finite rows give NaN.
    window_sizes : tuple of int, keyword-only
        Window size of each correlation pass, coarse first (50 % overlap; one iteration per pass, two
        for the last).
        The first should be at least four times the largest displacement; sizes larger than the image
        are reduced to it.
    min_dots_per_window : float, keyword-only
        Passes whose windows would hold fewer dots than this on average (from the number of ``xy`` inside
        the image) are replaced by one pass with the smallest window (a multiple of 8 px) that holds
        that many: sparse patterns, calibration grids.
    quality_window : int, keyword-only
        Side of the box of the significance measure (``quality``), px; reduced to the image size.
    mask : (H, W) bool array, optional
        True on pixels to exclude (as :func:`synthbos.correlation.correlate_pair`).
    device : str, optional
        Warp device of the image deformation; "cpu" when None.

    Returns
    -------
    uv : (N, 2) float array
        Predicted displacement (u, v) in pixels: the last pass's field, interpolated to ``xy`` by the
        correlation's separable cubic spline.
    quality : (N,) float array
        Normalised correlation coefficient of the reference image and the gradient image sampled at
        ``x + uv`` (bilinear), over a box of ``quality_window`` (or the last window, if larger) around each
        position, masked and
        out-of-image pixels left out: about 1 where the prediction is right, about 0 for an unrelated
        gradient image (its spread there is roughly one over the square root of the number of dots in
        the box).

    Notes
    -----
    Not part of Rajendran, Bane and Vlachos (2019), where the reference position itself is the
    prediction for the gradient image (which limits the displacement to the window margin). The
    correlation is Scarano's (2002) multigrid window deformation; the significance test is the
    normalised correlation after deformation (Raffel et al. 2018, section 5.5: a correct
    displacement leaves two nearly identical images).
    """
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(gradient, dtype=np.float64)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    h, w = a.shape
    side = min(h, w)
    fin = np.isfinite(xy).all(axis=1)
    n_in = np.count_nonzero(
        fin
        & (np.abs(np.where(fin, xy[:, 0], -9) - (w - 1) / 2) <= w / 2)
        & (np.abs(np.where(fin, xy[:, 1], -9) - (h - 1) / 2) <= h / 2)
    )
    smallest = 8 * int(np.ceil(np.sqrt(min_dots_per_window * h * w / max(n_in, 1)) / 8.0))
    window_sizes = [s for s in window_sizes if s > smallest] + [min(smallest, max(window_sizes))]
    sizes = []
    for s in window_sizes:
        s = int(min(s, side))
        if s >= 8 and s not in sizes:
            sizes.append(s)
    n = len(xy)
    if not sizes or n == 0:
        return np.zeros((n, 2)), np.zeros(n)
    while True:
        settings = CorrelationSettings(
            window_sizes=tuple(sizes),
            overlaps=0.5,
            iterations=(1,) * (len(sizes) - 1) + (2,),
            # the coarse passes of a strongly varying field are smeared, not wrong: no peak-coefficient or
            # coarse-to-fine disagreement failures here; the significance below judges the result
            min_correlation=0.0,
            max_disagreement=1.0e6,
            device="cpu" if device is None else device,
        )
        try:
            res = correlate_pair(a, b, settings=settings, mask=mask)
            break
        except SynthbosError:
            if mask is None or len(sizes) == 1:
                raise
            sizes = sizes[1:]  # the mask covers most of every coarse window: start finer
    node_y, node_x = res.y[:, 0].astype(np.float64), res.x[0, :].astype(np.float64)
    u, v = _fill_nan(res.u.astype(np.float64)), _fill_nan(res.v.astype(np.float64))

    rows, cols = np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64)
    # the correlation's separable cubic spline of the node field at every pixel, constant beyond the
    # outer nodes (the edge windows are the least reliable, their extrapolation more so)
    wy = spline_weights(node_y, np.clip(rows, node_y[0], node_y[-1]))
    wx = spline_weights(node_x, np.clip(cols, node_x[0], node_x[-1]))
    du, dv = wy @ u @ wx.T, wy @ v @ wx.T

    # The correlation measures the displacement at the midpoint of a dot's two positions: solve
    # d = field(x + d / 2) for the displacement of the dot at reference position x (the field is
    # sampled bilinearly from its values at the pixels, which it varies too slowly to notice).
    finite = np.isfinite(xy).all(axis=1)
    pts = np.where(finite[:, None], xy, 0.0)
    uv = np.zeros((n, 2))
    for _ in range(_MIDPOINT_ITERATIONS):
        mid = [np.clip(pts[:, 1] + 0.5 * uv[:, 1], 0, h - 1), np.clip(pts[:, 0] + 0.5 * uv[:, 0], 0, w - 1)]
        uv = np.stack([ndimage.map_coordinates(f, mid, order=1) for f in (du, dv)], axis=1)
    uv[~finite] = np.nan

    # Significance: undo the prediction on the gradient image (one midpoint step: the field varies
    # slowly) and correlate it with the reference locally.
    my, mx = rows[:, None] + 0.5 * dv, cols[None, :] + 0.5 * du
    ru = ndimage.map_coordinates(du, [my, mx], order=1, mode="nearest")
    rv = ndimage.map_coordinates(dv, [my, mx], order=1, mode="nearest")
    sy, sx = rows[:, None] + rv, cols[None, :] + ru
    inside = (sy >= 0) & (sy <= h - 1) & (sx >= 0) & (sx <= w - 1)
    warped = ndimage.map_coordinates(b, [sy, sx], order=1, mode="nearest")
    valid = inside.astype(np.float64)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        moved = ndimage.map_coordinates(m.astype(np.float64), [sy, sx], order=0, mode="nearest") > 0
        valid *= ~(m | moved)
    # the box holds at least ~20 dots: the chance correlation of unrelated images falls as 1 / sqrt(dots)
    dense_enough = 8 * int(np.ceil(np.sqrt(20.0 * h * w / max(n_in, 1)) / 8.0))
    box = min(max(int(quality_window), sizes[-1], dense_enough), side)
    ncc = local_normalized_correlation(a, warped, size=box, weights=valid)
    r = np.clip(np.rint(pts[:, 1]).astype(np.int64), 0, h - 1)
    c = np.clip(np.rint(pts[:, 0]).astype(np.int64), 0, w - 1)
    quality = np.where(finite, ncc[r, c], np.nan)
    return uv, quality
