"""Dot tracking with prior information and correlation correction (Rajendran, Bane and Vlachos 2019).

:func:`track_pair` takes a reference and a gradient image and returns one row per dot. With a prior and
the default estimators it is a stack of one for the stacked tracker (:func:`tracking.stack.track_pairs`),
with or without a mask; this module keeps the per-pair path of the variants the stack does not run
(standard tracking without a prior, the paper's and the other estimators). With a prior
(predicted reference-image positions of the manufactured dots) every dot is looked for in a small window
around its prediction, iterating on a residual image from which the dots found so far are removed;
without one, dots are identified in each image by dynamic thresholding and paired (standard tracking).
Displacements come both from the difference of the two positions (``u, v``) and from the correction
(``u_cc, v_cc``). By default the positions are a joint least-squares fit of the pixel-integrated dot
model to both images and the correction is that fit with each pair's common shape
(:mod:`tracking.dotfit`); ``TrackingSettings.paper()`` selects the paper's three-point Gaussian and
correlation of the dot maps.

Further additions to the paper: with ``TrackingSettings.predictor = "correlation"`` (the default) the
gradient-image positions are predicted by a coarse-to-fine correlation of the pair (:mod:`tracking.predict`),
so displacements far beyond the window margin are tracked, with and without a prior, and a match is
reported (MATCHED) only where it agrees with that prediction and the prediction is significant
(otherwise PREDICTOR_MISMATCH, PREDICTOR_WEAK); in every mode a dot cut by the image edge (EDGE_CUT) or
failing a median test against its neighbours (OUTLIER) is not MATCHED, and a mask excludes pixels
(MASKED). Without a prior, where nothing says the pattern is dots, a matched dot whose window does not
register onto the gradient image at its displacement is not MATCHED either (MISREGISTERED,
:mod:`tracking.register`; docs/tracking-patterns.md).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from synthbos import SynthbosError

from .correction import correlation_correction
from .diameter import estimate_dot_diameter
from .dotfit import fit_dots, fit_window_half, moment_shifts
from .frame_stats import fill_level, saturation_level
from .identify import (
    blob_properties,
    dynamic_threshold_identification,
    estimate_noise,
    identify_near_predictions,
    static_threshold_identification,
)
from .mask import check_mask, mask_reach, masked_fill, touches
from .match import match_multiparametric, match_nearest
from .neighbours import confirmed_by_neighbours_stack, neighbour_outliers_stack
from .predict import predict_displacement
from .register import local_gradients, registration_offsets, spline_coefficients

# The vocabulary lives in tracking.settings; TRACK_DTYPE, DotStatus, TrackingSettings, is_valid and the
# geometry helpers are also reachable from here, where they were defined until the vocabulary moved.
from .settings import (  # noqa: F401  (re-exported)
    DIAMETER_PER_WIDTH,
    EDGE_CUT_PX,
    MODEL_WIDTH_RANGE,
    PIXEL_EDGE_PX,
    RESIDUAL_STAMP_WIDTHS,
    RESIDUAL_WIDTH_CLIP,
    SEARCH_MARGIN_PX,
    THREE_POINT_WIDTH_RANGE,
    TRACK_DTYPE,
    TRACKING_RANGES,
    WILD_FIT_PX,
    DotStatus,
    TrackingSettings,
    distortion_options,
    is_valid,
    prior_inside,
    residual_reach,
    start_width,
    window_sizes,
)
from .stack import stack_support, track_pairs
from .wide_search import drop_shared_blobs, merge_wide

__all__ = ["TRACK_DTYPE", "DotStatus", "TrackingSettings", "is_valid", "track_pair"]


def _check_image(name, image):
    a = np.asarray(image)
    if a.ndim != 2:
        raise SynthbosError(f"{name} image must be 2-D, got shape {a.shape}")
    if min(a.shape) < 8:
        raise SynthbosError(f"{name} image is too small ({a.shape[0]}x{a.shape[1]}), need at least 8x8")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise SynthbosError(f"{name} image must hold real numbers, got dtype {a.dtype}")
    a = np.asarray(a, dtype=np.float64)  # no copy for float64 input: the images are only read
    lo, hi = a.min(), a.max()  # NaN propagates to both, inf shows in one
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise SynthbosError(f"{name} image contains non-finite pixels (NaN or inf)")
    if lo == 0 and hi == 0:
        raise SynthbosError(f"{name} image is all zero")
    return a, hi


class _Frame(NamedTuple):
    image: np.ndarray
    noise: float
    saturation: float
    fill: float


def _model_start(found, sigma0):
    """Rows found and their starting parameters: the identification's estimate, width ``sigma0``."""
    idx = np.flatnonzero(np.isfinite(found["x"]))
    # The three-point peak is that of the pixel-broadened dot (variance sigma0^2 + 1/12, same flux).
    peak = found["i0"][idx] * (1.0 + 1.0 / (12.0 * sigma0**2))
    start = np.stack([found["x"][idx], found["y"][idx], peak, np.full(idx.size, sigma0), np.zeros(idx.size)], axis=1)
    return idx, start


