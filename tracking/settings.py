"""The tracking method's vocabulary: settings, status bits, table dtype, window geometry and rule constants.

Every rule of the method (a threshold, a clip, a bound) is written here once, as a plain Python value.
The host code reads these values; the kernel modules (:mod:`tracking.identify_kernels`,
:mod:`tracking.kernel_constants`, :mod:`tracking.predict_kernels`) read them as ``wp.constant``s defined
from them. This module imports no other module of :mod:`tracking`, so that every step, host or kernel,
can import it.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

import numpy as np

from synthbos import SynthbosError
from synthbos.values import check_ranges

__all__ = [
    "CENTROID_METHODS",
    "DISTORTION_STEPS",
    "MATCH_METHODS",
    "TRACKING_RANGES",
    "TRACK_DTYPE",
    "DotStatus",
    "TrackingSettings",
    "distortion_options",
    "is_valid",
    "prior_inside",
    "residual_reach",
    "start_width",
    "window_sizes",
]

#: Sub-pixel estimators of Brady, Raben and Vlachos (2009) on a dot's segmented map
#: (:func:`tracking.centroid.fit_centroids`); ``TrackingSettings.centroid`` also takes "model".
CENTROID_METHODS = ("gaussian3", "centroid", "gaussian4", "lsq")

#: What the model fit's positions measure on a distorted dot (``TrackingSettings.distortion``).
DISTORTION_STEPS = ("ellipse", "flux", "kernel", "moment", "none")


def distortion_options(distortion: str) -> dict:
    """The moment step's options (:func:`tracking.dotfit.moment_shifts`) for ``TrackingSettings.distortion``:
    the elliptical step, and the shared-kernel step with its kernels fitted (True) or left at their
    elliptical prior ("prior", the "flux" setting).

    Examples
    --------
    >>> distortion_options("flux")
    {'ellipse': False, 'kernel': 'prior'}
    """
    return {"ellipse": distortion == "ellipse", "kernel": {"kernel": True, "flux": "prior"}.get(distortion, False)}

#: Pairings of standard tracking (:mod:`tracking.match`).
MATCH_METHODS = ("nearest", "multiparametric")

# --- rule constants (each read by the host code and, as a ``wp.constant``, by the kernels) -----------------

#: A dot's e^-2 diameter per Gaussian width: ``d = 4 eta``.
DIAMETER_PER_WIDTH = 4.0

#: The image's edge lies this far (px) beyond its outer pixel centres (pixel centres at integers): a prior
#: position further out is OUTSIDE_IMAGE.
PIXEL_EDGE_PX = 0.5

#: The dot map's half-width is ``ceil(d / 2 + MAP_MARGIN_PX)``.
MAP_MARGIN_PX = 0.5

#: Side (px) of the common identification window (3 px dots) that the kernels measure in registers.
SMALL_WINDOW = 7

#: A three-point Gaussian width outside ``(lo, hi) * eta0`` (exclusive) is replaced by ``eta0``.
THREE_POINT_WIDTH_RANGE = (0.3, 3.0)

#: A three-point fit further than this (px) from the peak pixel along x or y is wild: the peak pixel is kept.
WILD_FIT_PX = 1.0

#: The residual image (Eq. 2) subtracts each found dot with its width clipped to ``[lo, hi] * eta0`` ...
RESIDUAL_WIDTH_CLIP = (0.5, 1.5)

#: ... in a stamp of half-width ``ceil(RESIDUAL_STAMP_WIDTHS * eta0)``.
RESIDUAL_STAMP_WIDTHS = 4.5

#: The model fit keeps each dot's width within ``[lo, hi] * eta0``.
MODEL_WIDTH_RANGE = (0.25, 4.0)

#: A model-fit step that takes a dot farther than this (px, along x or y) from its start is refused.
FIT_MAX_MOVE_PX = 1.0

#: The elliptical moment step (``TrackingSettings.distortion`` "ellipse"): a distorted gradient-image dot's
#: elliptical Gaussian is fitted by this many block-Jacobi Gauss-Newton sweeps ...
ELLIPSE_SWEEPS = 4
#: ... each step scaled by this factor (every dot moves at once, against its neighbours' last models) ...
ELLIPSE_DAMPING = 0.7
#: ... with this Levenberg-Marquardt term, relative to the normal matrix's diagonal ...
ELLIPSE_MARQUARDT = 1.0e-2
#: ... moving its centre (px along x or y), the logarithms of its two widths and its shear at most this
#: far per sweep ...
ELLIPSE_MAX_STEP = 0.3
#: ... and keeping each width within this range times its start, ``sqrt(sigma^2 + 1/12)``.
ELLIPSE_WIDTH_RANGE = (0.6, 3.0)
#: The first moment of the dot's share of the light by those models is then taken this many times, the
#: model moved to the last moment (and its flux to the last share's) in between.
ELLIPSE_MOMENT_ITERATIONS = 3

#: The shared-kernel step (``TrackingSettings.distortion`` "kernel", :mod:`tracking.kernel_step`): after the
#: elliptical step, every dot within ``KERNEL_REACH_PX`` of a moving dot of its image takes part (the moving
#: dots' neighbours share their light). Each distorted one (by its own first moment, not only its partner's)
#: gets a non-parametric ray-landing kernel of ``KERNEL_TAPS`` x ``KERNEL_TAPS`` weights on a sub-pixel grid
#: of this step (px); the others keep their elliptical prior ...
KERNEL_GRID_STEP = 1.0 / 3.0
KERNEL_TAPS = 9
#: ... fitted (weighted ridge least squares) to the ``2 KERNEL_WINDOW_HALF + 1`` square window of pixels
#: about the dot, weighted ``exp(-r^2 / (2 KERNEL_WINDOW_SIGMA^2))`` (r in px), and shared there by every dot
#: within ``KERNEL_REACH_PX`` of it (at most ``KERNEL_MAX_NEIGHBOURS`` with itself; more keeps its last one) ...
KERNEL_WINDOW_HALF = 5
KERNEL_WINDOW_SIGMA_PX = 3.0
KERNEL_REACH_PX = 9.0
KERNEL_MAX_NEIGHBOURS = 32
#: ... the ridge, this times the normal matrix's mean diagonal, pulling it towards its prior: the elliptical
#: fit's covariance less the spot's (eigenvalues at least ``KERNEL_PRIOR_MIN_VAR_PX2``) ...
KERNEL_RIDGE = 0.1
KERNEL_PRIOR_MIN_VAR_PX2 = 0.01
#: ... then the shares of every dot's kernel model and the moment are taken this many times, the kernels
#: fitted in the first ``KERNEL_FITS`` of them (more fits moved snapshot 1's p99 at 256 px by under 0.001 px
#: at 2.5 times the cost).
KERNEL_ITERATIONS = 3
KERNEL_FITS = 1
#: The shares are held to the reference flux: every dot's model has its reference partner's flux (its own in
#: the reference image; a dot sends the same rays in both images), and per-dot multipliers ``alpha`` of the
#: models in the shares are fitted, ``KERNEL_FLUX_SWEEPS`` sweeps of iterative proportional fitting per
#: iteration, so that each share holds that flux; a sweep changes ``alpha`` by at most ``KERNEL_FLUX_STEP``
#: times, and ``alpha`` stays within ``1 / KERNEL_FLUX_BOUND`` and ``KERNEL_FLUX_BOUND``.
KERNEL_FLUX_SWEEPS = 40
KERNEL_FLUX_STEP = 2.0
KERNEL_FLUX_BOUND = 1.5

#: Standard tracking pairs within, and the wide search looks as far as, ``max_displacement`` plus this (px)
#: unless ``TrackingSettings.search_radius`` is set.
SEARCH_MARGIN_PX = 1.0

#: EDGE_CUT: a matched dot whose e^-2 disk reaches past the image edge by amounts that differ by more than
#: this (px, along x or y) between the two images.
EDGE_CUT_PX = 0.5

#: The correlation predictor's pyramid ends at a pass that changes no tile's displacement by more than this
#: (px) from the coarser pass's field (interpolated to its tile centres): the field is resolved for the
#: tracker's needs.
PREDICTOR_RESOLVED_PX = 0.25

#: A predictor tile's correlation peak is its plane's largest sample unless other local maxima reach within
#: this fraction of it: then the one nearest the searched displacement (zero in the first pass, the coarser
#: field's in the others). A regular dot grid whose pitch divides the tile correlates circularly alike at
#: every lattice shift (peaks equal to the noise); the nearest is the smallest displacement the images
#: allow, as the paper's search around each dot's own position assumes.
PREDICTOR_PEAK_TIE = 0.1
#: A peak of a predictor tile's correlation plane is its largest sample within this many samples along each
#: axis (a 5 x 5 square): lattice peaks lie a grid's pitch apart (5 px or more for dots of 2 px or more), a
#: broad peak's shoulder next to its top.
PREDICTOR_PEAK_REACH = 2

#: A predictor tile (and the predictor's significance box) takes part only where at least this fraction
#: of its reference pixels is not masked.
PREDICTOR_MIN_VALID_FRACTION = 0.25


class DotStatus(enum.IntFlag):
    """Bit flags of the ``status`` field of :func:`track_pair`'s table.

    FOUND_REFERENCE, FOUND_GRADIENT
        The dot was identified in that image (``x, y`` resp. ``x_gradient, y_gradient`` are finite).
    MATCHED
        Found in both and paired: ``u, v`` are finite. This is the "valid" bit.
    CC_VALID
        The correlation correction gave ``u_cc, v_cc`` (always set with MATCHED unless the correlation
        peak fell on its plane's edge; ``u_cc, v_cc`` are finite whenever MATCHED is set).
    CC_FLAGGED
        The correlation correction disagrees with the centroid difference by more than
        ``TrackingSettings.cc_threshold`` pixels.
    OUTSIDE_IMAGE
        The prior position lies outside the image (or is not finite); nothing was measured.
    NEAR_BORDER
        The dot's window reaches past the image edge.
    SATURATED
        Two or more of the dot's pixels sit at the saturation level; its position is less reliable.
    OVERLAPPED
        The dot's window held more than one blob; Eq. 1 chose among them.
    AMBIGUOUS
        A closer prior dot claimed the same blob in every iteration (only with NOT found).
    FIT_FALLBACK
        The centroid fit fell back to a simpler estimate (e.g. a non-positive neighbour sample).
    MASKED
        The dot (its e^-2 disk, in either image) touches the excluded area of ``track_pair``'s ``mask``;
        it is not measured (never MATCHED).
    PREDICTOR_MISMATCH
        The measured displacement differs from the correlation predictor's by more than
        ``TrackingSettings.predictor_tolerance`` pixels, and from the local linear fit of its matched
        neighbours' displacements too (which would overrule a poor prediction): the blob found is
        probably another dot. ``u, v`` stay NaN (never MATCHED); ``x_gradient, y_gradient`` show what was
        found.
    PREDICTOR_WEAK
        The correlation predictor is not significant at the dot: the normalised correlation of the pair
        around it at the predicted displacement (:func:`tracking.predict.predict_displacement`) is below
        ``TrackingSettings.predictor_min_correlation`` (an unrelated or decorrelated gradient image).
        Never MATCHED.
    EDGE_CUT
        The dot's e^-2 disk (diameter ``d``) reaches past the image edge by amounts that differ by more
        than half a pixel between the two images (a dot entering or leaving the field of view): its
        two positions are pulled inwards by different amounts. Never MATCHED. (A dot cut alike in both
        images keeps NEAR_BORDER only: its biases largely cancel, below 0.1 px with the model fit.)
    OUTLIER
        The displacement fails the normalised median test against the local linear fit of its nearest
        matched neighbours (``TrackingSettings.outlier_threshold``): probably paired with the wrong blob.
        Never MATCHED.
    DISTORTED
        The dot's light in either image was measurably asymmetric (a dot distorted by the flow inside the
        camera's light cone): both its positions are the first moments of its share of the light (the
        mean landing positions of its rays), not the symmetric model's centres
        (``TrackingSettings.distortion``; :func:`tracking.dotfit.moment_shifts`).
    MISREGISTERED
        Standard tracking only (no prior, where nothing says the pattern is dots): the reference image
        around the dot, moved by the measured displacement, does not land on the gradient image. Lucas-Kanade
        steps that register the dot's identification window (half-width ``ceil(d / 2 +
        window_margin)``) onto the gradient image, starting from ``u_cc, v_cc``, end further than
        ``TrackingSettings.registration_tolerance`` from ``u_cc, v_cc`` or from ``u, v``, or cannot be
        solved (:func:`tracking.register.registration_offsets`). On dots this is rare (noise only);
        on speckle, squares or blobs that merge or part between the images it marks the blobs that the dot
        model measured wrongly. Never MATCHED; ``x_gradient, y_gradient`` show what was found.

    Examples
    --------
    >>> from synthbos import DotStatus
    >>> status = DotStatus.FOUND_REFERENCE | DotStatus.FOUND_GRADIENT | DotStatus.MATCHED
    >>> int(status), bool(status & DotStatus.MATCHED), bool(status & DotStatus.OUTLIER)
    (7, True, False)
    """

    FOUND_REFERENCE = 1
    FOUND_GRADIENT = 2
    MATCHED = 4
    CC_VALID = 8
    CC_FLAGGED = 16
    OUTSIDE_IMAGE = 32
    NEAR_BORDER = 64
    SATURATED = 128
    OVERLAPPED = 256
    AMBIGUOUS = 512
    FIT_FALLBACK = 1024
    MASKED = 2048
    PREDICTOR_MISMATCH = 4096
    PREDICTOR_WEAK = 8192
    EDGE_CUT = 16384
    OUTLIER = 32768
    DISTORTED = 65536
    MISREGISTERED = 131072


TRACK_DTYPE = np.dtype(
    [
        ("x", "f8"),
        ("y", "f8"),
        ("u", "f8"),
        ("v", "f8"),
        ("u_cc", "f8"),
        ("v_cc", "f8"),
        ("x_gradient", "f8"),
        ("y_gradient", "f8"),
        ("diameter", "f8"),
        ("peak", "f8"),
        ("status", "i4"),
        ("iteration", "i2"),
        ("iteration_gradient", "i2"),
        ("u_pred", "f8"),
        ("v_pred", "f8"),
        ("pred_correlation", "f8"),
        ("dot_id", "i8"),
    ]
)


def is_valid(table_or_status):
    """True where a row's displacement is valid (the MATCHED bit).

    Parameters
    ----------
    table_or_status : structured array or array of int
        A :func:`track_pair` table (any structured array with a ``status`` field) or its ``status``
        column.

    Returns
    -------
    bool array
        One entry per row.

    Examples
    --------
    >>> import numpy as np
    >>> from synthbos.tracking import TRACK_DTYPE, DotStatus, is_valid
    >>> table = np.zeros(3, dtype=TRACK_DTYPE)
    >>> table["status"] = [DotStatus.MATCHED | DotStatus.CC_VALID, DotStatus.FOUND_REFERENCE, DotStatus.MATCHED]
    >>> is_valid(table)
    array([ True, False,  True])
    >>> is_valid(table["status"])
    array([ True, False,  True])
    """
    status = np.asarray(table_or_status)
    if status.dtype.names is not None:
        if "status" not in status.dtype.names:
            raise SynthbosError(f"is_valid needs a tracking table with a status field; got fields "
                                f"{', '.join(status.dtype.names)}")
        status = status["status"]
    if status.dtype.kind not in "iu":
        raise SynthbosError(f"is_valid needs integer status flags; got dtype {status.dtype}")
    return (status & DotStatus.MATCHED) != 0


# Allowed range of every number of TrackingSettings (``synthbos.values.check_ranges``): finite, with bounds
# past which a run only allocates or iterates without end (a dot window is ~(d + 2 max_displacement)^2 px).
TRACKING_RANGES = {
    "fit_iterations": {"integer": True, "minimum": 1, "maximum": 20},
    "distortion_chi2": {"above": 0.0, "maximum": 1e4},
    "weights": {"list": {"sizes": (3,)}, "minimum": 0.0, "maximum": 1e3},
    "diameter": {"optional": True, "above": 0.0, "maximum": 64.0},
    "window_margin": {"minimum": 0.0, "maximum": 16.0},
    "max_iterations": {"integer": True, "minimum": 1, "maximum": 20},
    "max_displacement": {"above": 0.0, "maximum": 100.0},
    "prior_radius": {"above": 0.0, "maximum": 64.0},
    "cc_threshold": {"above": 0.0, "maximum": 100.0},
    "threshold_fraction": {"minimum": 0.0, "below": 1.0},
    "noise_threshold": {"minimum": 0.0, "maximum": 100.0},
    "detection_snr": {"minimum": 0.0, "maximum": 1e3},
    "min_relative_peak": {"minimum": 0.0, "maximum": 1.0},
    "match_weights": {"list": {"sizes": (3,)}, "minimum": 0.0, "maximum": 1e3},
    "search_radius": {"optional": True, "above": 0.0, "maximum": 128.0},
    "threshold": {"optional": True},
    "n_levels": {"integer": True, "minimum": 1, "maximum": 64},
    "saturation_level": {"optional": True},
    "predictor_windows": {"list": {"max_size": 8}, "integer": True, "minimum": 8, "maximum": 1024},
    "predictor_tolerance": {"above": 0.0, "maximum": 100.0},
    "predictor_min_correlation": {"minimum": -1.0, "maximum": 1.0},
    "outlier_threshold": {"above": 0.0, "infinite": True},
    "outlier_epsilon": {"minimum": 0.0, "maximum": 100.0},
    "outlier_neighbours": {"integer": True, "minimum": 3, "maximum": 64},
    "registration_tolerance": {"above": 0.0, "infinite": True},
}


@dataclass(frozen=True)
class TrackingSettings:
    """Settings of the whole tracking pipeline.

    The defaults are the most accurate estimators (``centroid="model"``, ``correction="model"``);
    :meth:`paper` gives the procedure of Rajendran, Bane and Vlachos (2019) as published
    (``centroid="gaussian3"``, ``correction="paper"``).

    Attributes
    ----------
    centroid : {"model", "gaussian3", "centroid", "gaussian4", "lsq"}
        Sub-pixel estimator. "model" (default): least-squares fit of the pixel-integrated Gaussian dot
        model with peak, width and background free, every dot jointly with its neighbours
        (:func:`tracking.dotfit.fit_dots`): no bias (below 1e-3 px p95 without noise at 20 dots per
        32x32 px) and at the Cramer-Rao bound under white noise. The others are the estimators of
        Brady, Raben and Vlachos (2009) on the dot's segmented map (:func:`tracking.centroid.fit_centroids`).
        On isolated pixel-integrated 3 px dots "gaussian3" (the paper's) and "lsq" are biased by less
        than 1e-3 px, "gaussian4" by 2e-3 px and "centroid" by up to 0.01 px; in a dense pattern the
        neighbours' tails inside the map bias all four (p95 ~0.01 px for "gaussian3" at 20 dots per
        32x32 px), and "gaussian3", using five pixels, has ~1.35x the bound's noise.
    correction : {"model", "paper"}
        How ``u_cc, v_cc`` are measured. "model" (default): the last step of the model fit taken again
        with each pair's common peak and width, for position and background only (the shift that best
        maps the reference dot onto the gradient dot under the dot model, its neighbours at their
        common shapes too); at or below the bound, and never noisier than ``u, v``. "paper": the
        correlation of the two dots' segmented maps with a three-point Gaussian peak fit (Rajendran,
        Bane and Vlachos 2019, section 2.3); the maps' cut and the peak fit bias it (p95 ~0.04 px
        without noise in a dense pattern), so it wins over "gaussian3" only from ~3 % noise.
    fit_iterations : int
        Block-Jacobi Gauss-Newton steps of the model fit (the model correction comes with the last).
        Three leave no zero-noise tail at 20 dots per 32x32 px (largest error ~0.003 px); two are
        ~7 % faster overall and keep a tail of ~1 % of the dots between 0.005 and 0.02 px (p95 < 0.001 px).
    distortion : {"ellipse", "flux", "kernel", "moment", "none"}
        What the model fit's positions are taken to measure on a dot whose image the flow has distorted
        (rays through different parts of the aperture crossing different density spread and skew it).
        "moment": the mean of its light, the mean landing position of its rays that the renderer's truth
        and BOS define: after the fit, each dot moves from the symmetric model's centre to the first
        moment of its share of the light (:func:`tracking.dotfit.moment_shifts`) where that shift is
        significant against the image noise, and is flagged DISTORTED. "ellipse" (default): the same,
        but a moving gradient-image dot's share of a pixel shared with its neighbours is weighed by
        elliptical models fitted to the moving dots (:func:`tracking.ellipse.ellipse_step`), which follow
        light the flow spread along its gradient. "kernel" (opt-in): the elliptical step, then, in every
        pair that holds a moving dot, the shared-kernel step (:func:`tracking.kernel_step.kernel_step`):
        every dot of both images gets a non-parametric ray-landing kernel fitted to the pixels about it and
        shared there by its neighbours, its share held to its reference partner's flux, and the moving dots
        take the first moments of these shares (zero-noise p90 0.0031-0.0068 px on snapshots 0-2 at 256 px
        against the ellipse's 0.0079-0.0371; about 2.5 s of CPU per distorted 256-px pair,
        docs/distortion.md). "flux" (opt-in): the same with every kernel left at its elliptical prior (no
        kernel fit), so that only the shares held to the reference flux act (p90 0.0026-0.0105 px on
        snapshots 0-2; about 0.3 s of CPU per distorted 256-px pair).
        "none": the symmetric model's centre. Only the model estimators (``centroid`` or ``correction``
        "model") use it.
    distortion_chi2 : float
        Significance of that shift: it is applied where ``|d|^2`` exceeds this many times half its
        variance under the image's white noise (a false alarm on an undistorted dot has probability
        ``exp(-distortion_chi2 / 2)``: 3.7e-6 at the default 25, so the fit stays at the Cramer-Rao bound).
    weights : (W_A, W_I, W_dx)
        Blob score weights of Eq. 1 (area, peak intensity, distance from the prediction).
    diameter : float or None
        Dot e^-2 diameter in pixels; None estimates it from the reference image's auto-correlation,
        ``d_p = d_cc / sqrt(2)``.
    window_margin : float
        Pixels added to the dot radius for the identification window (half-width
        ``ceil(d / 2 + window_margin)``).
    max_iterations : int
        Iterations on the residual image (Eq. 2); identification stops earlier when every dot is found or
        an iteration finds no new one.
    max_displacement : float
        Largest expected distance in pixels of a dot's gradient-image position from its prediction (the
        reference position with ``predictor="none"``, so then the largest displacement): the window of a
        second search for dots the first one missed grows by it, and it bounds that search.
    prior_radius : float
        Largest distance in pixels between a dot's peak pixel and its prior position.
    cc_threshold : float
        A correlation correction differing from the centroid difference by more than this (pixels) is
        flagged CC_FLAGGED.
    background : {"ring-median", "minimum"}
        Background of a window, subtracted before fitting and correlating: the median of the window's edge
        pixels (robust to noise and to neighbouring dots) or the window minimum.
    threshold_fraction : float
        Segmentation threshold above the background, as a fraction of the window's peak.
    noise_threshold : float
        The segmentation threshold is at least this many noise standard deviations.
    detection_snr : float
        A blob is a dot only if its peak exceeds the background by this many noise standard deviations ...
    min_relative_peak : float
        ... and by this fraction of the median dot peak of the image.
    matching : {"nearest", "multiparametric"}
        Pairing of standard tracking (no prior).
    match_weights : (w_distance, w_intensity, w_diameter)
        Weights of the multi-parametric match.
    search_radius : float or None
        Pairing radius of standard tracking (around the predicted position); ``max_displacement + 1`` by
        default.
    identification : {"dynamic", "static"}
        Whole-image identification of standard tracking.
    threshold : float or None
        Intensity threshold of standard identification; None: median + ``threshold_fraction`` times the
        range to the 99.9th percentile (at least ``noise_threshold`` sigmas).
    n_levels : int
        Threshold levels of the dynamic segmentation.
    saturation_level : float or None
        Intensity at which pixels saturate; None: the image maximum when five or more pixels share it.
    predictor : {"correlation", "none"}
        Prediction of the gradient-image positions, with and without a prior. "none" is the paper's: the
        reference position, with the window widened by ``max_displacement`` (displacements up to about
        ``max_displacement``). "correlation" (default, an addition) adds the displacement of a
        coarse-to-fine pyramid of window-offset correlations of the pair
        (:func:`tracking.predict.predict_displacement`; shifts up to about a quarter of the first
        window), so the gradient window stays as small as the reference one; dots it misses are looked
        for again in a window widened by ``max_displacement`` around the prediction. Every match is
        checked against the prediction (PREDICTOR_MISMATCH, PREDICTOR_WEAK).
    predictor_windows : tuple of int
        Tile sizes of the predictor's correlation passes, coarse first (a size may repeat: another
        pass at that size); the first should be at least four times the largest displacement. The
        pyramid ends early once a pass changes the field by no more than 0.25 px, so a gentle field
        costs two passes and a strongly varying one goes on to the 16 px tiles. (Until h9b the
        default was (64, 32, 16) window-deformation passes with 50 % overlap.)
    predictor_tolerance : float
        A measured displacement further than this (pixels) from the predicted one is flagged
        PREDICTOR_MISMATCH and not MATCHED.
    predictor_min_correlation : float
        Dots where the predictor's normalised correlation coefficient (its finest tiles at their
        neighbours' displacement, pooled over about 20 dots) is below this are flagged
        PREDICTOR_WEAK and not MATCHED. An unrelated frame gives 0 +- 0.1 (by chance up to ~0.45 in a
        512x512 px image); a right prediction gives 0.9 to 1 at 1 % noise (of the dot peak) and about
        0.8 at 5 %, but only about 0.5 for sparse patterns (6 dots per 32x32 px) at 10 %: lower it for
        such images. -1 disables the test.
    outlier_threshold : float
        Normalised median test of each matched dot's displacement against the local linear fit of its
        ``outlier_neighbours`` nearest matched dots (Westerweel and Scarano 2005 on scattered data, Duncan
        et al. 2010): a dot further from the fit than this times (the neighbours' median distance from
        it + ``outlier_epsilon``) is flagged OUTLIER and not MATCHED; ``inf`` disables the test.
    outlier_epsilon : float
        Measurement noise (px) of the test's normalisation.
    outlier_neighbours : int
        Neighbours of the median test.
    registration_tolerance : float
        Standard tracking (no prior) only: a matched dot whose window, registered onto the gradient image
        by Lucas-Kanade steps from the measured displacement, ends further than this (px) from ``u_cc,
        v_cc`` or ``u, v`` is flagged MISREGISTERED and not MATCHED (the pattern is not dots there);
        ``inf`` disables the check. The registration's own error is ~0.03 px on 3 px dots without noise
        and ~0.09 px at 5 % noise, so 0.25 px flags almost no true dot and keeps every dot measured within
        about 0.5 px.

    Examples
    --------
    >>> from synthbos import TrackingSettings
    >>> TrackingSettings().centroid, TrackingSettings.paper(max_displacement=4.0).centroid
    ('model', 'gaussian3')
    >>> TrackingSettings(max_displacement=4.0).max_displacement  # px, for larger displacements
    4.0
    """

    centroid: str = "model"
    correction: str = "model"
    fit_iterations: int = 3
    distortion: str = "kernel"
    distortion_chi2: float = 25.0
    weights: tuple[float, float, float] = (1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0)
    diameter: float | None = None
    window_margin: float = 1.0
    max_iterations: int = 5
    max_displacement: float = 2.0
    prior_radius: float = 1.5
    cc_threshold: float = 0.5
    background: str = "ring-median"
    threshold_fraction: float = 0.1
    noise_threshold: float = 2.0
    detection_snr: float = 6.0
    min_relative_peak: float = 0.3
    matching: str = "nearest"
    match_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    search_radius: float | None = None
    identification: str = "dynamic"
    threshold: float | None = None
    n_levels: int = 8
    saturation_level: float | None = None
    predictor: str = "correlation"
    predictor_windows: tuple[int, ...] = (64, 32, 16, 16)
    predictor_tolerance: float = 1.5
    predictor_min_correlation: float = 0.5
    outlier_threshold: float = 3.0
    outlier_epsilon: float = 0.2
    outlier_neighbours: int = 12
    registration_tolerance: float = 0.25

    def __post_init__(self):
        check_ranges(self, TRACKING_RANGES, "")
        if self.centroid not in ("model", *CENTROID_METHODS):
            raise SynthbosError(
                f"unknown centroid method {self.centroid!r}; choose one of {('model', *CENTROID_METHODS)}"
            )
        if self.correction not in ("model", "paper"):
            raise SynthbosError(f"unknown correction {self.correction!r}; choose 'model' or 'paper'")
        if self.fit_iterations < 1:
            raise SynthbosError(f"fit_iterations must be at least 1, got {self.fit_iterations}")
        if self.distortion not in DISTORTION_STEPS:
            raise SynthbosError(f"unknown distortion {self.distortion!r}; choose one of {DISTORTION_STEPS}")
        if self.matching not in MATCH_METHODS:
            raise SynthbosError(f"unknown matching {self.matching!r}; choose one of {MATCH_METHODS}")
        if self.background not in ("ring-median", "minimum"):
            raise SynthbosError(f"unknown background {self.background!r}; choose 'ring-median' or 'minimum'")
        if self.identification not in ("dynamic", "static"):
            raise SynthbosError(f"unknown identification {self.identification!r}; choose 'dynamic' or 'static'")
        if self.diameter is not None and not (np.isfinite(self.diameter) and self.diameter > 0):
            raise SynthbosError(f"dot diameter must be a positive number, got {self.diameter!r}")
        if self.predictor not in ("correlation", "none"):
            raise SynthbosError(f"unknown predictor {self.predictor!r}; choose 'correlation' or 'none'")
        if not (np.isfinite(self.predictor_tolerance) and self.predictor_tolerance > 0):
            raise SynthbosError(f"predictor_tolerance must be a positive number, got {self.predictor_tolerance!r}")
        if not (len(self.predictor_windows) and all(int(s) >= 8 for s in self.predictor_windows)):
            raise SynthbosError(
                f"predictor_windows must be window sizes of at least 8 px, got {self.predictor_windows!r}"
            )
        if self.max_iterations < 1:
            raise SynthbosError(f"max_iterations must be at least 1, got {self.max_iterations}")

    @classmethod
    def paper(cls, **overrides):
        """The procedure of Rajendran, Bane and Vlachos (2019): three-point Gaussian, map correlation."""
        return cls(**{"centroid": "gaussian3", "correction": "paper", "distortion": "none", **overrides})

    def as_dict(self):
        """Plain ``{name: value}`` (tuples as lists, None as the string "auto") for file attributes."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = "auto" if v is None else (list(v) if isinstance(v, tuple) else v)
        return out


