"""The host engine of the multigrid correlation: each step of :func:`correlation.passes.run_passes` on
NumPy arrays (windows, FFTs, peak fit and validation in NumPy/SciPy), the image deformation on the
settings' Warp device (:func:`correlation.deform.deform_pair`).

This is the reference of the Warp engine (:mod:`correlation.device_pass`): both walk the same
schedule (:func:`correlation.passes.pass_schedule`) and agree to float32 rounding.
"""

from __future__ import annotations

import numpy as np

from .deform import bspline3_coefficients, deform_pair, grid_to_pixels
from .flags import FLAG_BORDER, FLAG_DISAGREE, FLAG_ISOLATED, FLAG_MASKED, FLAG_MEDIAN, FLAG_PEAK_RATIO
from .passes import Measured, pass_schedule, run_passes
from .peak import overlap_weights, peak_ratio, subpixel_peak
from .rules import CONFIRM_CORRELATION, EDGE_MARGIN, SAMPLING_OFFSET
from .validation import fill_by_interpolation, neighbour_median, normalized_median_test
from .windows import extract_windows, window_validity
from .xcorr import cross_correlate, robust_phase_correlate

__all__ = ["HostEngine", "correlate_on_host"]


def _mean_subtracted(wa, wb, valid):
    """Windows minus their mean; with a (K, N, N) pixel weight stack, mean over valid pixels, 0 elsewhere."""
    wa = wa - wa.mean(axis=(-2, -1), keepdims=True, dtype=np.float32)
    wb = wb - wb.mean(axis=(-2, -1), keepdims=True, dtype=np.float32)
    if valid is not None:
        # only the windows with excluded pixels need the weighted means
        part = np.flatnonzero((valid < 1).any(axis=(-2, -1)))
        if len(part):
            vp = valid[part]
            count = np.maximum(vp.sum(axis=(-2, -1), keepdims=True), 1.0)
            for w in (wa, wb):
                wp_ = w[part]
                w[part] = np.where(vp > 0, wp_ - (wp_ * vp).sum(axis=(-2, -1), keepdims=True) / count, 0.0)
    return wa, wb


def _energies(wa, wb):
    """``sqrt(sum a^2 sum b^2)`` of (K, N, N) window stacks (float64)."""
    ea = np.einsum("kij,kij->k", wa, wa, dtype=np.float64)
    eb = np.einsum("kij,kij->k", wb, wb, dtype=np.float64)
    return np.sqrt(ea * eb)


def _correlate_windows(wa, wb, valid, settings):
    """Correlation planes of (K, N, N) window stacks; ``valid`` weights pixels (1 in, 0 out) or is None.

    Returns the planes and, per window pair, the norm that turns a plane value into a correlation
    coefficient (``sqrt(sum a'^2 sum b'^2)`` of the mean-subtracted windows; None with RPC).
    """
    if valid is None:
        # plain mean subtraction: done in the spectrum (the DC bin), no copy of the windows
        if settings.rpc:
            return robust_phase_correlate(
                wa, wb, diameter=settings.rpc_diameter, subtract_mean=True, workers=settings.workers
            ), None
        n = wa.shape[-1] * wa.shape[-2]
        ma = wa.mean(axis=(-2, -1), dtype=np.float64)
        mb = wb.mean(axis=(-2, -1), dtype=np.float64)
        ea = np.einsum("kij,kij->k", wa, wa, dtype=np.float64) - n * ma * ma
        eb = np.einsum("kij,kij->k", wb, wb, dtype=np.float64) - n * mb * mb
        norm = np.sqrt(np.maximum(ea, 0.0) * np.maximum(eb, 0.0))
        return cross_correlate(wa, wb, subtract_mean=True, workers=settings.workers), norm
    wa, wb = _mean_subtracted(wa, wb, valid)
    if settings.rpc:
        return robust_phase_correlate(
            wa, wb, diameter=settings.rpc_diameter, subtract_mean=False, workers=settings.workers
        ), None
    return cross_correlate(wa, wb, subtract_mean=False, workers=settings.workers), _energies(wa, wb)


def _peak_coefficient(planes, norm):
    """Plane maximum as a correlation coefficient; NaN where the norm is None (RPC) or zero."""
    if norm is None:
        return np.full(len(planes), np.nan)
    peak = planes.reshape(len(planes), -1).max(axis=1).astype(np.float64)
    return np.divide(peak, norm, out=np.zeros_like(peak), where=norm > 0)