def _start_sigma(founds, eta0):
    """Common starting width of the model fit, from the widths of the dots found (:func:`start_width`)."""
    eta = np.concatenate([f["eta"][np.isfinite(f["x"])] for f in founds])
    return float(start_width(np.median(eta) if eta.size else np.nan, eta0))


def _fit_models(images, founds, partner, eta0, saturation, noise, settings, device):
    """Joint least-squares fit of the pixel-integrated dot model to every dot found in both images.

    Both images in one call (:func:`tracking.dotfit.fit_dots`), the matched dots paired so that the
    last step also gives their positions at the pair's common shape (the model correction); with
    a ``settings.distortion`` step, the moving dots' positions then move to the first moments of their
    light (:func:`tracking.dotfit.moment_shifts`), and their common-shape positions become those. Returns
    per image a dict of ``params`` (N, 5; NaN where not found), ``ok`` (N,), ``shared_xy`` (N, 2; NaN where
    not matched) and ``moved`` (N,) bool.
    """
    half, render_half = fit_window_half(eta0)
    sigma0 = _start_sigma(founds, eta0)
    starts = [_model_start(found, sigma0) for found in founds]
    (idx_r, start_r), (idx_g, start_g) = starts
    # Row of each fitted dot's partner among the fitted rows of the other image.
    pos_g = np.full(len(founds[1]["x"]), -1)
    pos_g[idx_g] = np.arange(idx_g.size)
    pr = partner[idx_r]
    pair_r = np.where(pr >= 0, pos_g[np.maximum(pr, 0)], -1)
    pair = np.full(idx_r.size + idx_g.size, -1)
    has = np.flatnonzero(pair_r >= 0)
    pair[has] = idx_r.size + pair_r[has]
    pair[idx_r.size + pair_r[has]] = has
    frame = np.r_[np.zeros(idx_r.size, np.int64), np.ones(idx_g.size, np.int64)]
    params, ok, shared = fit_dots(
        images,
        np.vstack([start_r, start_g]),
        half=half,
        render_half=render_half,
        frame=frame,
        partner=pair,
        saturation=saturation,
        iterations=settings.fit_iterations,
        sigma_range=(MODEL_WIDTH_RANGE[0] * eta0, MODEL_WIDTH_RANGE[1] * eta0),
        device=device,
    )
    moved = np.zeros(len(params), dtype=bool)
    if settings.distortion != "none":
        d, moved = moment_shifts(
            images, params, half=render_half, frame=frame, partner=pair, saturation=saturation, noise=noise,
            chi2=settings.distortion_chi2, **distortion_options(settings.distortion), device=device,
        )  # fmt: skip
        params[:, :2] += d
        shared[moved] = np.where(np.isfinite(shared[moved]), params[moved, :2], np.nan)
    fits = []
    for (idx, _), found, rows in zip(starts, founds, (slice(0, idx_r.size), slice(idx_r.size, None)), strict=True):
        n = len(found["x"])
        f = {"params": np.full((n, 5), np.nan), "ok": np.zeros(n, dtype=bool), "shared_xy": np.full((n, 2), np.nan),
             "moved": np.zeros(n, dtype=bool)}  # fmt: skip
        for key, value in (("params", params), ("ok", ok), ("shared_xy", shared), ("moved", moved)):
            f[key][idx] = value[rows]
        fits.append(f)
    return fits


