"""Scoring of BOS processing methods against the ray-traced ground truth.

Pure functions, arrays in and arrays out. The conventions follow section 4 of Rajendran, Bane &
Vlachos (2019): errors are magnitudes of the vector difference between a measured and the true
displacement (px); error sets are split at a displacement threshold equal to half the standard
deviation of the theoretical (Eq. 4) displacement magnitudes; distributions are reported as CDFs and
percentiles.

How the truth reaches each method's points
------------------------------------------
* Tracking measures at dots: its error at a dot is measured minus the dot's own ray-traced
  displacement (no interpolation).
* Correlation measures on a grid of window centres: the truth there is the dot displacements
  interpolated linearly (barycentric interpolation on the Delaunay triangulation of the reference dot
  positions) to the window centre. Window centres outside the convex hull of the valid dots are
  not scored.
* A dense method (optical flow) measures at every pixel: its field is sampled bilinearly at each
  dot's reference position (``sample_field``) and scored there, like tracking. Dots whose four
  neighbouring pixels are not all measured are not scored.
* Displacement gradients: on the correlation grid, central differences of the measured and of the
  interpolated true field on the same grid; at dots, a least-squares plane through each dot and its
  nearest neighbours, fitted to the measured and to the true displacements alike. The error is the
  Frobenius norm of the difference of the 2 x 2 gradient tensors (px / px).
* In-cone spread: how much the flow spreads each dot's rays, ``raytrace.pairfile.in_cone_spread_px``
  (the root of the trace of the ray covariance added by the flow, px). Errors at dots take their dot's
  spread; errors at window centres take the dots' spreads interpolated like the truth. The error
  budget splits every error set into the bins ``SPREAD_BINS``.
* Density: the reconstructed depth-averaged density against the renderer's two truths (the cone of
  rays of each dot, and its chief ray) on the integration grid; errors in kg/m^3 and relative to the
  truth's range (max - min over the grid), RMS and percentiles of the absolute error.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import cKDTree
from synthbos.integration import triangulate
from synthbos.tracking.crlb import position_crlb

from synthbos.memo import RecentResults

__all__ = [
    "PERCENTILES",
    "SPREAD_BINS",
    "cramer_rao_displacement",
    "density_errors",
    "empirical_cdf",
    "error_percentiles",
    "grid_gradient",
    "interpolate_dots",
    "interpolate_truth",
    "sample_field",
    "scattered_gradient",
    "split_threshold",
    "spread_bin_masks",
    "vector_errors",
]

PERCENTILES = (50, 68, 90, 95, 99)

#: The error budget's bins of in-cone spread (name, lower edge px, upper edge px; lower edge included).
#: Chosen from tracking at zero noise on the default set-up (256 x 256 px, 1,000 rays per dot, f/11,
#: snapshots 0-4, one pair each: 6,341 dots, the renderer's recorded ray covariances; 2026-11-26): below
#: 0.05 px its error p90 is 0.0001 px, the level of exact dot images ("undistorted"); 0.05-0.2 px gives
#: p90 0.0006-0.004 px, below the 0.01 px the paper reports and below the noise at 1 % ("mild"); 0.2-0.5
#: px gives p90 0.011-0.039 px ("distorted"); beyond 0.5 px p90 0.10-0.14 px ("strong").
SPREAD_BINS = (("undistorted", 0.0, 0.05), ("mild", 0.05, 0.2), ("distorted", 0.2, 0.5),
               ("strong", 0.5, float("inf")))


def vector_errors(measured, truth):
    """Magnitude of the difference of two (N, 2) displacement sets; NaN where either is missing."""
    d = np.asarray(measured, dtype=np.float64) - np.asarray(truth, dtype=np.float64)
    return np.hypot(d[..., 0], d[..., 1])


def split_threshold(theory_px):
    """Half the standard deviation of the theoretical displacement magnitudes (Eq. 4), in px."""
    mag = np.hypot(*np.asarray(theory_px, dtype=np.float64).reshape(-1, 2).T)
    mag = mag[np.isfinite(mag)]
    return 0.5 * float(np.std(mag)) if len(mag) else 0.0


def empirical_cdf(errors, *, max_points=None):
    """Sorted finite errors and their cumulative probabilities k / n (k = 1..n).

    With ``max_points`` (for plotting), at most about that many of the n points are kept: every
    (n / max_points)-th, plus the 16 smallest and the 64 largest errors, each with its exact probability.
    Drawn as a step curve, it departs from the full one by less than ``1 / max_points`` in probability
    (below a pixel of a figure), while a campaign's hundreds of thousands of errors per curve would
    cost seconds to draw and megabytes of PDF.
    """
    e = np.sort(np.asarray(errors, dtype=np.float64)[np.isfinite(errors)])
    n = len(e)
    y = np.arange(1, n + 1) / max(n, 1)
    if max_points is None or n <= max_points + 80:
        return e, y
    keep = np.unique(np.concatenate([np.rint(np.linspace(0, n - 1, int(max_points))).astype(np.int64),
                                     np.arange(16), np.arange(n - 64, n)]))
    return e[keep], y[keep]


def error_percentiles(errors, percentiles=PERCENTILES):
    """Percentiles of the finite errors (NaN when there are none), as a dict {p: value}."""
    e = np.asarray(errors, dtype=np.float64)
    e = e[np.isfinite(e)]
    if len(e) == 0:
        return {p: float("nan") for p in percentiles}
    return {p: float(v) for p, v in zip(percentiles, np.percentile(e, percentiles), strict=True)}


def interpolate_truth(dot_xy, dot_disp, points_xy):
    """Linear (Delaunay barycentric) interpolation of dot displacements to points; NaN outside the hull."""
    ok = np.all(np.isfinite(dot_xy), axis=1) & np.all(np.isfinite(dot_disp), axis=1)
    # the pair's dots: the same points for every item of a pair, triangulated once (``triangulate``)
    interp = LinearNDInterpolator(triangulate(np.asarray(dot_xy)[ok]), np.asarray(dot_disp)[ok], fill_value=np.nan)
    pts = np.asarray(points_xy, dtype=np.float64)
    return interp(pts.reshape(-1, 2)).reshape(*pts.shape[:-1], 2)


def interpolate_dots(dot_xy, values, points_xy):
    """Linear (Delaunay barycentric) interpolation of per-dot values (N,) or (N, k) to points (M, 2).

    Dots whose position or value is not finite are left out; NaN outside the hull of the others, and
    everywhere when fewer than three remain.
    """
    dot_xy = np.asarray(dot_xy, dtype=np.float64)
    vals = np.asarray(values, dtype=np.float64)
    flat = vals.reshape(len(vals), -1)
    ok = np.all(np.isfinite(dot_xy), axis=1) & np.all(np.isfinite(flat), axis=1)
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    if ok.sum() < 3:
        return np.full((len(pts), *vals.shape[1:]), np.nan)
    interp = LinearNDInterpolator(triangulate(dot_xy[ok]), flat[ok], fill_value=np.nan)
    return interp(pts).reshape(len(pts), *vals.shape[1:])


def spread_bin_masks(spread) -> dict:
    """Masks of the points in each bin of ``SPREAD_BINS`` (name -> bool array); NaN spreads in none."""
    s = np.asarray(spread, dtype=np.float64)
    return {name: (s >= lo) & (s < hi) for name, lo, hi in SPREAD_BINS}


def sample_field(field, points_xy):
    """Bilinear samples of a dense (H, W, C) or (H, W) field at points (x = column, y = row; pixel centres
    at integers).

    Points in the outer half pixel of the image take the value at the nearest pixel centre's row or
    column; NaN beyond the image, or where one of the four neighbours is NaN.
    """
    f = np.asarray(field, dtype=np.float64)
    if f.ndim == 2:
        return sample_field(f[..., None], points_xy)[..., 0]
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    h, w = f.shape[:2]
    inside = np.all(np.isfinite(pts), axis=1) & np.all((pts >= -0.5) & (pts <= [w - 0.5, h - 0.5]), axis=1)
    x = np.clip(np.where(inside, pts[:, 0], 0.0), 0, w - 1)
    y = np.clip(np.where(inside, pts[:, 1], 0.0), 0, h - 1)
    x0 = np.clip(np.floor(x).astype(np.int64), 0, max(w - 2, 0))
    y0 = np.clip(np.floor(y).astype(np.int64), 0, max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    out = (1 - fy) * ((1 - fx) * f[y0, x0] + fx * f[y0, x1]) + fy * ((1 - fx) * f[y1, x0] + fx * f[y1, x1])
    out[~inside] = np.nan
    return out.reshape(*np.shape(points_xy)[:-1], *f.shape[2:])


def grid_gradient(u, v, x, y):
    """Displacement gradient on a regular grid by central differences.

    Parameters
    ----------
    u, v : (ny, nx) arrays
    x, y : (ny, nx) grid coordinates (px); rows share y, columns share x.

    Returns
    -------
    (ny, nx, 2, 2) array: [[du/dx, du/dy], [dv/dx, dv/dy]]; NaN where a neighbour is missing.
    """
    dx = float(np.median(np.diff(x[0]))) if x.shape[1] > 1 else 1.0
    dy = float(np.median(np.diff(y[:, 0]))) if y.shape[0] > 1 else 1.0
    out = np.full((*u.shape, 2, 2), np.nan)
    for k, f in enumerate((u, v)):
        if u.shape[1] > 2:
            out[:, 1:-1, k, 0] = (f[:, 2:] - f[:, :-2]) / (2 * dx)
        if u.shape[0] > 2:
            out[1:-1, :, k, 1] = (f[2:, :] - f[:-2, :]) / (2 * dy)
    return out


def scattered_gradient(xy, disp, *, neighbours=8):
    """Displacement gradient at scattered dots: least-squares plane through each dot and its neighbours.

    Parameters
    ----------
    xy : (N, 2) dot positions (px)
    disp : (N, 2) displacements, or (m, N, 2): m displacement fields at the same dots (a measured and a
        true one), fitted with one neighbour search; rows with NaN are skipped.
    neighbours : int
        Neighbours used besides the dot itself.

    Returns
    -------
    (N, 2, 2) array, or (m, N, 2, 2): [[du/dx, du/dy], [dv/dx, dv/dy]]; NaN for skipped dots.

    Notes
    -----
    Each field is fitted exactly as on its own; fields whose skipped dots are the same share the
    neighbours and the normal matrices of the fits, which are also remembered for the last few dot
    sets (a campaign's items of one pair mostly measure the same dots).
    """
    xy = np.asarray(xy, dtype=np.float64)
    disp = np.asarray(disp, dtype=np.float64)
    fields = disp[None] if disp.ndim == 2 else disp
    xy_ok = np.all(np.isfinite(xy), axis=1)
    out = np.full((len(fields), len(xy), 2, 2), np.nan)
    shared_ok = fit = None
    for f, field in enumerate(fields):
        ok = xy_ok & np.all(np.isfinite(field), axis=1)
        if shared_ok is None or not np.array_equal(ok, shared_ok):
            idx_ok = np.flatnonzero(ok)
            k = min(neighbours + 1, len(idx_ok))
            pts = xy[idx_ok]
            shared_ok = ok
            fit = _plane_fits.get([pts], lambda pts=pts, k=k: _plane_fit(pts, k), extra=k) if k >= 3 else None
        if fit is None:
            continue
        nn, a, ata, good = fit
        b = field[idx_ok][nn]  # (n, k, 2)
        atb = np.einsum("nki,nkj->nij", a, b)
        coef = np.full((len(idx_ok), 3, 2), np.nan)
        coef[good] = np.linalg.solve(ata[good], atb[good])
        # coef[:, 1, c] = d disp_c / dx, coef[:, 2, c] = d disp_c / dy
        out[f, idx_ok] = np.transpose(coef[:, 1:, :], (0, 2, 1))
    return out[0] if disp.ndim == 2 else out


_plane_fits = RecentResults(4)  # a campaign's items of one pair mostly measure the same dots


def _plane_fit(pts, k):
    """What the plane fits at the dots ``pts`` share whatever the field: each dot's ``k`` nearest dots
    (itself included), the design matrices, their normal matrices, and which of those are regular."""
    _, nn = cKDTree(pts).query(pts, k=k)
    dx = pts[nn] - pts[:, None, :]  # (n, k, 2)
    a = np.concatenate([np.ones((*dx.shape[:2], 1)), dx], axis=2)  # columns: 1, dx, dy
    ata = np.einsum("nki,nkj->nij", a, a)
    good = np.abs(np.linalg.det(ata)) > 1e-9
    for v in (nn, a, ata, good):
        v.flags.writeable = False  # shared by the items that measure the same dots
    return nn, a, ata, good


def cramer_rao_displacement(noise_percent, *, peak=1.0, diameter=3.0):
    """Cramér-Rao bound of one axis of a displacement (px) of an isolated dot under pixel noise.

    The position bound is that of the pixel-integrated Gaussian dot model with its peak, width and
    background unknown (``tracking.crlb.position_crlb``; about 0.92 sigma_n / I0 per axis for a 3 px
    dot); a displacement is the difference of two independent positions, so sqrt(2) times it.
    """
    sigma_n = noise_percent / 100.0 * peak
    if sigma_n == 0:
        return 0.0
    centre = np.array([[16.3, 16.6]])  # an isolated dot off the pixel grid, well inside a 33 x 33 image
    pos = position_crlb(centre, (33, 33), diameter=diameter, noise=sigma_n, peak=peak)[0, 0]
    return float(np.sqrt(2.0) * pos)


def density_errors(density, truth, *, region=None, percentiles=(50, 90, 95, 99)):
    """Error of a reconstructed density against a truth on the same grid.

    Parameters
    ----------
    density, truth : (ny, nx) arrays, kg/m^3; NaN where absent.
    region : (ny, nx) bool array, optional
        The reference region; the mean error there is reported as ``offset_kg_m3`` (the part of the
        error that a different constant of integration would remove).

    Returns
    -------
    dict
        ``n``, ``range_kg_m3`` (max - min of the truth), ``rms_kg_m3``, ``p{k}_kg_m3`` (percentiles of
        the absolute error), the same divided by the range as ``rms_rel``, ``p{k}_rel``, and
        ``offset_kg_m3``.
    """
    d, t = np.asarray(density, np.float64), np.asarray(truth, np.float64)
    ok = np.isfinite(d) & np.isfinite(t)
    err = (d - t)[ok]
    rng = float(np.ptp(t[np.isfinite(t)])) if np.isfinite(t).any() else float("nan")
    out = {"n": int(ok.sum()), "range_kg_m3": rng}
    rms = float(np.sqrt(np.mean(err**2))) if len(err) else float("nan")
    pct = error_percentiles(np.abs(err), percentiles)
    out["rms_kg_m3"] = rms
    out.update({f"p{k}_kg_m3": v for k, v in pct.items()})
    scale = rng if rng > 0 else float("nan")
    out["rms_rel"] = rms / scale
    out.update({f"p{k}_rel": v / scale for k, v in pct.items()})
    sel = ok & (np.asarray(region, bool) if region is not None else True)
    out["offset_kg_m3"] = float(np.mean((d - t)[sel])) if sel.any() else float("nan")
    return out