def _isolated(measured, unmasked):
    """Measured nodes with fewer than two measured neighbours among at least three unmasked ones."""
    m = np.pad(measured, 1).astype(np.int32)
    k = np.pad(unmasked, 1).astype(np.int32)
    ny, nx = measured.shape
    shifts = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
    n_meas = sum(m[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx] for dy, dx in shifts)
    n_open = sum(k[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx] for dy, dx in shifts)
    return measured & (n_open >= 3) & (n_meas < 2)


def _confirmed(u, v, raw, coef, valid, tolerance):
    """Vectors that the previous iteration measured alike and that correlate about as well as their neighbours.

    The second condition (a correlation coefficient at least ``CONFIRM_CORRELATION`` times the
    median of the valid neighbours') keeps a window partly filled with something else (a reflection,
    the edge of the pattern, a patch of unrelated texture) or one with too few dots to pin the peak
    down from being confirmed: it measures the same biased vector every time, but correlates worse.
    """
    ok = np.hypot(u - raw[0], v - raw[1]) <= tolerance
    if not np.all(np.isnan(coef)):  # RPC has no coefficients
        nb_coef, count = neighbour_median(coef, valid)
        ok &= (count == 0) | (coef >= CONFIRM_CORRELATION * nb_coef)
    return ok


def _edge_weights(du, dv, rows, cols, shape, margin):
    """1 where both deformed images are sampled at least ``margin`` px inside the image, else 0.

    Interpolated values there depend on the boundary extension, not on the image, and differ between
    the two deformed images; excluding the same pixels from both windows keeps them alike.
    Returns None when no pixel of the region is affected.
    """
    h, w = shape
    hu, hv = 0.5 * float(np.abs(du).max()), 0.5 * float(np.abs(dv).max())
    band_r, band_c = margin + hv, margin + hu
    near_r = (rows < band_r) | (rows > h - 1 - band_r)
    near_c = (cols < band_c) | (cols > w - 1 - band_c)
    if not (near_r.any() or near_c.any()):
        return None
    weights = np.ones(du.shape, dtype=np.float32)

    def inside(y, x, ahu, ahv):
        return (
            (y - ahv >= margin)
            & (y + ahv <= h - 1 - margin)
            & (x - ahu >= margin)
            & (x + ahu <= w - 1 - margin)
        )

    ir, ic = np.flatnonzero(near_r), np.flatnonzero(near_c)
    weights[ir, :] *= inside(rows[ir, None], cols[None, :], 0.5 * np.abs(du[ir]), 0.5 * np.abs(dv[ir]))
    weights[:, ic] *= inside(rows[:, None], cols[None, ic], 0.5 * np.abs(du[:, ic]), 0.5 * np.abs(dv[:, ic]))
    return weights


