"""A coarse displacement predictor for the gradient image: correlation of large windows."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from synthbos.correlation.peak import subpixel_peak
from synthbos.correlation.xcorr import cross_correlate

__all__ = ["predict_displacement"]


def predict_displacement(reference, gradient, xy, *, window=16, max_displacement=None):
    """Predict each dot's displacement from the correlation of the windows around it.

    Parameters
    ----------
    reference, gradient : (H, W) arrays
        The image pair.
    xy : (N, 2) array
        Positions (x = column) at which to predict.
    window : int, keyword-only
        Side of the square, non-overlapping interrogation windows.
    max_displacement : float, optional
        Predictions are clipped to this magnitude per component.

    Returns
    -------
    (N, 2) array
        Predicted (u, v) in pixels, bilinearly interpolated from the window grid after a 3x3 median
        filter of the grid (so a few failed windows do not spoil it); zeros for an image smaller than one
        window.

    Notes
    -----
    Not part of Rajendran, Bane and Vlachos (2019), where the reference position itself is the
    prediction for the gradient image. Centring each dot's gradient window on this prediction keeps the
    window as small as the reference one even for displacements comparable to the dot spacing.
    """
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(gradient, dtype=np.float64)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    h, w = a.shape
    ny, nx = h // window, w // window
    if ny == 0 or nx == 0 or len(xy) == 0:
        return np.zeros((len(xy), 2))
    ta = a[: ny * window, : nx * window].reshape(ny, window, nx, window).swapaxes(1, 2)
    tb = b[: ny * window, : nx * window].reshape(ny, window, nx, window).swapaxes(1, 2)
    corr = cross_correlate(ta, tb, subtract_mean=True)
    row, col, _ = subpixel_peak(corr)
    u = col - window // 2
    v = row - window // 2
    if ny >= 3 and nx >= 3:
        u = ndimage.median_filter(u, size=3, mode="nearest")
        v = ndimage.median_filter(v, size=3, mode="nearest")
    # Window (i, j) is centred at ((j + 0.5) window - 0.5, (i + 0.5) window - 0.5).
    gx = (xy[:, 0] + 0.5) / window - 0.5
    gy = (xy[:, 1] + 0.5) / window - 0.5
    coords = np.stack([np.clip(np.nan_to_num(gy), 0, ny - 1), np.clip(np.nan_to_num(gx), 0, nx - 1)])
    pu = ndimage.map_coordinates(u, coords, order=1, mode="nearest")
    pv = ndimage.map_coordinates(v, coords, order=1, mode="nearest")
    out = np.stack([pu, pv], axis=1)
    if max_displacement is not None:
        out = np.clip(out, -max_displacement, max_displacement)
    return out