def _take_model(found, fit):
    """Use the model fit's position, width and peak (failed fits keep their last step, flagged)."""
    params = fit["params"]
    has = np.isfinite(params[:, 0])
    found["x"] = np.where(has, params[:, 0], found["x"])
    found["y"] = np.where(has, params[:, 1], found["y"])
    found["eta"] = np.where(has, params[:, 3], found["eta"])
    found["i0"] = np.where(has, params[:, 2], found["i0"])
    found["flags"][has & ~fit["ok"]] |= DotStatus.FIT_FALLBACK
    found["flags"][has & fit["moved"]] |= DotStatus.DISTORTED


def _auto_threshold(image, settings, noise):
    if settings.threshold is not None:
        return float(settings.threshold)
    med = float(np.median(image))
    top = float(np.percentile(image, 99.9))
    return med + max(settings.threshold_fraction * (top - med), settings.noise_threshold * noise)


def _standard_candidates(image, settings, noise):
    thr = _auto_threshold(image, settings, noise)
    if settings.identification == "dynamic":
        labels, _ = dynamic_threshold_identification(image, threshold=thr, n_levels=settings.n_levels)
    else:
        labels, _ = static_threshold_identification(image, threshold=thr)
    props = blob_properties(image, labels)
    return np.stack([props["x"], props["y"]], axis=1)


def _neighbour_options(settings):
    return {"k": settings.outlier_neighbours, "threshold": settings.outlier_threshold,
            "epsilon": settings.outlier_epsilon}  # fmt: skip


def _confirmed_by_neighbours(out, good, query, settings, device):
    """True where a queried dot's displacement agrees with the local linear fit of the ``good`` dots'
    (within the outlier test and ``predictor_tolerance``): its neighbours overrule a poor prediction
    (the correlation is least reliable in the windows at the image edge). The stacked test
    (:func:`tracking.neighbours.confirmed_by_neighbours_stack`) on a stack of one."""
    if not query.any():  # (the usual case: nothing to confirm, nothing to launch)
        return np.zeros(len(query), dtype=bool)
    xy = np.stack([out["x"], out["y"]], axis=1)
    uv = np.stack([out["x_gradient"], out["y_gradient"]], axis=1) - xy
    ok = confirmed_by_neighbours_stack(xy[None], uv[None], good[None], query[None], **_neighbour_options(settings),
                                       tolerance=settings.predictor_tolerance, device=device)  # fmt: skip
    return ok.numpy()[0].astype(bool)


def _neighbour_outliers(xy, uv, settings, device):
    """True where a vector is further from the local linear fit of its ``settings.outlier_neighbours``
    nearest vectors than ``outlier_threshold`` times (their median distance from that fit +
    ``outlier_epsilon``; :mod:`tracking.neighbours`): a normalised median test
    for scattered data (Westerweel and Scarano 2005, eq. 2, with a local linear reference as in Duncan
    et al. 2010 so that smooth gradients do not count as outliers), in two rounds. The stacked test
    (:func:`tracking.neighbours.neighbour_outliers_stack`) on a stack of one."""
    if len(xy) == 0:
        return np.zeros(0, dtype=bool)
    valid = np.ones((1, len(xy)), dtype=np.int32)
    bad = neighbour_outliers_stack(xy[None], uv[None], valid, **_neighbour_options(settings), device=device)
    return bad.numpy()[0].astype(bool)


