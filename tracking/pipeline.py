"""Dot tracking with prior information and correlation correction (Rajendran, Bane and Vlachos 2019).

:func:`track_pair` takes a reference and a gradient image and returns one row per dot. With a prior
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

import dataclasses
import enum
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from synthbos.correlation.median_test import residual_limit
from synthbos.correlation.windows import checked_mask

from synthbos import SynthbosError
from synthbos.values import check_ranges

from .centroid import CENTROID_METHODS, fit_centroids, gaussian3_from_samples
from .correction import correlation_correction
from .diameter import estimate_dot_diameter
from .dotfit import fit_dots, fit_dots_numpy, fit_window_half, moment_shifts, moment_shifts_numpy
from .identify import (
    blob_properties,
    dynamic_threshold_identification,
    estimate_noise,
    static_threshold_identification,
)
from .match import MATCH_METHODS, match_multiparametric, match_nearest
from .neighbours import neighbour_fit, neighbour_fit_numpy
from .predict import predict_displacement
from .register import local_gradients, registration_offsets, registration_offsets_numpy, spline_coefficients
from .residual import subtract_gaussians
from .windows import measure_windows, measure_windows_numpy

__all__ = ["TRACK_DTYPE", "DotStatus", "TrackingSettings", "is_valid", "track_pair"]


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
        (``TrackingSettings.distortion``; :func:`tracking.dotfit.moment_shifts_numpy`).
    MISREGISTERED
        Standard tracking only (no prior, where nothing says the pattern is dots): the reference image
        around the dot, moved by the measured displacement, does not land on the gradient image. Lucas-Kanade
        steps that register the dot's identification window (half-width ``ceil(d / 2 +
        window_margin)``) onto the gradient image, starting from ``u_cc, v_cc``, end further than
        ``TrackingSettings.registration_tolerance`` from ``u_cc, v_cc`` or from ``u, v``, or cannot be
        solved (:func:`tracking.register.registration_offsets_numpy`). On dots this is rare (noise only);
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
    distortion : {"moment", "none"}
        What the model fit's positions are taken to measure on a dot whose image the flow has distorted
        (rays through different parts of the aperture crossing different density spread and skew it).
        "moment" (default): the mean of its light, the mean landing position of its rays that the
        renderer's truth and BOS define: after the fit, each dot moves from the symmetric model's centre
        to the first moment of its share of the light (:func:`tracking.dotfit.moment_shifts`) where that
        shift is significant against the image noise, and is flagged DISTORTED. "none": the symmetric
        model's centre. Only the model estimators (``centroid`` or ``correction`` "model") use it.
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
    backend : {"warp", "numpy"}
        The per-dot window step as a Warp kernel or as the NumPy reference (same results).

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
    distortion: str = "moment"
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
    backend: str = "warp"

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
        if self.distortion not in ("moment", "none"):
            raise SynthbosError(f"unknown distortion {self.distortion!r}; choose 'moment' or 'none'")
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
        if self.backend not in ("warp", "numpy"):
            raise SynthbosError(f"unknown backend {self.backend!r}; choose 'warp' or 'numpy'")
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


def _saturation_level(image, level, top=None):
    """The given level, or the image's maximum (``top`` where known) if five or more pixels reach it."""
    if level is not None:
        return float(level)
    top = image.max() if top is None else top
    return float(top) if np.count_nonzero(image == top) >= 5 else np.inf


