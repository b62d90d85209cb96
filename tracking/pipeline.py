"""Dot tracking with prior information and correlation correction (Rajendran, Bane and Vlachos 2019).

:func:`track_pair` takes a reference and a gradient image and returns one row per dot: it is a stack of
one for :func:`tracking.stack.track_pairs`, the method's one orchestration, whatever the settings. With a
prior (predicted reference-image positions of the manufactured dots) every dot is looked for in a small
window around its prediction, iterating on a residual image from which the dots found so far are
removed; without one, dots are identified in each image by dynamic thresholding and paired (standard
tracking). Displacements come both from the difference of the two positions (``u, v``) and from the
correction (``u_cc, v_cc``). By default the positions are a joint least-squares fit of the
pixel-integrated dot model to both images and the correction is that fit with each pair's common shape
(:mod:`tracking.dotfit`); ``TrackingSettings.paper()`` selects the paper's three-point Gaussian and
correlation of the dot maps (:mod:`tracking.correction`).

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

import numpy as np

from synthbos import SynthbosError

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
from .stack import track_pairs

__all__ = ["TRACK_DTYPE", "DotStatus", "TrackingSettings", "is_valid", "track_pair"]


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

    The pair is tracked as a stack of one by :func:`tracking.stack.track_pairs`, the method's one
    orchestration, on ``device``.

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
    ref, grad = _plane("reference", reference), _plane("gradient", gradient)
    if ref.shape != grad.shape:
        raise SynthbosError(f"reference and gradient images differ in shape: {ref.shape} and {grad.shape}")
    prior = None
    if prior_xy is not None:
        prior = np.asarray(prior_xy, dtype=np.float64)
        if prior.ndim != 2 or prior.shape[1] != 2:
            raise SynthbosError(f"prior positions must be an Nx2 array, got shape {prior.shape}")
        if mapping is not None:
            mapped = np.asarray(mapping(prior), dtype=np.float64)
            if mapped.shape != prior.shape:
                raise SynthbosError(
                    f"the mapping must give one (x, y) per prior position, an array of shape {prior.shape}; "
                    f"it gave shape {mapped.shape}"
                )
            prior = mapped
    tables = track_pairs(ref[None], grad[None], prior_xy=prior, mask=mask, settings=settings, device=device)
    return tables[0]


def _plane(name, image):
    """One image as the stack takes it: 2-D, at least 8 x 8 (its values are checked there)."""
    a = np.asarray(image)
    if a.ndim != 2:
        raise SynthbosError(f"{name} image must be 2-D, got shape {a.shape}")
    if min(a.shape) < 8:
        raise SynthbosError(f"{name} image is too small ({a.shape[0]}x{a.shape[1]}), need at least 8x8")
    return a
