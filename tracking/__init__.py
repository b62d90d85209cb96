"""Dot tracking for BOS: images in, per-dot table out (Rajendran, Bane and Vlachos 2019).

:func:`track_pair` is the pipeline; the pieces it is built from are public so that tests and the
harness can call them one by one.
"""

from .calibration import (
    GridCalibration,
    SoloffMapping,
    calibrate_grid,
    fit_soloff,
    mapping_from_dict,
    mapping_to_dict,
)
from .centroid import (
    CENTROID_METHODS,
    centroid_gaussian3,
    centroid_gaussian4,
    centroid_intensity_weighted,
    centroid_lsq_gaussian,
    fit_centroids,
)
from .correction import correlation_correction
from .crlb import displacement_crlb, position_crlb
from .diameter import estimate_dot_diameter
from .dotfit import fit_dots
from .identify import (
    blob_properties,
    blob_score,
    dynamic_threshold_identification,
    estimate_noise,
    segment_windows,
    static_threshold_identification,
)
from .match import MATCH_METHODS, match_multiparametric, match_nearest
from .pipeline import track_pair
from .residual import render_gaussians, subtract_gaussians
from .settings import TRACK_DTYPE, DotStatus, TrackingSettings, is_valid

__all__ = [
    "CENTROID_METHODS",
    "MATCH_METHODS",
    "TRACK_DTYPE",
    "DotStatus",
    "GridCalibration",
    "SoloffMapping",
    "TrackingSettings",
    "blob_properties",
    "blob_score",
    "calibrate_grid",
    "centroid_gaussian3",
    "centroid_gaussian4",
    "centroid_intensity_weighted",
    "centroid_lsq_gaussian",
    "correlation_correction",
    "displacement_crlb",
    "dynamic_threshold_identification",
    "estimate_dot_diameter",
    "estimate_noise",
    "fit_centroids",
    "fit_dots",
    "fit_soloff",
    "is_valid",
    "mapping_from_dict",
    "mapping_to_dict",
    "match_multiparametric",
    "match_nearest",
    "position_crlb",
    "render_gaussians",
    "segment_windows",
    "static_threshold_identification",
    "subtract_gaussians",
    "track_pair",
]