def _identify(image, pred, *, half, map_half, radius, settings, eta0, max_iterations, noise, sat_level, fill, device):
    """Find one dot near each predicted position, iterating on the residual image (Eqs. 1 and 2).

    ``fill`` is the value of the pixels outside the image (the median background, :func:`_fill_level`).
    Returns a dict of per-dot arrays: x, y, eta, i0, iteration, flags, root (N, 2) = (col, row) of the
    dot's peak pixel, and, for the paper's correction (the only user), dotmap (N, c, c): its
    background-free pixels centred on the peak, others zero.
    """
    h_img, w_img = image.shape
    n = len(pred)
    c = 2 * map_half + 1
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
    # every comparison with NaN is false and +-inf fails one of the bounds: non-finite rows are outside
    px, py = pred[:, 0], pred[:, 1]
    inside = (px > -0.5) & (px < w_img - 0.5)
    inside &= py > -0.5
    inside &= py < h_img - 0.5
    out["flags"][~inside] |= DotStatus.OUTSIDE_IMAGE
    origin_all = np.rint(np.where(inside[:, None], pred, 0.0)).astype(np.int64)
    origin_all -= half
    ox, oy = origin_all[:, 0], origin_all[:, 1]
    border = (ox < 0) | (oy < 0)
    border |= ox + 2 * half >= w_img
    border |= oy + 2 * half >= h_img
    out["flags"][inside & border] |= DotStatus.NEAR_BORDER
    todo = inside.copy()
    subtracted = np.zeros(n, dtype=bool)
    residual = image
    ref_peak = None
    measure = measure_windows if settings.backend == "warp" else measure_windows_numpy
    method = "gaussian3" if settings.centroid == "model" else settings.centroid
    # the three-point start needs only the centre of the dot maps
    extra = {"device": device, "full_maps": keep_maps or method != "gaussian3"} if settings.backend == "warp" else {}
    for it in range(1, max_iterations + 1):
        sel = np.flatnonzero(todo)
        if sel.size == 0:
            break
        every = sel.size == n  # the first round, all inside (the usual case): no gather
        origin = origin_all if every else origin_all[sel]
        m = measure(
            residual,
            origin,
            (pred if every else pred[sel]) - origin,
            half=half,
            map_half=map_half,
            radius=radius,
            threshold_fraction=settings.threshold_fraction,
            noise_floor=settings.noise_threshold * noise,
            weights=settings.weights,
            use_minimum=settings.background == "minimum",
            saturation=sat_level,
            fill=fill,
            **extra,
        )
        has = m["chosen"] >= 0
        cpeak = m["peak"]
        if ref_peak is None:
            ref_peak = _median(cpeak[has]) if has.any() else 0.0
        ok = has & (cpeak > settings.detection_snr * noise) & (cpeak > settings.min_relative_peak * ref_peak)
        ok &= cpeak > 0
        w = 2 * half + 1
        root_r, root_c = np.divmod(np.maximum(m["chosen"], 0), w)
        root_c += origin[:, 0]
        root_r += origin[:, 1]
        # Two prior dots may claim one blob: the nearer keeps it, the other waits for the residual image.
        absroot = (root_r + 2 * w) * (w_img + 4 * w) + (root_c + 2 * w)
        cidx = np.flatnonzero(ok)
        claimed = np.sort(absroot[cidx])
        if cidx.size < 2 or (claimed[1:] != claimed[:-1]).all():
            win_idx = cidx  # every blob claimed once (the usual case): nothing to resolve
        else:
            order = cidx[np.lexsort((m["dist"][cidx], absroot[cidx]))]
            first = np.ones(len(order), dtype=bool)
            first[1:] = absroot[order][1:] != absroot[order][:-1]
            win_idx = order[first]
            out["flags"][sel[order[~first]]] |= DotStatus.AMBIGUOUS
        if win_idx.size == 0:
            break
        # The model fit (centroid="model") starts from the three-point estimate, which needs only the
        # peak pixel and its four neighbours.
        if method == "gaussian3":
            if "cross" in m:  # the kernel cut only the centre cross: peak, left, right, up, down
                cross = m["cross"]
            else:
                k0 = map_half * c + map_half
                cross = m["dotmap"].reshape(len(sel), c * c)[:, [k0, k0 - 1, k0 + 1, k0 - c, k0 + c]]
            # the five samples as contiguous rows (the three-point fit's array operations read them often)
            dx, dy, eta, i0, fit_ok = gaussian3_from_samples(*np.take(cross.T, win_idx, axis=1))
            xw, yw = map_half + dx, map_half + dy
        else:
            dotmap = m["dotmap"][win_idx]
            hc = np.full(len(win_idx), map_half)
            xw, yw, eta, i0, fit_ok = fit_centroids(dotmap, method=method, peak_rc=(hc, hc), mask=dotmap != 0)
        # A wild fit (beyond the peak pixel's neighbours) falls back to the peak pixel.
        wild = ~(np.isfinite(xw) & np.isfinite(yw)) | (np.abs(xw - map_half) > 1.0) | (np.abs(yw - map_half) > 1.0)
        xw = np.where(wild, map_half, xw)
        yw = np.where(wild, map_half, yw)
        fit_ok &= ~wild
        eta_ok = np.isfinite(eta) & (eta > 0.3 * eta0) & (eta < 3.0 * eta0)
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
            # Eq. 2, applied where it matters: found dots near a dot still missing leave the image.
            found = np.flatnonzero(np.isfinite(out["x"]) & ~subtracted)
            if found.size:
                fxy = np.stack([out["x"][found], out["y"][found]], axis=1)
                near = cKDTree(fxy).query_ball_point(pred[todo], residual_reach(half, eta0))
                near = np.unique(
                    np.concatenate([np.asarray(a, dtype=np.int64) for a in near] + [np.zeros(0, np.int64)])
                )
                if near.size:
                    idx = found[near]
                    residual = subtract_gaussians(
                        residual,
                        fxy[near],
                        out["i0"][idx],
                        np.clip(out["eta"][idx], 0.5 * eta0, 1.5 * eta0),
                        radius=int(np.ceil(4.5 * eta0)),
                    )
                    subtracted[idx] = True
    return out