def _corrections(out, r, g, pi, m, fits, settings):
    """The correction ``(u_cc, v_cc, cc_ok)`` of the rows ``m`` (matched; ``pi`` their gradient-image rows);
    where it failed (``cc_ok`` False) the centroid difference stands in."""
    if m.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool)
    gi = pi[m]
    if settings.correction == "model":
        # The model correction: both positions refitted with the pair's common peak and width.
        du = fits[1]["shared_xy"][gi] - fits[0]["shared_xy"][m]
        ucc, vcc = du[:, 0], du[:, 1]
        cc_ok = np.isfinite(ucc) & np.isfinite(vcc)
        ucc = np.where(cc_ok, ucc, out["x_gradient"][m] - out["x"][m])
        vcc = np.where(cc_ok, vcc, out["y_gradient"][m] - out["y"][m])
    else:
        # The paper's correlation correction: both dot maps are centred on their peak pixels, so the
        # displacement is the peak pixels' offset plus the correlation peak's.
        du, dv, cc_ok = correlation_correction(r["dotmap"][m], g["dotmap"][gi], max_shift=2)
        ucc = g["root"][gi, 0] - r["root"][m, 0] + du
        vcc = g["root"][gi, 1] - r["root"][m, 1] + dv
    return ucc, vcc, cc_ok


def _misregistered(images, out, m, uv_cc, half, settings, device):
    """True where row ``m``'s window, registered onto the gradient image from ``uv_cc``
    (:mod:`tracking.register`), ends further than ``settings.registration_tolerance`` from ``uv_cc`` or
    from the centroid difference, or cannot be registered (the MISREGISTERED rule)."""
    xy = np.stack([out["x"][m], out["y"][m]], axis=1)
    uv = np.stack(uv_cc, axis=1)
    coef = spline_coefficients(images[1])
    grads = local_gradients(xy, uv, k=settings.outlier_neighbours)
    c, ok = registration_offsets(images[0], coef, xy, uv, half=half, gradients=grads, device=device)
    centroid = np.stack([out["x_gradient"][m], out["y_gradient"][m]], axis=1) - xy
    far = np.hypot(c[:, 0], c[:, 1]) > settings.registration_tolerance
    far |= np.hypot(*(uv + c - centroid).T) > settings.registration_tolerance
    return far | ~ok


#: A dot whose e^-2 disk reaches past the image edge by amounts that differ by more than this (px) between
#: the two images is flagged EDGE_CUT: the truncation biases of its two centroids no longer cancel (the
#: measured overshoots understate the difference, as both centroids are pulled inwards).
def _overshoot(x, y, radius, shape):
    """(N, 2): how far (px) a disk of ``radius`` at (x, y) reaches past the image area, along x and y."""
    h, w = shape
    e = PIXEL_EDGE_PX
    ox = np.maximum(np.maximum(-e - (x - radius), (x + radius) - (w - e)), 0.0)
    oy = np.maximum(np.maximum(-e - (y - radius), (y + radius) - (h - e)), 0.0)
    return np.stack([ox, oy], axis=1)






