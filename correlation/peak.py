"""Sub-pixel location of correlation peaks (and of any sampled, peaked signal).

The three-point estimators fit a curve through the peak sample and its two neighbours along each
axis independently (Raffel et al., Particle Image Velocimetry, 3rd ed., section 5.4.4). They work on
whole stacks of planes at once.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PEAK_METHODS", "overlap_weights", "peak_ratio", "subpixel_peak", "three_point_offset"]

PEAK_METHODS = ("gaussian", "parabolic", "centroid")

_TINY = 1e-12


def three_point_offset(left, centre, right, *, method="gaussian"):
    """Sub-sample offset of a peak from three samples at -1, 0 and +1.

    Parameters
    ----------
    left, centre, right : arrays of one shape
        Samples at the peak's neighbours and at the peak.
    method : {"gaussian", "parabolic", "centroid"}
        ``gaussian``: fit of ``exp(a + b t + c t^2)``, offset
        ``(ln L - ln R) / (2 (ln L - 2 ln C + ln R))``; it needs three positive samples, and where
        one is not positive it falls back to the parabolic fit. ``parabolic``:
        ``(L - R) / (2 (L - 2 C + R))``. ``centroid``: ``(R - L) / (L + C + R)``.

    Returns
    -------
    array
        Offsets, clipped to [-0.5, 0.5] (a peak sample is the maximum, so a larger offset would be a
        wrong fit); never NaN: a flat triple gives 0.
    """
    left, centre, right = (np.asarray(a, dtype=np.float64) for a in (left, centre, right))
    if method not in PEAK_METHODS:
        raise ValueError(f"unknown sub-pixel peak method {method!r}; choose one of {PEAK_METHODS}")
    if method == "centroid":
        den = left + centre + right
        off = np.divide(right - left, den, out=np.zeros_like(den), where=np.abs(den) > _TINY)
        return np.clip(off, -0.5, 0.5)
    den = left - 2.0 * centre + right
    parabolic = np.divide(left - right, 2.0 * den, out=np.zeros_like(den), where=den < -_TINY)
    if method == "parabolic":
        return np.clip(parabolic, -0.5, 0.5)
    positive = (left > 0) & (centre > 0) & (right > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ll, lc, lr = (np.log(np.where(positive, a, 1.0)) for a in (left, centre, right))
    gden = ll - 2.0 * lc + lr
    ok = positive & (gden < -_TINY)
    gauss = np.divide(ll - lr, 2.0 * gden, out=np.zeros_like(gden), where=ok)
    return np.clip(np.where(ok, gauss, parabolic), -0.5, 0.5)


def _peak_index(flat, select):
    """Flat index of each plane's highest sample, of ``plane * select`` where ``select`` is given."""
    if select is None:
        return np.argmax(flat, axis=1)
    return np.argmax(flat * np.asarray(select, dtype=flat.dtype).ravel()[None, :], axis=1)


def subpixel_peak(planes, *, method="gaussian", weights=None, select=None):
    """Locate the highest peak of each plane in a stack to sub-pixel accuracy.

    Parameters
    ----------
    planes : (..., h, w) array
        Correlation planes (or any peaked images).
    method : {"gaussian", "parabolic", "centroid"}
        Three-point estimator applied along rows and along columns.
    weights : (h, w) array of positive numbers, optional
        Known smooth factor of the planes that the fit should not see, such as the fraction of the
        window pairs that overlaps at each displacement (:func:`overlap_weights`): the five samples
        of each fit are divided by it (the integer peak is found on the planes as given).
    select : (h, w) array of positive numbers, optional
        The integer peak is the highest sample of ``plane * select`` instead of ``plane``: with
        :func:`overlap_weights`, the peak of a periodic pattern's equal peaks that lies nearest to
        zero displacement (the predictor).

    Returns
    -------
    row, col : (...) float arrays
        Peak position in plane coordinates (index space, pixel centres at integers).
    on_border : (...) bool array
        True where the integer peak lies on the plane's edge; there the missing neighbour is
        taken equal to the peak sample's other neighbour, so the offset is 0 along that axis.
    """
    planes = np.asarray(planes)
    if not np.issubdtype(planes.dtype, np.floating):
        planes = planes.astype(np.float64)
    h, w = planes.shape[-2:]
    flat = planes.reshape(-1, h, w)
    idx = _peak_index(flat.reshape(len(flat), -1), select)
    r, c = np.divmod(idx, w)
    k = np.arange(len(flat))
    on_border = (r == 0) | (r == h - 1) | (c == 0) | (c == w - 1)
    rm, rp = np.clip(r - 1, 0, h - 1), np.clip(r + 1, 0, h - 1)
    cm, cp = np.clip(c - 1, 0, w - 1), np.clip(c + 1, 0, w - 1)
    # only the five samples per plane go to float64
    centre = flat[k, r, c].astype(np.float64)
    # On the border there is no outer neighbour: a symmetric triple gives offset 0 on that axis.
    up = np.where(r == 0, flat[k, rp, c], flat[k, rm, c]).astype(np.float64)
    down = np.where(r == h - 1, flat[k, rm, c], flat[k, rp, c]).astype(np.float64)
    lf = np.where(c == 0, flat[k, r, cp], flat[k, r, cm]).astype(np.float64)
    rt = np.where(c == w - 1, flat[k, r, cm], flat[k, r, cp]).astype(np.float64)
    if weights is not None:
        wgt = np.asarray(weights, dtype=np.float64)
        centre = centre / wgt[r, c]
        up = up / np.where(r == 0, wgt[rp, c], wgt[rm, c])
        down = down / np.where(r == h - 1, wgt[rm, c], wgt[rp, c])
        lf = lf / np.where(c == 0, wgt[r, cp], wgt[r, cm])
        rt = rt / np.where(c == w - 1, wgt[r, cm], wgt[r, cp])
    row = r + three_point_offset(up, centre, down, method=method)
    col = c + three_point_offset(lf, centre, rt, method=method)
    shape = planes.shape[:-2]
    return row.reshape(shape), col.reshape(shape), on_border.reshape(shape)


