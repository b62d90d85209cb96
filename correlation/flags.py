"""The bits of a correlation vector's flag, defined once: the host code (:mod:`correlation.multigrid`)
and the kernels (:mod:`correlation.pass_kernels`, as ``wp.constant``\\ s) both read them here."""

from __future__ import annotations

import enum

__all__ = [
    "FLAG_BORDER",
    "FLAG_DISAGREE",
    "FLAG_ISOLATED",
    "FLAG_MASKED",
    "FLAG_MEDIAN",
    "FLAG_PEAK_RATIO",
    "VectorFlag",
]


class VectorFlag(enum.IntFlag):
    """Bits of :attr:`CorrelationResult.flags`; 0 is a vector measured in its own window and accepted.

    A vector is *replaced* when its window gave a significant correlation peak that the normalised
    median test rejected (``MEDIAN`` alone); it *failed* when its window gave no usable measurement
    (``PEAK``, ``BORDER``, ``DISAGREE`` or ``ISOLATED``). Both carry in ``u``, ``v`` a value
    interpolated from the valid vectors around them (harmonic interpolation,
    ``validation.fill_by_interpolation``), so that the field stays continuous for integration (NaN where nothing
    was measured anywhere). ``MASKED`` windows are NaN. :func:`count_vectors` counts them.

    MEDIAN
        Replaced by interpolation from the valid vectors around it: failed the normalised median test.
    PEAK
        Failed: correlation peak not significant (peak ratio below peak_ratio_min, random patterns
        only, or peak correlation coefficient below min_correlation in the iterations that judge it).
    BORDER
        Failed: the correlation peak lay on the border of the correlation plane.
    MASKED
        Window more than half covered by the mask; u, v are NaN.
    DISAGREE
        Failed: differs from the previous pass's field (an independent, coarser estimate) by more than
        max_disagreement times the window size.
    ISOLATED
        Failed: fewer than two of its (at least three unmasked) neighbours were measured, so nothing
        confirms it; a lone vector among failed ones is as likely a chance peak.
    """

    MEDIAN = 1
    PEAK = 2
    BORDER = 4
    MASKED = 8
    DISAGREE = 16
    ISOLATED = 32


# The bits as plain ints, for NumPy arrays of flags.
FLAG_MEDIAN = int(VectorFlag.MEDIAN)
FLAG_PEAK_RATIO = int(VectorFlag.PEAK)
FLAG_BORDER = int(VectorFlag.BORDER)
FLAG_MASKED = int(VectorFlag.MASKED)
FLAG_DISAGREE = int(VectorFlag.DISAGREE)
FLAG_ISOLATED = int(VectorFlag.ISOLATED)