def track_pair(
    reference,
    gradient,
    *,
    prior_xy=None,
    mapping=None,
    mask=None,
    settings: TrackingSettings | None = None,
    device=None,
):
    """Track every dot from the reference to the gradient image.

    Parameters
    ----------
    reference, gradient : (H, W) arrays
        The image pair (any real dtype).
    prior_xy : (N, 2) array, optional
        Predicted reference-image positions of the pattern's dots (x = column, y = row, pixel centres at
        integers), or target positions when ``mapping`` is given. Without it, standard tracking:
        dots are identified in both images and paired.
    mapping : callable, optional
        Calibration mapping target -> image (e.g. :func:`tracking.calibration.fit_soloff`'s result),
        applied to ``prior_xy``.
    mask : (H, W) bool array, optional
        True on the pixels to EXCLUDE (a model, a reflection, the outside of a window), as in
        :func:`synthbos.correlation.correlate_pair`; 0/1 arrays are accepted. Excluded pixels take no
        part in identification or in the correlation predictor. A dot whose e^-2 disk touches the
        excluded area in either image is flagged MASKED and not measured (with a prior its row stays,
        NaN; without one, no dot is identified in the excluded area itself).
    settings : TrackingSettings, optional
        Defaults to ``TrackingSettings()``.
    device : str or None, optional
        Warp device of the kernels ("cpu", "cuda:0"); Warp's default when None.

    Returns
    -------
    numpy structured array of dtype :data:`TRACK_DTYPE`, one row per prior dot in the prior's order (row i
    is prior dot i), or per dot identified in the reference image without a prior. Fields:

    ``x, y`` (f8)
        Reference-image position, px (x = column, y = row, pixel centres at integers).
    ``u, v`` (f8)
        Displacement by centroid difference, px.
    ``u_cc, v_cc`` (f8)
        Displacement by correlation correction, px.
    ``x_gradient, y_gradient`` (f8)
        Gradient-image position, px.
    ``diameter`` (f8)
        e^-2 diameter ``4 eta`` of the Gaussian fitted to the reference dot, px.
    ``peak`` (f8)
        Its peak intensity ``I0`` above the background.
    ``status`` (i4)
        :class:`DotStatus` bit flags; MATCHED marks a valid row.
    ``iteration, iteration_gradient`` (i2)
        Iteration of the residual scheme in which the dot was found in each image (1 = first; 0 = not found).
    ``u_pred, v_pred`` (f8)
        Displacement predicted by the correlation predictor, px (NaN with ``predictor="none"``).
    ``pred_correlation`` (f8)
        The predictor's local normalised correlation at the dot (its significance, about 1 for a good
        prediction, about 0 for an unrelated gradient image; NaN with ``predictor="none"``).
    ``dot_id`` (i8)
        The prior's row the dot belongs to (row i of ``prior_xy``: i), or -1 without a prior (the dots
        identified in the reference image carry no identity).

    Values that could not be measured are NaN, and the status says why; a MATCHED row has finite
    ``x, y, u, v, u_cc, v_cc, x_gradient, y_gradient, diameter, peak``.

    Raises
    ------
    synthbos.SynthbosError
        Images of different shapes, not 2-D, all zero or with non-finite pixels; a prior that is not Nx2 or
        lies entirely outside the image; a diameter that cannot be estimated; a mask of the wrong shape
        or type, or one that excludes every pixel.

    Notes
    -----
    The result does not depend on a constant added to either image (every background is estimated), so
    dark dots on a bright background are tracked by giving ``max - image`` for both images.

    With a prior and settings the stacked tracker runs (:func:`tracking.stack.stack_support`: the default
    estimators), the pair is tracked as a stack of one by :func:`tracking.stack.track_pairs` on
    ``device``, its mask too.

    Examples
    --------
    >>> import numpy as np
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> table = synthbos.track_pair(pair.reference, pair.gradient, prior_xy=synthbos.nominal_prior(pair))
    >>> len(table) == pair.n_dots  # one row per prior dot
    True
    >>> ok = synthbos.is_valid(table) & pair.valid
    >>> error = np.hypot(table["u"][ok] - pair.displacement_px[ok, 0], table["v"][ok] - pair.displacement_px[ok, 1])
    >>> bool(np.percentile(error, 90) < 0.05)  # px
    True
    """
    settings = TrackingSettings() if settings is None else settings
    ref, grad, tops, excluded = _checked_images(reference, gradient, mask)
    prior = None if prior_xy is None else _checked_prior(prior_xy, mapping, ref.shape)
    if prior is not None and stack_support(settings) is None:
        # the stacked tracker's variants: one orchestration, this pair a stack of one
        mask1 = None if excluded is None else excluded[None]
        return track_pairs(ref[None], grad[None], prior_xy=prior, mask=mask1, settings=settings, device=device)[0]
    run = _setup(ref, grad, tops, excluded, settings, device)
    if prior is not None:
        r, g, pred = _dots_from_prior(run, prior)
        partner = np.arange(len(prior))
    else:
        r, g, partner, pred = _dots_without_prior(run)
    fits = None
    if settings.centroid == "model" or settings.correction == "model":
        saturation = (run.frame_r.saturation, run.frame_g.saturation)
        noise = (run.frame_r.noise, run.frame_g.noise)
        fits = _fit_models((ref, grad), (r, g), partner, run.eta0, saturation, noise, settings, device)
    if settings.centroid == "model":
        _take_model(r, fits[0])
        _take_model(g, fits[1])
    return _table(run, r, g, partner, prior, pred, fits)