def _median(a):
    """``np.median`` of a 1-D float array (the mean of the middle two for even sizes), by one partial sort
    of ``a`` in place; NaN input goes to NumPy."""
    k = a.size // 2
    a.partition(k)
    if np.isnan(a[k:]).any():  # NaN sorts last, so one would be in the upper half
        return float(np.median(a))
    if a.size % 2:
        return float(a[k])
    return float((a[:k].max() + a[k]) / 2.0)


class _Frame(NamedTuple):
    image: np.ndarray
    noise: float
    saturation: float
    fill: float


def _fill_level(image):
    """Value of the pixels outside the image in the windows: the median of every fourth row and column."""
    return _median(image[::4, ::4].flatten())  # np.median's value; flatten copies


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
        d / 4.0,
        int(np.ceil(d / 2.0 + settings.window_margin)),
        int(np.ceil(d / 2.0 + settings.window_margin + settings.max_displacement)),
        int(np.ceil(d / 2.0 + 0.5)),
    )


def residual_reach(half, eta0):
    """Distance (px) from a dot still missing within which a found dot leaves the residual image (Eq. 2):
    the window's half-diagonal, the subtracted stamp (4.5 eta0) and a pixel."""
    return half * np.sqrt(2.0) + 4.5 * eta0 + 1.0


def prior_inside(prior, shape):
    """True where a prior position (``(..., 2)``, x = column) is finite and within half a pixel beyond the
    outer pixel centres of an image of ``shape``."""
    h, w = shape
    prior = np.asarray(prior, dtype=np.float64)
    fin = np.isfinite(prior).all(axis=-1)
    p = np.where(fin[..., None], prior, -1e9)
    return fin & (p[..., 0] > -0.5) & (p[..., 0] < w - 0.5) & (p[..., 1] > -0.5) & (p[..., 1] < h - 0.5)


