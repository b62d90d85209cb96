"""The normalised median test (Westerweel and Scarano 2005), written once: Warp funcs and NumPy twins.

A value ``U_0`` is tested against a reference ``U_m`` and a scale ``r_m`` taken from its neighbours. Its
normalised residual ``r_0 = |U_0 - U_m| / (r_m + epsilon)`` (Westerweel and Scarano, Exp. Fluids 39 (2005)
1096, eq. 2) above a threshold marks an outlier; in the product form, its deviation ``|U_0 - U_m|`` above
the limit ``threshold (r_m + epsilon)``. Both forms are here, because the callers use both, and each
keeps the rounding it has always had: the quotient where two components' residuals are combined, the
limit where a distance is compared, or where the limit is capped by another tolerance.

Three idioms use it. Each gathers its own neighbourhood at the call site and calls the core here:

Vector grid of the correlation (3x3 neighbours, the grid continued linearly beyond its edges)
    Host :func:`correlation.validation.normalized_median_test`, device
    ``correlation.pass_kernels.median_residual``: ``U_m`` and ``r_m`` are the neighbours' median and
    the median of their residuals from it (:func:`median_scale`, :func:`median_scale_wp`); each
    component's :func:`normalised_residual` (:func:`normalised_residual_wp`), counted where finite,
    combined as ``sqrt(r_0u^2 + r_0v^2) > threshold``. The medians of neighbours that replace and
    confirm vectors use :func:`nan_median` (:func:`median_wp`).
Tile field of the tracker's correlation predictor (the up to eight neighbouring tiles, NaN beyond)
    Host ``tracking.predict._replace_outliers``, device ``tracking.predict_kernels.median_test``: the
    same median and scale, each component's deviation compared with :func:`residual_limit`
    (:func:`residual_limit_wp`; threshold 3, epsilon 0.5 px); the neighbours' medians of the
    significance step use :func:`nan_median` (:func:`median_sorted_wp`).
Scattered dots of the tracker's outlier test (the ``k`` nearest dots)
    Host ``tracking.pipeline`` (the outlier test and the confirmation of the predictor), device
    ``tracking.neighbour_kernels.outlier_flags_kernel`` and ``confirm_flags_kernel``: ``U_m`` is
    a local linear fit's value at the dot and ``r_m`` the median distance of the neighbours' vectors
    from the fit (``tracking.neighbours``, ``tracking.neighbour_kernels.plane_fit``); the distance ``|uv - U_m|``
    is compared with :func:`residual_limit` (:func:`residual_limit_wp`).

The Warp funcs (suffix ``_wp``) work on the up to eight neighbours of a grid node in a :data:`vec8d`;
the NumPy functions on a stack of neighbours along one axis, NaN where a neighbour is missing. They
agree to the bit: the same sorted order, the median as ``0.5 (a + b)`` of the middle one or two values,
the same sums and products.
"""

from __future__ import annotations

import numpy as np
import warp as wp

__all__ = [
    "median_scale",
    "median_scale_wp",
    "median_sorted_wp",
    "median_wp",
    "nan_median",
    "normalised_residual",
    "normalised_residual_wp",
    "residual_limit",
    "residual_limit_wp",
    "sort_wp",
    "vec8d",
]

#: The up to eight neighbours of a grid node (the first ``count`` entries used).
vec8d = wp.types.vector(length=8, dtype=wp.float64)


# --- NumPy ------------------------------------------------------------------------------------------------