class _Run(NamedTuple):
    """What every step of one pair's tracking reads: the images, the settings and the window geometry."""

    ref: np.ndarray
    grad: np.ndarray
    excluded: np.ndarray | None
    settings: TrackingSettings
    device: object
    diameter: float
    eta0: float
    half_r: int
    half_g: int
    map_half: int
    frame_r: _Frame
    frame_g: _Frame
    search: float
    near_mask: np.ndarray | None


def _checked_images(reference, gradient, mask):
    """The two images checked, their maxima (None where a mask filled them) and the checked mask."""
    ref, top_r = _check_image("reference", reference)
    grad, top_g = _check_image("gradient", gradient)
    if ref.shape != grad.shape:
        raise SynthbosError(f"reference and gradient images differ in shape: {ref.shape} and {grad.shape}")
    excluded = check_mask(mask, ref.shape)
    if excluded is not None:
        ref, grad = masked_fill(ref, excluded), masked_fill(grad, excluded)
        top_r = top_g = None  # the maxima of the filled images
    return ref, grad, (top_r, top_g), excluded


def _checked_prior(prior_xy, mapping, shape):
    """The prior positions checked and mapped into the image; some must lie inside it."""
    h_img, w_img = shape
    prior = np.asarray(prior_xy, dtype=np.float64)
    if prior.ndim != 2 or prior.shape[1] != 2:
        raise SynthbosError(f"prior positions must be an Nx2 array, got shape {prior.shape}")
    if mapping is not None:
        prior = np.asarray(mapping(prior), dtype=np.float64).reshape(-1, 2)
    if not prior_inside(prior, (h_img, w_img)).any():
        raise SynthbosError(f"no prior dot lies inside the {h_img}x{w_img} image")
    return prior


def _setup(ref, grad, tops, excluded, settings, device):
    """The dot diameter, window geometry, both frames' statistics and the mask's reach."""
    d = settings.diameter
    if d is None:
        d = estimate_dot_diameter(ref)
        if not (np.isfinite(d) and d > 0):
            raise SynthbosError("cannot estimate the dot diameter from the reference image; give it in settings")
    eta0, half_r, half_g, map_half = window_sizes(d, settings)
    noise_r, noise_g = estimate_noise(ref, excluded=excluded), estimate_noise(grad, excluded=excluded)
    frame_r = _Frame(ref, noise_r, saturation_level(ref, settings.saturation_level, tops[0]), fill_level(ref))
    frame_g = _Frame(grad, noise_g, saturation_level(grad, settings.saturation_level, tops[1]), fill_level(grad))
    search = settings.max_displacement + SEARCH_MARGIN_PX if settings.search_radius is None else settings.search_radius
    near_mask = None
    if excluded is not None:
        near_mask = mask_reach(excluded, d)
    return _Run(
        ref, grad, excluded, settings, device, d, eta0, half_r, half_g, map_half, frame_r, frame_g, search, near_mask
    )


def _predict(run, xy):
    """The correlation predictor's displacement and coefficient at ``xy``."""
    return predict_displacement(
        run.ref, run.grad, xy, window_sizes=run.settings.predictor_windows, mask=run.excluded, device=run.device
    )


def _find(run, frame, pred, *, wide=False, standard=False):
    """One call of the identification: the prior's narrow window, the paper's wide one, or standard."""
    settings = run.settings
    return identify_near_predictions(
        frame.image,
        pred,
        half=run.half_g if wide else run.half_r,
        map_half=run.map_half,
        radius=1.0 if standard else (run.search if wide else settings.prior_radius),
        settings=settings,
        eta0=run.eta0,
        max_iterations=1 if standard else settings.max_iterations,
        noise=frame.noise,
        sat_level=frame.saturation,
        fill=frame.fill,
        device=run.device,
    )