# --- window geometry -------------------------------------------------------------------------------------


def start_width(median_eta, eta0):
    """The model fit's common starting width: the median three-point width ``median_eta`` less the pixel's
    own (variance 1/12), at least ``eta0 / 2``; ``eta0`` where the median is NaN (no dot found).
    Scalars or arrays (one pair each)."""
    med = np.asarray(median_eta, dtype=np.float64)
    eta0 = np.asarray(eta0, dtype=np.float64)
    width = np.sqrt(np.maximum(np.nan_to_num(med) ** 2 - 1.0 / 12.0, 0.25 * eta0**2))
    return np.where(np.isfinite(med), width, eta0)


def window_sizes(d, settings):
    """``(eta0, half_r, half_g, map_half)`` for dots of e^-2 diameter ``d``: the nominal Gaussian width
    ``d / 4``, the half-widths of the identification windows in the reference image and (widened by
    ``max_displacement``) of the wide search, and the dot map's half-width."""
    return (
        d / DIAMETER_PER_WIDTH,
        int(np.ceil(d / 2.0 + settings.window_margin)),
        int(np.ceil(d / 2.0 + settings.window_margin + settings.max_displacement)),
        int(np.ceil(d / 2.0 + MAP_MARGIN_PX)),
    )


def search_reach(settings) -> float:
    """Radius (px) of the wide search and of standard tracking's pairing: ``search_radius``, or by default
    ``max_displacement`` plus ``SEARCH_MARGIN_PX``.

    Examples
    --------
    >>> search_reach(TrackingSettings(max_displacement=4.0)), search_reach(TrackingSettings(search_radius=2.5))
    (5.0, 2.5)
    """
    return settings.max_displacement + SEARCH_MARGIN_PX if settings.search_radius is None else settings.search_radius


def residual_reach(half, eta0):
    """Distance (px) from a dot still missing within which a found dot leaves the residual image (Eq. 2):
    the window's half-diagonal, the subtracted stamp (``RESIDUAL_STAMP_WIDTHS`` eta0) and a pixel."""
    return half * np.sqrt(2.0) + RESIDUAL_STAMP_WIDTHS * eta0 + 1.0


def prior_inside(prior, shape):
    """True where a prior position (``(..., 2)``, x = column) is finite and within half a pixel beyond the
    outer pixel centres of an image of ``shape``."""
    h, w = shape
    prior = np.asarray(prior, dtype=np.float64)
    fin = np.isfinite(prior).all(axis=-1)
    p = np.where(fin[..., None], prior, -1e9)
    e = PIXEL_EDGE_PX
    return fin & (p[..., 0] > -e) & (p[..., 0] < w - e) & (p[..., 1] > -e) & (p[..., 1] < h - e)