def nan_median(stack, *, axis=-1):
    """Median of the finite values of a stack along one axis, and how many there are.

    Parameters
    ----------
    stack : array
        Values; NaN (and infinite) entries are left out.
    axis : int, keyword-only
        The axis to reduce.

    Returns
    -------
    median : float array
        The stack's shape without ``axis``; NaN where there is no finite value.
    count : int array
        The number of finite values.

    Examples
    --------
    >>> nan_median([[1.0, 5.0, np.nan, 2.0], [np.nan] * 4])
    (array([ 2., nan]), array([3, 0]))
    """
    stack = np.asarray(stack, dtype=np.float64)
    finite = np.isfinite(stack)
    if not finite.all():
        stack = np.where(finite, stack, np.nan)
    count = np.sum(finite, axis=axis, keepdims=True)
    ordered = np.sort(stack, axis=axis)  # NaN sort last
    lo = np.maximum(count - 1, 0) // 2
    hi = np.minimum(count // 2, stack.shape[axis] - 1)
    med = 0.5 * (np.take_along_axis(ordered, lo, axis) + np.take_along_axis(ordered, hi, axis))
    med = np.where(count > 0, med, np.nan)
    return np.squeeze(med, axis=axis), np.squeeze(count, axis=axis)


def median_scale(stack, *, axis=-1):
    """The reference and the scale of the normalised median test from a stack of neighbours.

    Parameters
    ----------
    stack : array
        The neighbours' values along ``axis``, NaN where a neighbour is missing.
    axis : int, keyword-only
        The neighbours' axis.

    Returns
    -------
    median : float array
        ``U_m``, the median of the neighbours (NaN where there are none).
    scale : float array
        ``r_m``, the median of their residuals ``|U_i - U_m|`` (NaN where there are none).
    count : int array
        The number of neighbours.

    Examples
    --------
    >>> median_scale([1.0, 2.0, 4.0, np.nan, 9.0])
    (array(3.), array(1.5), array(4))
    """
    stack = np.asarray(stack, dtype=np.float64)
    med, count = nan_median(stack, axis=axis)
    scale, _ = nan_median(np.abs(stack - np.expand_dims(med, axis)), axis=axis)
    return med, scale, count


def normalised_residual(deviation, scale, *, epsilon):
    """``r_0 = deviation / (scale + epsilon)`` (Westerweel and Scarano 2005, eq. 2).

    Parameters
    ----------
    deviation : float array
        ``|U_0 - U_m|``.
    scale : float array
        ``r_m``.
    epsilon : float, keyword-only
        The acceptable fluctuation (px).

    Returns
    -------
    float array
        Infinite or NaN where ``scale + epsilon`` is 0.

    Examples
    --------
    >>> float(normalised_residual(1.0, 0.25, epsilon=0.25))
    2.0
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(deviation, dtype=np.float64) / (scale + epsilon)


def residual_limit(scale, *, epsilon, threshold):
    """The largest deviation the test accepts: ``threshold * (scale + epsilon)``.

    Parameters
    ----------
    scale : float array
        ``r_m``.
    epsilon, threshold : float, keyword-only
        The acceptable fluctuation (px) and the threshold on the normalised residual.

    Returns
    -------
    float array

    Examples
    --------
    >>> float(residual_limit(0.25, epsilon=0.5, threshold=3.0))
    2.25
    """
    return threshold * (np.asarray(scale, dtype=np.float64) + epsilon)


# --- Warp -------------------------------------------------------------------------------------------------


@wp.func
def sort_wp(values: vec8d, count: int) -> vec8d:
    """The first ``count`` entries in ascending order (insertion sort; the rest as they were)."""
    s = vec8d(values)
    for a in range(1, count):
        x = s[a]
        b = a - 1
        while b >= 0 and s[b] > x:
            s[b + 1] = s[b]
            b -= 1
        s[b + 1] = x
    return s


@wp.func
def median_sorted_wp(values: vec8d, count: int) -> wp.float64:
    """Median of the first ``count`` entries, already sorted; NaN where ``count`` is 0 (:func:`nan_median`)."""
    if count == 0:
        return wp.float64(wp.nan)
    return wp.float64(0.5) * (values[(count - 1) // 2] + values[count // 2])


@wp.func
def median_wp(values: vec8d, count: int) -> wp.float64:
    """Median of the first ``count`` entries; NaN where ``count`` is 0 (:func:`nan_median`)."""
    return median_sorted_wp(sort_wp(values, count), count)


@wp.func
def median_scale_wp(values: vec8d, count: int) -> wp.vec2d:
    """(``U_m``, ``r_m``) of the first ``count`` entries: their median and the median of their residuals
    from it; NaN where ``count`` is 0 (:func:`median_scale`)."""
    s = sort_wp(values, count)
    med = median_sorted_wp(s, count)
    d = vec8d()
    for a in range(count):
        d[a] = wp.abs(s[a] - med)
    return wp.vec2d(med, median_wp(d, count))


@wp.func
def normalised_residual_wp(deviation: wp.float64, scale: wp.float64, epsilon: wp.float64) -> wp.float64:
    """``deviation / (scale + epsilon)`` (:func:`normalised_residual`)."""
    return deviation / (scale + epsilon)


@wp.func
def residual_limit_wp(scale: wp.float64, epsilon: wp.float64, threshold: wp.float64) -> wp.float64:
    """``threshold * (scale + epsilon)`` (:func:`residual_limit`)."""
    return threshold * (scale + epsilon)