def _dots_from_prior(run, prior):
    """The dots of both images found from the prior (the gradient image's around the prediction) and the
    predictor's (displacement, coefficient), None without the predictor."""
    r = _find(run, run.frame_r, prior)
    found_r = np.isfinite(r["x"])
    base = np.where(found_r[:, None], np.stack([r["x"], r["y"]], axis=1), prior)
    if run.settings.predictor != "correlation":
        return r, _find(run, run.frame_g, base, wide=True), None
    pred_uv, pred_q = _predict(run, base)
    pred_g = base + np.nan_to_num(pred_uv)
    g = _find(run, run.frame_g, pred_g)
    # Dots the prediction missed get the paper's wide window, around the prediction.
    miss = np.flatnonzero(~np.isfinite(g["x"]) & found_r)
    if miss.size:
        merge_wide(g, _find(run, run.frame_g, pred_g[miss], wide=True), miss)
        drop_shared_blobs(g, pred_g)
    return r, g, (pred_uv, pred_q)


def _dots_without_prior(run):
    """Standard tracking: the dots of each image found on their own and paired; returns both images'
    dots, the partner of each reference dot and the predictor's (displacement, coefficient) or None."""
    settings, excluded = run.settings, run.excluded
    cand_r = _standard_candidates(run.ref, settings, run.frame_r.noise)
    cand_g = _standard_candidates(run.grad, settings, run.frame_g.noise)
    if excluded is not None:
        cand_r = cand_r[~touches(excluded, cand_r)]
        cand_g = cand_g[~touches(excluded, cand_g)]
    r = _find(run, run.frame_r, cand_r, standard=True)
    g = _find(run, run.frame_g, cand_g, standard=True)
    r = {k: v[np.isfinite(r["x"])] for k, v in r.items()}
    g = {k: v[np.isfinite(g["x"])] for k, v in g.items()}
    rxy = np.stack([r["x"], r["y"]], axis=1)
    gxy = np.stack([g["x"], g["y"]], axis=1)
    pred = None
    if settings.predictor == "correlation":
        pred = _predict(run, rxy)
        rxy = rxy + np.nan_to_num(pred[0])  # pair around the predicted gradient-image positions
    if settings.matching == "nearest":
        return r, g, match_nearest(rxy, gxy, radius=run.search), pred
    sizes = (4 * r["eta"], 4 * g["eta"])
    partner = match_multiparametric(
        rxy, gxy, r["i0"], g["i0"], *sizes, radius=run.search, weights=settings.match_weights
    )
    return r, g, partner, pred


def _positions(r, g, partner, *, with_prior):
    """The table with both images' positions, widths and iterations, its status bits so far, which
    reference and gradient dots were found and each reference dot's partner index (0 where none)."""
    n = len(r["x"])
    out = np.zeros(n, dtype=TRACK_DTYPE)
    for name in ("u", "v", "u_cc", "v_cc", "x_gradient", "y_gradient"):
        out[name] = np.nan
    out["x"], out["y"] = r["x"], r["y"]
    out["diameter"] = DIAMETER_PER_WIDTH * r["eta"]
    out["peak"] = r["i0"]
    out["iteration"] = r["iteration"]
    status = r["flags"].astype(np.int32)
    found_r = np.isfinite(r["x"])
    status[found_r] |= DotStatus.FOUND_REFERENCE
    ng = len(g["x"])
    has_p = partner >= 0
    pi = np.where(has_p, partner, 0)
    gx = g["x"][pi] if ng else np.full(n, np.nan)
    gy = g["y"][pi] if ng else np.full(n, np.nan)
    found_g = has_p & np.isfinite(gx)
    out["x_gradient"] = np.where(found_g, gx, np.nan)
    out["y_gradient"] = np.where(found_g, gy, np.nan)
    out["iteration_gradient"] = np.where(found_g, g["iteration"][pi] if ng else 0, 0)
    if with_prior:
        status |= g["flags"].astype(np.int32) & ~np.int32(DotStatus.OUTSIDE_IMAGE)
    status[found_g] |= DotStatus.FOUND_GRADIENT
    status[found_g] |= g["flags"][pi[found_g]].astype(np.int32) & np.int32(DotStatus.DISTORTED)
    return out, status, found_r, found_g, pi


