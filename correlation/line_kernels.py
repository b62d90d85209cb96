"""Warp kernels of the device-resident correlation whose threads each loop over an image line: the cubic
B-spline prefilter along rows and columns, and the statistics that normalise an image (host code:
:mod:`correlation.device_pass`, which launches them all with ``LOOP_BLOCK`` threads a block).

They are a Warp module of their own, whose default block size is ``LOOP_BLOCK``: Warp compiles a module
once per block size, and in :mod:`correlation.pass_kernels`, launched at 256 threads elsewhere, they made
a first GPU run compile that whole module twice.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from synthbos.device import quiet_warp

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)

#: Block size of these kernels: few threads, spread over many multiprocessors.
LOOP_BLOCK = 32

wp.set_module_options({"enable_backward": False, "block_dim": LOOP_BLOCK})


# ---------------------------------------------------------------- cubic B-spline prefilter (Unser 1999)


@wp.kernel
def bspline3_prefilter_lines(
    src: wp.array2d(dtype=wp.float32),
    axis: int,
    line: wp.array2d(dtype=wp.float64),
    dst: wp.array2d(dtype=wp.float32),
):
    """Cubic B-spline coefficients along rows (axis 1) or columns (axis 0), mirror boundary.

    One thread per line; ``line`` is float64 scratch of shape (lines, length). The recursive filter
    with the pole ``z = sqrt(3) - 2``: gain 6, causal sweep started by the exact mirror sum, anticausal
    sweep started by the mirror closed form (as ``scipy.ndimage.spline_filter1d(mode="mirror")``).
    """
    k = wp.tid()
    n = src.shape[1]
    if axis == 0:
        n = src.shape[0]
    if n == 1:
        if axis == 0:
            dst[0, k] = src[0, k]
        else:
            dst[k, 0] = src[k, 0]
        return
    gain = wp.float64(6.0)
    z = wp.float64(-0.2679491924311228)
    zn1 = wp.float64(1.0)
    for _ in range(n - 1):
        zn1 *= z
    # causal start: the mirror sum
    first = wp.float64(0.0)
    last = wp.float64(0.0)
    if axis == 0:
        first = gain * wp.float64(src[0, k])
        last = gain * wp.float64(src[n - 1, k])
    else:
        first = gain * wp.float64(src[k, 0])
        last = gain * wp.float64(src[k, n - 1])
    c = first + zn1 * last
    zi = z
    for i in range(1, n - 1):
        x = wp.float64(0.0)
        y = wp.float64(0.0)
        if axis == 0:
            x = wp.float64(src[i, k])
            y = wp.float64(src[n - 1 - i, k])
        else:
            x = wp.float64(src[k, i])
            y = wp.float64(src[k, n - 1 - i])
        c += zi * gain * (x + zn1 * y)
        zi *= z
    c = c / (wp.float64(1.0) - zn1 * zn1)
    line[k, 0] = c
    # causal sweep, the running value in a register
    for i in range(1, n):
        x = wp.float64(0.0)
        if axis == 0:
            x = wp.float64(src[i, k])
        else:
            x = wp.float64(src[k, i])
        c = gain * x + z * c
        line[k, i] = c
    # anticausal sweep, written out as it goes
    c = (z * line[k, n - 2] + c) * z / (z * z - wp.float64(1.0))
    for j in range(n):
        i = n - 1 - j
        if j > 0:
            c = z * (c - line[k, i])
        if axis == 0:
            dst[i, k] = wp.float32(c)
        else:
            dst[k, i] = wp.float32(c)


# ---------------------------------------------------------------- image normalisation (multigrid._checked_image)


@wp.kernel
def column_stats(image: wp.array2d(dtype=Any), stats: wp.array2d(dtype=wp.float64)):
    """Per column (coalesced): sum, min and max of the finite pixels, and the number of non-finite ones."""
    j = wp.tid()
    total = wp.float64(0.0)
    lo = wp.float64(1.0e308)
    hi = wp.float64(-1.0e308)
    bad = wp.float64(0.0)
    for i in range(image.shape[0]):
        x = wp.float64(image[i, j])
        if wp.isfinite(x):
            total += x
            lo = wp.min(lo, x)
            hi = wp.max(hi, x)
        else:
            bad += wp.float64(1.0)
    stats[j, 0] = total
    stats[j, 1] = lo
    stats[j, 2] = hi
    stats[j, 3] = bad


@wp.kernel
def combine_stats(stats: wp.array2d(dtype=wp.float64), pixels: wp.float64, summary: wp.array(dtype=wp.float64)):
    """One thread: ``summary`` = mean, largest |pixel - mean|, min, max, non-finite count."""
    total = wp.float64(0.0)
    lo = wp.float64(1.0e308)
    hi = wp.float64(-1.0e308)
    bad = wp.float64(0.0)
    for j in range(stats.shape[0]):
        total += stats[j, 0]
        lo = wp.min(lo, stats[j, 1])
        hi = wp.max(hi, stats[j, 2])
        bad += stats[j, 3]
    mean = total / pixels
    summary[0] = mean
    summary[1] = wp.max(hi - mean, mean - lo)
    summary[2] = lo
    summary[3] = hi
    summary[4] = bad


@wp.kernel
def column_moments(
    image: wp.array2d(dtype=Any), summary: wp.array(dtype=wp.float64), stats: wp.array2d(dtype=wp.float64)
):
    """Per column: sum of y and of y^2, y = (pixel - mean) / largest |pixel - mean|."""
    j = wp.tid()
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    for i in range(image.shape[0]):
        y = (wp.float64(image[i, j]) - summary[0]) / summary[1]
        s1 += y
        s2 += y * y
    stats[j, 0] = s1
    stats[j, 1] = s2


@wp.kernel
def combine_moments(stats: wp.array2d(dtype=wp.float64), pixels: wp.float64, summary: wp.array(dtype=wp.float64)):
    """One thread: ``summary[5]`` = standard deviation of y."""
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    for j in range(stats.shape[0]):
        s1 += stats[j, 0]
        s2 += stats[j, 1]
    m = s1 / pixels
    summary[5] = wp.sqrt(wp.max(s2 / pixels - m * m, wp.float64(0.0)))


@wp.kernel
def normalise_image(
    image: wp.array2d(dtype=Any), summary: wp.array(dtype=wp.float64), out: wp.array2d(dtype=wp.float32)
):
    """``out = ((pixel - mean) / largest |pixel - mean|) / std``: zero mean, unit standard deviation."""
    i, j = wp.tid()
    y = (wp.float64(image[i, j]) - summary[0]) / summary[1]
    out[i, j] = wp.float32(y / summary[5])


#: The dtypes images go up as (``device_pass``: float32 where it holds every value, else float64). Both
#: overloads of the three image kernels are declared at import: an overload made at a launch changes
#: the module's content, and with it its hash, so every process that met a new dtype compiled the whole
#: module again (6 times in a first GPU campaign, 6-8 s each, when these kernels lived in
#: ``pass_kernels``, 2026-11-27).
IMAGE_DTYPES = (wp.float32, wp.float64)
for _kernel in (column_stats, column_moments, normalise_image):
    for _dtype in IMAGE_DTYPES:
        wp.overload(_kernel, {"image": wp.array2d(dtype=_dtype)})
