"""Window-deformation cross-correlation: two images in, a displacement field out (no file I/O).

The entry point is :func:`correlate_pair` with :class:`CorrelationSettings`; the building blocks
(peak fit, window correlation, deformation, validation) are public for the tracker and the tests.
"""

from .multigrid import (
    FLAG_BORDER,
    FLAG_DISAGREE,
    FLAG_ISOLATED,
    FLAG_MASKED,
    FLAG_MEDIAN,
    FLAG_PEAK_RATIO,
    CorrelationResult,
    CorrelationSettings,
    VectorFlag,
    correlate_pair,
    count_vectors,
)

__all__ = [
    "FLAG_BORDER",
    "FLAG_DISAGREE",
    "FLAG_ISOLATED",
    "FLAG_MASKED",
    "FLAG_MEDIAN",
    "FLAG_PEAK_RATIO",
    "CorrelationResult",
    "CorrelationSettings",
    "VectorFlag",
    "correlate_pair",
    "count_vectors",
]