def _fit_models(images, founds, partner, eta0, saturation, noise, settings, device):
    """Joint least-squares fit of the pixel-integrated dot model to every dot found in both images.

    Both images in one call (:func:`tracking.dotfit.fit_dots`), the matched dots paired so that the
    last step also gives their positions at the pair's common shape (the model correction); with
    ``settings.distortion == "moment"``, the positions (both kinds) then move to the first moments of
    the dots' light (:func:`tracking.dotfit.moment_shifts`). Returns per image a dict of ``params``
    (N, 5; NaN where not found), ``ok`` (N,), ``shared_xy`` (N, 2; NaN where not matched) and ``moved``
    (N,) bool.
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
    fit = fit_dots if settings.backend == "warp" else fit_dots_numpy
    extra = {"device": device} if settings.backend == "warp" else {}
    frame = np.r_[np.zeros(idx_r.size, np.int64), np.ones(idx_g.size, np.int64)]
    params, ok, shared = fit(
        images,
        np.vstack([start_r, start_g]),
        half=half,
        render_half=render_half,
        frame=frame,
        partner=pair,
        saturation=saturation,
        iterations=settings.fit_iterations,
        sigma_range=(0.25 * eta0, 4.0 * eta0),
        **extra,
    )
    moved = np.zeros(len(params), dtype=bool)
    if settings.distortion == "moment":
        shift = moment_shifts if settings.backend == "warp" else moment_shifts_numpy
        d, moved = shift(
            images, params, half=render_half, frame=frame, partner=pair, saturation=saturation, noise=noise,
            chi2=settings.distortion_chi2, **extra,
        )  # fmt: skip
        params[:, :2] += d
        shared += d
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


def _drop_shared_blobs(found, pred):
    """Where two dots ended up on one blob (peak pixel), keep the one nearer its prediction."""
    ok = np.flatnonzero(np.isfinite(found["x"]))
    if ok.size < 2:
        return
    key = found["root"][ok, 1] * (found["root"][ok, 0].max() + 1) + found["root"][ok, 0]
    dist = np.hypot(found["x"][ok] - pred[ok, 0], found["y"][ok] - pred[ok, 1])
    order = np.lexsort((dist, key))
    dup = np.zeros(len(ok), dtype=bool)
    dup[order[1:]] = key[order][1:] == key[order][:-1]
    lose = ok[dup]
    for name in ("x", "y", "eta", "i0"):
        found[name][lose] = np.nan
    found["iteration"][lose] = 0
    found["flags"][lose] |= DotStatus.AMBIGUOUS


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


def _neighbour_fit(xy, uv, query, self_index, settings, device, *, return_neighbours=False):
    """:func:`tracking.neighbours.neighbour_fit` with ``settings.outlier_neighbours``, on the settings' backend."""
    k = settings.outlier_neighbours
    if settings.backend == "warp":
        return neighbour_fit(xy, uv, query, self_index, k=k, return_neighbours=return_neighbours, device=device)
    return neighbour_fit_numpy(xy, uv, query, self_index, k=k, return_neighbours=return_neighbours)


def _confirmed_by_neighbours(out, good, query, settings, device):
    """True where a queried dot's displacement agrees with the local linear fit of the ``good`` dots'
    (within the outlier test and ``predictor_tolerance``): its neighbours overrule a poor prediction
    (the correlation is least reliable in the windows at the image edge)."""
    ok = np.zeros(len(good), dtype=bool)
    gi, qi = np.flatnonzero(good), np.flatnonzero(query)
    k = settings.outlier_neighbours
    if qi.size == 0 or gi.size <= k + 3 or not np.isfinite(settings.outlier_threshold):
        return ok

    def xy_uv(i):
        xy = np.stack([out["x"][i], out["y"][i]], axis=1)
        return xy, np.stack([out["x_gradient"][i], out["y_gradient"][i]], axis=1) - xy

    gxy, guv = xy_uv(gi)
    qxy, quv = xy_uv(qi)
    fit, spread = _neighbour_fit(gxy, guv, qxy, np.full(len(qi), -1), settings, device)
    r = np.linalg.norm(quv - fit, axis=1)
    limit = residual_limit(spread, epsilon=settings.outlier_epsilon, threshold=settings.outlier_threshold)
    limit = np.minimum(limit, settings.predictor_tolerance)
    ok[qi] = r <= limit
    return ok