def overlap_weights(shape):
    """Fraction of a window pair that overlaps at each displacement of a correlation plane.

    Parameters
    ----------
    shape : (h, w)
        Window (and plane) shape; zero displacement at ``(h // 2, w // 2)`` as in
        :func:`correlation.xcorr.cross_correlate`.

    Returns
    -------
    (h, w) float64 array
        ``(1 - |dy| / h) (1 - |dx| / w)``. The correlated part of a window correlation scales with it
        (only dots inside both windows pair up), which pulls a three-point fit towards zero
        displacement by about ``sigma^2 / N`` (``sigma^2`` the peak's variance, 0.08 px for 3 px dots
        in 16 px windows); dividing the fitted samples by it removes that bias (Westerweel, Meas. Sci.
        Technol. 8 (1997) 1379, eq. 17; Raffel et al. 2018, section 5.4.3).
    """
    h, w = shape
    wy = 1.0 - np.abs(np.arange(h) - h // 2) / h
    wx = 1.0 - np.abs(np.arange(w) - w // 2) / w
    return wy[:, None] * wx[None, :]


def peak_ratio(planes, *, exclusion=2, select=None):
    """Ratio of the highest correlation peak to the second highest, per plane.

    Parameters
    ----------
    planes : (..., h, w) array
        Correlation planes.
    exclusion : int
        Half-width of the square around the highest sample that belongs to the first peak.
    select : (h, w) array, optional
        The first peak is the one :func:`subpixel_peak` picks with the same ``select``.

    Returns
    -------
    (...) float64 array
        ``(C1 - Cmin) / (C2 - Cmin)`` with ``C1`` the first peak (the plane maximum), ``C2`` the maximum outside the
        ``(2 exclusion + 1)^2`` square around it and ``Cmin`` the plane minimum: at least 1, finite
        (a flat plane gives 1). Shifting by the minimum keeps the ratio meaningful for mean-subtracted
        planes whose second peak may be negative (Keane and Adrian's detectability, Raffel et al. 2018,
        section 5.5.1).
    """
    planes = np.asarray(planes)
    h, w = planes.shape[-2:]
    flat = planes.reshape(-1, h * w)
    k = np.arange(len(flat))
    idx = _peak_index(flat, select)
    r, c = np.divmod(idx, w)
    c1 = flat[k, idx].astype(np.float64)
    cmin = flat.min(axis=1).astype(np.float64)
    rest = flat.copy()
    # blank the (2 exclusion + 1)^2 square around each maximum in one scatter
    off = np.arange(-exclusion, exclusion + 1)
    rr = r[:, None, None] + off[None, :, None]
    cc = c[:, None, None] + off[None, None, :]
    inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
    kk = np.broadcast_to(k[:, None, None], inside.shape)
    rest[kk[inside], (rr * w + cc)[inside]] = -np.inf
    c2 = rest.max(axis=1).astype(np.float64)
    c2 = np.where(np.isfinite(c2), c2, cmin)  # the first peak filled the plane
    num, den = c1 - cmin, c2 - cmin
    ratio = np.divide(num, den, out=np.ones_like(num), where=den > 0)
    ratio = np.where((den <= 0) & (num > 0), np.finfo(np.float64).max, ratio)
    return ratio.reshape(planes.shape[:-2])