def _predictor_test(out, status, matched, found_r, found_g, pred, settings, device):
    """The predictor's columns and its tests (PREDICTOR_MISMATCH unless the neighbours confirm the
    displacement, PREDICTOR_WEAK); returns the pairs still matched."""
    out["u_pred"] = out["v_pred"] = out["pred_correlation"] = np.nan
    if pred is None:
        return matched
    pred_uv, pred_q = pred
    out["u_pred"], out["v_pred"], out["pred_correlation"] = pred_uv[:, 0], pred_uv[:, 1], pred_q
    du = out["x_gradient"] - out["x"] - pred_uv[:, 0]
    dv = out["y_gradient"] - out["y"] - pred_uv[:, 1]
    off = found_r & found_g & ~(np.hypot(du, dv) <= settings.predictor_tolerance)
    weak = found_r & ~(pred_q >= settings.predictor_min_correlation)
    off &= ~_confirmed_by_neighbours(out, matched & ~off & ~weak, off & ~weak, settings, device)
    status[off] |= DotStatus.PREDICTOR_MISMATCH
    status[weak] |= DotStatus.PREDICTOR_WEAK
    return matched & ~(off | weak)


def _table(run, r, g, partner, prior, pred, fits):
    """The per-dot table (``TRACK_DTYPE``) from both images' dots: the mask, predictor, edge-cut and
    neighbour tests, the corrections and the status bits."""
    settings, device = run.settings, run.device
    out, status, found_r, found_g, pi = _positions(r, g, partner, with_prior=prior is not None)
    matched = found_r & found_g
    if run.near_mask is not None:
        hidden = touches(run.near_mask, np.stack([out["x"], out["y"]], axis=1))
        hidden |= touches(run.near_mask, np.stack([out["x_gradient"], out["y_gradient"]], axis=1))
        if prior is not None:
            hidden |= touches(run.near_mask, prior)
        status[hidden] |= DotStatus.MASKED
        matched &= ~hidden
    matched = _predictor_test(out, status, matched, found_r, found_g, pred, settings, device)
    over = [
        _overshoot(out[cx], out[cy], run.diameter / 2.0, run.ref.shape)
        for cx, cy in (("x", "y"), ("x_gradient", "y_gradient"))
    ]
    cut = (np.abs(over[0] - over[1]) > EDGE_CUT_PX).any(axis=1)
    cut &= matched
    status[cut] |= DotStatus.EDGE_CUT
    matched &= ~cut
    mi = np.flatnonzero(matched)
    wrong = _neighbour_outliers(
        np.stack([out["x"][mi], out["y"][mi]], axis=1),
        np.stack([out["x_gradient"][mi] - out["x"][mi], out["y_gradient"][mi] - out["y"][mi]], axis=1),
        settings,
        device,
    )
    status[mi[wrong]] |= DotStatus.OUTLIER
    matched[mi[wrong]] = False
    m = np.flatnonzero(matched)
    ucc, vcc, cc_ok = _corrections(out, r, g, pi, m, fits, settings)
    if prior is None and m.size and np.isfinite(settings.registration_tolerance):
        off = _misregistered((run.ref, run.grad), out, m, (ucc, vcc), run.half_r, settings, device)
        status[m[off]] |= DotStatus.MISREGISTERED
        matched[m[off]] = False
        m, ucc, vcc, cc_ok = m[~off], ucc[~off], vcc[~off], cc_ok[~off]
    status[matched] |= DotStatus.MATCHED
    out["u"] = np.where(matched, out["x_gradient"] - out["x"], np.nan)
    out["v"] = np.where(matched, out["y_gradient"] - out["y"], np.nan)
    if m.size:
        out["u_cc"][m], out["v_cc"][m] = ucc, vcc
        st = status[m]
        st[cc_ok] |= DotStatus.CC_VALID
        off = np.hypot(ucc - out["u"][m], vcc - out["v"][m]) > settings.cc_threshold
        st[off] |= DotStatus.CC_FLAGGED
        status[m] = st
    out["status"] = status
    out["dot_id"] = np.arange(len(out)) if prior is not None else -1
    return out