def _neighbour_outliers(xy, uv, settings, device):
    """True where a vector is further from the local linear fit of its ``settings.outlier_neighbours``
    nearest vectors than ``outlier_threshold`` times (their median distance from that fit +
    ``outlier_epsilon``; :mod:`tracking.neighbours`): a normalised median test
    for scattered data (Westerweel and Scarano 2005, eq. 2, with a local linear reference as in Duncan
    et al. 2010 so that smooth gradients do not count as outliers). Two rounds: the second fits only
    the vectors the first one kept (refitted only where a neighbour was dropped: elsewhere the nearest
    kept vectors are the same, and so is the fit)."""
    n = len(xy)
    neighbours, epsilon, threshold = settings.outlier_neighbours, settings.outlier_epsilon, settings.outlier_threshold
    if n <= neighbours + 3 or not np.isfinite(threshold):
        return np.zeros(n, dtype=bool)

    def far(fit, spread):  # |uv - fit| (the root of the sum of the two squares, as np.linalg.norm's) beyond the limit
        d = uv - fit
        limit = residual_limit(spread, epsilon=epsilon, threshold=threshold)
        return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) > limit

    own = np.arange(n)
    fit, spread, near = _neighbour_fit(xy, uv, xy, own, settings, device, return_neighbours=True)
    bad = far(fit, spread)
    clean = np.flatnonzero(~bad)
    if bad.any() and len(clean) > neighbours + 3:
        where = np.full(n, -1)
        where[clean] = np.arange(len(clean))
        redo = np.flatnonzero(bad[near].any(axis=1))
        fit[redo], spread[redo] = _neighbour_fit(xy[clean], uv[clean], xy[redo], where[redo], settings, device)
        bad = far(fit, spread)
    return bad


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
    if settings.backend == "warp":
        c, ok = registration_offsets(images[0], coef, xy, uv, half=half, gradients=grads, device=device)
    else:
        c, ok = registration_offsets_numpy(images[0], coef, xy, uv, half=half, gradients=grads)
    centroid = np.stack([out["x_gradient"][m], out["y_gradient"][m]], axis=1) - xy
    far = np.hypot(c[:, 0], c[:, 1]) > settings.registration_tolerance
    far |= np.hypot(*(uv + c - centroid).T) > settings.registration_tolerance
    return far | ~ok


#: A dot whose e^-2 disk reaches past the image edge by amounts that differ by more than this (px) between
#: the two images is flagged EDGE_CUT: the truncation biases of its two centroids no longer cancel (the
#: measured overshoots understate the difference, as both centroids are pulled inwards).
_EDGE_CUT_PX = 0.5


def _overshoot(x, y, radius, shape):
    """(N, 2): how far (px) a disk of ``radius`` at (x, y) reaches past the image area, along x and y."""
    h, w = shape
    ox = np.maximum(np.maximum(-0.5 - (x - radius), (x + radius) - (w - 0.5)), 0.0)
    oy = np.maximum(np.maximum(-0.5 - (y - radius), (y + radius) - (h - 0.5)), 0.0)
    return np.stack([ox, oy], axis=1)


def _disk(radius):
    r = int(np.ceil(radius))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return xx * xx + yy * yy <= radius * radius + 1e-9


def _check_mask(mask, shape):
    m = checked_mask(mask, shape)
    if m is not None and m.all():
        raise SynthbosError("the mask excludes every pixel: nothing can be tracked")
    return m


def _masked_fill(image, mask):
    """The image with its excluded pixels set to the median of the others (no dot is found there)."""
    out = image.copy()
    out[mask] = np.median(image[~mask])
    return out


