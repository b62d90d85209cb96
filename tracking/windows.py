"""Measuring the window around each predicted dot position: segmentation, Eq. 1, dot map.

One step of identification with prior information (Rajendran, Bane and Vlachos 2019, section 2.2), for
a whole set of predictions at once. :func:`measure_windows` runs it as a Warp kernel (one thread per dot;
on the CPU Warp compiles it to native code), the stacked tracker's (``identify_kernels.measure_stack``)
on a stack of one; :func:`tracking.reference.measure_windows_numpy` is the array-program reference that
defines the result and that the tests compare the kernel with.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .identify_kernels import measure_stack
from .sorting import median_network

__all__ = ["WINDOW_FIELDS", "measure_windows", "median_network"]

WINDOW_FIELDS = ("chosen", "nblobs", "nsat", "bg", "peak", "dist")



def measure_windows(
    image,
    origin,
    pred,
    *,
    half,
    map_half,
    radius,
    threshold_fraction,
    noise_floor,
    weights,
    use_minimum=False,
    saturation=np.inf,
    fill=0.0,
    full_maps=True,
    device=None,
):
    """Segment the window of each dot, choose its blob with Eq. 1 and cut out its dot map (a Warp kernel,
    one thread per dot).

    Parameters
    ----------
    image : (H, W) float array
        The (residual) image.
    origin : (N, 2) int array
        Column and row of each window's first pixel; windows are ``2 half + 1`` pixels square.
    pred : (N, 2) array
        Predicted position (x, y) in the image; ``pred - origin`` is its place in the window.
    half, map_half : int, keyword-only
        Window and dot-map half-widths.
    radius : float, keyword-only
        Blobs whose peak lies farther than this from the prediction are not candidates.
    threshold_fraction, noise_floor : float, keyword-only
        Segmentation threshold ``bg + max(threshold_fraction (max - bg), noise_floor)``.
    weights : (W_A, W_I, W_dx), keyword-only
        Eq. 1 weights.
    use_minimum : bool, keyword-only
        Background = window minimum instead of the median of the window's edge pixels.
    saturation : float, keyword-only
        Pixels at or above it count as saturated.
    fill : float, keyword-only
        Value of pixels outside the image.

    full_maps : bool, keyword-only
        False: instead of ``dotmap``, ``cross`` (N, 5): only the centre of each dot map, its peak pixel
        and left, right, upper and lower neighbours (what the three-point fit needs, for less work).
    device : str or None, keyword-only
        Warp device ("cpu", "cuda:0"); Warp's default when None.

    Returns
    -------
    dict
        ``chosen`` (N,) flat window index of the chosen blob's peak pixel (-1: no candidate), ``nblobs``
        (blobs in the window), ``nsat`` (saturated pixels of the chosen blob), ``bg`` (background),
        ``peak`` (chosen peak minus background), ``dist`` (its distance from the prediction) and ``dotmap``
        (N, 2 map_half + 1, 2 map_half + 1): the chosen blob and its one-pixel rim minus background, other
        pixels zero, centred on the peak pixel.

    Notes
    -----
    The image is a stack of one for the stacked tracker's kernel (``tracking.identify_kernels.measure_stack``).
    """
    n = len(origin)
    w = 2 * half + 1
    c = 2 * map_half + 1
    if n == 0:
        return _empty(c, full_maps=full_maps)
    # the windows in the order of their pixels in memory (row t: window order[t]), inputs gathered in that
    # order so that the kernel reads and writes through memory in order (10-15 % less time on the CPU)
    order = _band_order(origin, image.shape[1], w)
    origin, pred = np.take(origin, order, axis=0), np.take(pred, order, axis=0)
    image = np.ascontiguousarray(image, dtype=np.float64)
    on_cpu = wp.get_device(device).is_cpu
    img = wp.array(image[None], dtype=wp.float64, device=device, copy=not on_cpu)  # CPU: the NumPy memory

    def one(value, dtype=wp.float64):
        return wp.array([value], dtype=dtype, device=device)

    # Per-thread scratch; CPU threads run one after another, so one row serves them all.
    rows = 1 if on_cpu else n
    out_i = wp.empty((n, 3), dtype=wp.int32, device=device)
    out_f = wp.empty((n, 3), dtype=wp.float64, device=device)
    dotmap = wp.empty((n if full_maps else 1, c, c), dtype=wp.float64, device=device)
    cross = wp.empty((1 if full_maps else n, 5), dtype=wp.float64, device=device)
    wa, wi, wd = (float(x) for x in weights)
    inputs = [
        img, wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=device), n, one(fill), one(noise_floor),
        one(min(saturation, 1e300)), one(1, wp.int32),
        wp.array(np.ascontiguousarray(origin, dtype=np.int32), dtype=wp.int32, device=device),
        wp.array(np.ascontiguousarray(pred, dtype=np.float64), dtype=wp.vec2d, device=device),
        wp.full(n, 1, dtype=wp.int32, device=device), int(half), int(map_half), float(radius),
        float(threshold_fraction), wa, wi, wd, int(bool(use_minimum)),
        wp.empty((rows, w * w), dtype=wp.float64, device=device),
        wp.empty((rows, 4 * (w - 1)), dtype=wp.float64, device=device),
        wp.array(median_network(4 * (w - 1)), dtype=wp.int32, device=device),
        *(wp.empty((rows, w * w), dtype=wp.int32, device=device) for _ in range(3)),
        dotmap, out_i, out_f, cross, int(bool(full_maps)),
    ]  # fmt: skip
    wp.launch(measure_stack, dim=n, inputs=inputs, device=device)
    return _results(out_i, out_f, dotmap, cross, order, full_maps=full_maps)


def _empty(c, *, full_maps):
    """``measure_windows``' result for no windows."""
    out = {name: np.zeros(0, dtype=np.int64) for name in ("chosen", "nblobs", "nsat")}
    out.update({name: np.zeros(0) for name in ("bg", "peak", "dist")})
    out["dotmap" if full_maps else "cross"] = np.zeros((0, c, c) if full_maps else (0, 5))
    return out


def _band_order(origin, width, w):
    """The windows in raster order of 8-row bands (int32 indices), so that neighbouring threads read
    neighbouring pixels (the kernel takes them in that order and writes each at its own row). Only the
    speed depends on it."""
    n = len(origin)
    key = (origin[:, 1] // 8) * (width + 4 * w) + origin[:, 0]
    # argsort as a sort of key and index packed into one int64 (a third of the time; ties in index order)
    shift = int(n).bit_length()
    packed = ((key - key.min()).astype(np.int64) << shift) | np.arange(n, dtype=np.int64)
    return (np.sort(packed) & ((1 << shift) - 1)).astype(np.int32)


def _results(out_i, out_f, dotmap, cross, order, *, full_maps):
    """``measure_windows``' result from the kernel's outputs (row t: window ``order[t]``), in the dots' order."""
    n = out_i.shape[0]
    back = np.empty(n, dtype=np.int64)
    back[order] = np.arange(n)
    oi, of = np.take(out_i.numpy(), back, axis=0), np.take(out_f.numpy(), back, axis=0)  # faster than oi[back]
    out = {
        "chosen": oi[:, 0].astype(np.int64),
        "nblobs": oi[:, 1].astype(np.int64),
        "nsat": oi[:, 2].astype(np.int64),
        "bg": of[:, 0],
        "peak": of[:, 1],
        "dist": of[:, 2],
    }
    if full_maps:
        out["dotmap"] = np.take(dotmap.numpy(), back, axis=0)
    else:
        out["cross"] = np.take(cross.numpy(), back, axis=0)
    return out