class HostEngine:
    """The steps of :func:`correlation.passes.run_passes` on NumPy arrays, for one image pair.

    Parameters
    ----------
    a, b : (H, W) float32 arrays
        The reference and gradient images, normalised (``multigrid._checked_image``).
    valid_px : (H, W) float32 array of 0 and 1, or None
        1 on the pixels that take part in the correlation (no mask: None).
    settings : CorrelationSettings
        With the pattern resolved.
    """

    def __init__(self, a, b, valid_px, settings):
        self.a, self.b, self.valid_px, self.settings = a, b, valid_px, settings
        self.coefs = None  # interpolant of each image, made before the first deformation
        self.win_valid = None  # pixel weights of the current pass's windows (None: all valid)
        self.masked = None  # its windows more than half masked

    def interpolant(self):
        """Cubic B-spline coefficients of both images, or the images themselves (Keys, Lanczos)."""
        if self.settings.interpolator == "cubic":
            self.coefs = (bspline3_coefficients(self.a), bspline3_coefficients(self.b))
        else:
            self.coefs = (self.a, self.b)

    def windows(self, step, previous, field):
        """The (K, N, N) window stacks and their pixel weights, and the predictor ``(pu, pv)`` at the nodes:
        of the images themselves at the first step, else of the images deformed by ``field``."""
        if step.first_of_pass:
            self.win_valid, self.masked = window_validity(self.valid_px, step.grid)
        g, size = step.grid, step.size
        ny, nx = len(g.yc), len(g.xc)
        r0, c0 = int(g.rows[0]), int(g.cols[0])
        pix_valid = self.win_valid
        if field is None:
            img_a, img_b, origin = self.a, self.b, (r0, c0)
            pu = pv = np.zeros((ny, nx))
        else:
            py, px = previous.node
            q = SAMPLING_OFFSET
            du, dv = grid_to_pixels(field, py, px, g.rows + q, g.cols + q)
            pu, pv = grid_to_pixels(field, py, px, *step.node).astype(np.float64)
            img_a, img_b = deform_pair(
                *self.coefs,
                du,
                dv,
                origin=(r0 + q, c0 + q),
                interpolator=self.settings.interpolator,
                device=self.settings.device,
            )
            origin = (0, 0)
            edge = _edge_weights(du, dv, g.rows + q, g.cols + q, self.a.shape, EDGE_MARGIN)
            if edge is not None:
                edge = extract_windows(edge, size, g.step, 0, 0, ny, nx).reshape(-1, size, size)
                pix_valid = edge if self.win_valid is None else edge * self.win_valid
        wa = extract_windows(img_a, size, g.step, *origin, ny, nx).reshape(-1, size, size)
        wb = extract_windows(img_b, size, g.step, *origin, ny, nx).reshape(-1, size, size)
        return (wa, wb, pix_valid), (pu, pv)

    def correlate(self, step, windows):
        """Correlation planes of the window stacks and their norms (:func:`_correlate_windows`)."""
        return _correlate_windows(*windows, self.settings)

    def fit_peaks(self, step, planes, predictor, coarse):
        """The measured field (the predictor plus the peak's offset), its peak ratio and coefficient, and the
        flags of every test before the normalised median test."""
        s, size = self.settings, step.size
        planes, norm = planes
        pu, pv = predictor
        ny, nx = pu.shape
        select = s.peak_selection(size)
        prow, pcol, border = subpixel_peak(
            planes, method=s.subpixel, weights=overlap_weights((size, size)), select=select
        )
        ratio = peak_ratio(planes, select=select).reshape(ny, nx)
        coef = _peak_coefficient(planes, norm).reshape(ny, nx)
        u = pu + (pcol - size // 2).reshape(ny, nx)
        v = pv + (prow - size // 2).reshape(ny, nx)
        flags = np.where(border.reshape(ny, nx), FLAG_BORDER, 0).astype(np.int32)
        weak = ratio < s.peak_ratio_threshold()
        if norm is not None and step.judges_correlation:
            weak |= coef < s.min_correlation
        flags |= np.where(weak, FLAG_PEAK_RATIO, 0).astype(np.int32)
        if coarse is not None:
            far = np.hypot(u - coarse[0], v - coarse[1]) > s.max_disagreement * size
            flags |= np.where(far, FLAG_DISAGREE, 0).astype(np.int32)
        flags |= np.where(self.masked, FLAG_MASKED, 0).astype(np.int32)
        return Measured(u, v, ratio, coef, flags)

    def median_test(self, step, measured, raw):
        """``MEDIAN`` added to the vectors that fail the normalised median test and that ``raw`` (the
        previous iteration, when given) does not confirm."""
        s = self.settings
        u, v, _, coef, flags = measured
        valid = flags == 0
        outliers = normalized_median_test(u, v, epsilon=s.median_epsilon, threshold=s.median_threshold, valid=valid)
        if raw is not None:
            outliers &= ~_confirmed(u, v, (raw.u, raw.v), coef, valid, s.confirm_tolerance)
        return flags | np.where(outliers, FLAG_MEDIAN, 0).astype(np.int32)

    def isolated_test(self, step, flags):
        """``ISOLATED`` added to the measured vectors with too few measured neighbours (:func:`_isolated`)."""
        return flags | np.where(_isolated(flags == 0, ~self.masked), FLAG_ISOLATED, 0).astype(np.int32)

    def fill(self, step, measured, flags):
        """The field with every flagged vector filled from the valid ones (``fill_by_interpolation``)."""
        return fill_by_interpolation(measured.u, measured.v, flags != 0)


def correlate_on_host(a, b, *, settings, valid_px=None):
    """The passes and iterations of :func:`correlation.correlate_pair` with the host engine.

    Parameters
    ----------
    a, b : (H, W) float32 arrays
        The normalised reference and gradient images.
    settings : CorrelationSettings
        With the pattern resolved.
    valid_px : (H, W) float32 array of 0 and 1, optional
        1 on pixels that take part in the correlation (no mask: all).

    Returns
    -------
    dict
        ``u``, ``v`` (filled field), ``peak_ratio``, ``correlation``, ``flags`` of the last iteration on
        its grid, ``node`` (its row and column coordinates) and ``masked`` (its windows more than half
        masked).
    """
    engine = HostEngine(a, b, valid_px, settings)
    steps = pass_schedule(a.shape, settings)
    (u, v), measured, flags = run_passes(engine, steps)
    return {
        "u": u,
        "v": v,
        "peak_ratio": measured.ratio,
        "correlation": measured.coef,
        "flags": flags,
        "node": steps[-1].node,
        "masked": engine.masked,
    }