def _touches(mask_near, xy):
    """True where the rounded position lies on ``mask_near`` (outside the image: False)."""
    h, w = mask_near.shape
    fin = np.isfinite(xy).all(axis=1)
    c = np.rint(np.where(fin, xy[:, 0], -1.0)).astype(np.int64)
    r = np.rint(np.where(fin, xy[:, 1], -1.0)).astype(np.int64)
    inside = fin & (c >= 0) & (c < w) & (r >= 0) & (r < h)
    out = np.zeros(len(xy), dtype=bool)
    out[inside] = mask_near[r[inside], c[inside]]
    return out


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
        Warp device of the window kernel ("cpu", "cuda:0"); Warp's default when None.

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
    ref, top_r = _check_image("reference", reference)
    grad, top_g = _check_image("gradient", gradient)
    if ref.shape != grad.shape:
        raise SynthbosError(f"reference and gradient images differ in shape: {ref.shape} and {grad.shape}")
    h_img, w_img = ref.shape
    excluded = _check_mask(mask, ref.shape)
    if excluded is not None:
        ref, grad = _masked_fill(ref, excluded), _masked_fill(grad, excluded)
        top_r = top_g = None  # the maxima of the filled images
    if prior_xy is not None:
        prior = np.asarray(prior_xy, dtype=np.float64)
        if prior.ndim != 2 or prior.shape[1] != 2:
            raise SynthbosError(f"prior positions must be an Nx2 array, got shape {prior.shape}")
        if mapping is not None:
            prior = np.asarray(mapping(prior), dtype=np.float64).reshape(-1, 2)
        if not prior_inside(prior, (h_img, w_img)).any():
            raise SynthbosError(f"no prior dot lies inside the {h_img}x{w_img} image")

    d = settings.diameter
    if d is None:
        d = estimate_dot_diameter(ref)
        if not (np.isfinite(d) and d > 0):
            raise SynthbosError("cannot estimate the dot diameter from the reference image; give it in settings")
    eta0, half_r, half_g, map_half = window_sizes(d, settings)
    noise_r, noise_g = estimate_noise(ref), estimate_noise(grad)

    frame_r = _Frame(ref, noise_r, _saturation_level(ref, settings.saturation_level, top_r), _fill_level(ref))
    frame_g = _Frame(grad, noise_g, _saturation_level(grad, settings.saturation_level, top_g), _fill_level(grad))
    search = settings.max_displacement + 1.0 if settings.search_radius is None else settings.search_radius
    use_pred = settings.predictor == "correlation"
    near_mask = None
    if excluded is not None:
        near_mask = ndimage.binary_dilation(excluded, structure=_disk(d / 2.0))

    def predict(xy):
        return predict_displacement(
            ref, grad, xy, window_sizes=settings.predictor_windows, mask=excluded, device=device
        )

    def find(frame, pred, *, wide=False, standard=False):
        """One call of the identification: the prior's narrow window, the paper's wide one, or standard."""
        return _identify(
            frame.image,
            pred,
            half=half_g if wide else half_r,
            map_half=map_half,
            radius=1.0 if standard else (search if wide else settings.prior_radius),
            settings=settings,
            eta0=eta0,
            max_iterations=1 if standard else settings.max_iterations,
            noise=frame.noise,
            sat_level=frame.saturation,
            fill=frame.fill,
            device=device,
        )

    if prior_xy is not None:
        r = find(frame_r, prior)
        found_r = np.isfinite(r["x"])
        base = np.where(found_r[:, None], np.stack([r["x"], r["y"]], axis=1), prior)
        if use_pred:
            pred_uv, pred_q = predict(base)
            pred_g = base + np.nan_to_num(pred_uv)
            g = find(frame_g, pred_g)
            # Dots the prediction missed get the paper's wide window, around the prediction.
            miss = np.flatnonzero(~np.isfinite(g["x"]) & found_r)
            if miss.size:
                g2 = find(frame_g, pred_g[miss], wide=True)
                for key in g:
                    if key == "flags":
                        g[key][miss] |= g2[key]
                    else:
                        g[key][miss] = g2[key]
                _drop_shared_blobs(g, pred_g)
        else:
            g = find(frame_g, base, wide=True)
        partner = np.arange(len(prior))
    else:
        cand_r = _standard_candidates(ref, settings, noise_r)
        cand_g = _standard_candidates(grad, settings, noise_g)
        if excluded is not None:
            cand_r = cand_r[~_touches(excluded, cand_r)]
            cand_g = cand_g[~_touches(excluded, cand_g)]
        r = find(frame_r, cand_r, standard=True)
        g = find(frame_g, cand_g, standard=True)
        r = {k: v[np.isfinite(r["x"])] for k, v in r.items()}
        g = {k: v[np.isfinite(g["x"])] for k, v in g.items()}
        rxy = np.stack([r["x"], r["y"]], axis=1)
        gxy = np.stack([g["x"], g["y"]], axis=1)
        if use_pred:
            pred_uv, pred_q = predict(rxy)
            rxy = rxy + np.nan_to_num(pred_uv)  # pair around the predicted gradient-image positions
        if settings.matching == "nearest":
            partner = match_nearest(rxy, gxy, radius=search)
        else:
            partner = match_multiparametric(
                rxy,
                gxy,
                r["i0"],
                g["i0"],
                4 * r["eta"],
                4 * g["eta"],
                radius=search,
                weights=settings.match_weights,
            )
    fits = None
    if settings.centroid == "model" or settings.correction == "model":
        saturation = (frame_r.saturation, frame_g.saturation)
        noise = (frame_r.noise, frame_g.noise)
        fits = _fit_models((ref, grad), (r, g), partner, eta0, saturation, noise, settings, device)
    if settings.centroid == "model":
        _take_model(r, fits[0])
        _take_model(g, fits[1])

    n = len(r["x"])
    out = np.zeros(n, dtype=TRACK_DTYPE)
    for name in ("u", "v", "u_cc", "v_cc", "x_gradient", "y_gradient"):
        out[name] = np.nan
    out["x"], out["y"] = r["x"], r["y"]
    out["diameter"] = 4.0 * r["eta"]
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
    if prior_xy is not None:
        status |= g["flags"].astype(np.int32) & ~np.int32(DotStatus.OUTSIDE_IMAGE)
    status[found_g] |= DotStatus.FOUND_GRADIENT
    status[found_g] |= g["flags"][pi[found_g]].astype(np.int32) & np.int32(DotStatus.DISTORTED)
    matched = found_r & found_g
    if near_mask is not None:
        hidden = _touches(near_mask, np.stack([out["x"], out["y"]], axis=1))
        hidden |= _touches(near_mask, np.stack([out["x_gradient"], out["y_gradient"]], axis=1))
        if prior_xy is not None:
            hidden |= _touches(near_mask, prior)
        status[hidden] |= DotStatus.MASKED
        matched &= ~hidden
    out["u_pred"] = out["v_pred"] = out["pred_correlation"] = np.nan
    if use_pred:
        out["u_pred"], out["v_pred"], out["pred_correlation"] = pred_uv[:, 0], pred_uv[:, 1], pred_q
        du = out["x_gradient"] - out["x"] - pred_uv[:, 0]
        dv = out["y_gradient"] - out["y"] - pred_uv[:, 1]
        off = found_r & found_g & ~(np.hypot(du, dv) <= settings.predictor_tolerance)
        weak = found_r & ~(pred_q >= settings.predictor_min_correlation)
        off &= ~_confirmed_by_neighbours(out, matched & ~off & ~weak, off & ~weak, settings, device)
        status[off] |= DotStatus.PREDICTOR_MISMATCH
        status[weak] |= DotStatus.PREDICTOR_WEAK
        matched &= ~(off | weak)
    over = [
        _overshoot(out[cx], out[cy], d / 2.0, (h_img, w_img)) for cx, cy in (("x", "y"), ("x_gradient", "y_gradient"))
    ]
    cut = (np.abs(over[0] - over[1]) > _EDGE_CUT_PX).any(axis=1)
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
    if prior_xy is None and m.size and np.isfinite(settings.registration_tolerance):
        off = _misregistered((ref, grad), out, m, (ucc, vcc), half_r, settings, device)
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
    out["dot_id"] = np.arange(n) if prior_xy is not None else -1
    return out
