"""Per-frame image statistics of a stack of frames, computed on the device.

The numbers the tracker (:func:`tracking.pipeline.track_pair`) takes from each image before it looks
for dots: the extremes and the image check, the saturation level, the fill level of the windows, the
noise and the dot diameter. :func:`frame_statistics` computes them for a whole ``(F, H, W)`` stack with
a fixed number of launches (independent of ``F``) and no host synchronisation, so it can be queued or
captured in a graph; :func:`tracking.reference.frame_statistics_numpy` calls the tracker's host functions frame by frame
and defines the result.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from synthbos import SynthbosError

from .stats_kernels import (
    band_lags,
    band_moments,
    column_lags,
    column_pass,
    frame_moments,
    frame_results,
    segment_counts,
    segment_keys,
    segment_median,
    segment_of_slot,
)
from .workspace import on_device

__all__ = ["FRAME_STATISTICS", "frame_statistics", "segment_medians"]

FRAME_STATISTICS = ("lo", "hi", "bad", "saturation", "fill", "noise", "diameter")

# The divisor of tracking.identify.estimate_noise, computed as it computes it.
_NOISE_SCALE = float(0.31864 * np.sqrt(2.0))
# Rows per band: a thread walks one column of one band (more threads for few frames, reads that stay in cache).
_BAND = 64


def _sizes(h, w):
    """Row step and sizes of the two sorted segments of one frame: differences, sub-sampled pixels."""
    row_step = max(1, h // 256)
    n_noise = ((h + row_step - 1) // row_step) * (w - 1)
    n_fill = ((h + 3) // 4) * ((w + 3) // 4)
    return row_step, n_noise, n_fill


def saturation_level(image, level, top=None):
    """The given level, or the image's maximum (``top`` where known) if five or more pixels reach it."""
    if level is not None:
        return float(level)
    top = image.max() if top is None else top
    return float(top) if np.count_nonzero(image == top) >= 5 else np.inf


def partial_median(a):
    """``np.median`` of a 1-D float array (the mean of the middle two for even sizes), by one partial sort
    of ``a`` in place; NaN input goes to NumPy."""
    k = a.size // 2
    a.partition(k)
    if np.isnan(a[k:]).any():  # NaN sorts last, so one would be in the upper half
        return float(np.median(a))
    if a.size % 2:
        return float(a[k])
    return float((a[:k].max() + a[k]) / 2.0)


def fill_level(image):
    """Value of the pixels outside the image in the windows: the median of every fourth row and column."""
    return partial_median(image[::4, ::4].flatten())  # np.median's value; flatten copies


def frame_statistics(images, *, device=None):
    """Image statistics of every frame of a stack, as device arrays, without a host synchronisation.

    Parameters
    ----------
    images : (F, H, W) ``wp.array3d`` of float64, or (F, H, W) NumPy array
        The frames, ``H, W >= 8``. A Warp array is used where it lies; a NumPy array is uploaded.
    device : str or None, keyword-only
        Warp device ("cpu", "cuda:0"); for a Warp array, None means the array's device (any other must
        be that device); for a NumPy array, Warp's default when None.

    Returns
    -------
    dict of (F,) ``wp.array`` on the device
        ``lo``, ``hi``: each frame's minimum and maximum (NaN if a pixel is NaN);
        ``bad`` (int32): 1 if a pixel is non-finite, 2 if the frame is all zero, else 0 (the tracker's
        ``_check_image``); ``saturation``: ``saturation_level(image, None)``; ``fill``:
        ``fill_level(image)``; ``noise``: ``estimate_noise(image)``; ``diameter``:
        ``estimate_dot_diameter(image)``; all float64.

    Notes
    -----
    The order statistics are exact (the values NumPy gives): the noise differences and the sub-sampled
    pixels of all frames go into one buffer, whose slots are radix-sorted by the values rounded to float32
    and then, stably, by segment (two sorts of the whole buffer; 24 bytes of device memory per element,
    about 3.5 MB per 512x512 frame); the k-th value of a segment is then found among the few that share
    its float32 key (``stats_kernels.order_statistic``). The diameter's sums differ from the host's only
    in summation order. One exception:
    a constant frame gets NaN as diameter (its mean-subtracted image is zero), where the host can
    return a number when NumPy's mean of the constant is not the constant itself.

    Launches: seven kernels and two radix sorts, whatever ``F``.
    """
    img = on_device(images, wp.float64, 3, device, "frame_statistics' images")
    device = img.device
    n_frames, h, w = img.shape
    if min(h, w) < 8:
        raise SynthbosError(f"frames are too small ({h}x{w}), need at least 8x8")
    row_step, n_noise, n_fill = _sizes(h, w)
    n_frame = n_noise + n_fill
    count = n_frames * n_frame
    if count >= 2**31:
        raise SynthbosError(f"{n_frames} frames of {h}x{w} are too many for one call; pass fewer frames at once")

    out = {name: wp.empty(n_frames, dtype=wp.float64, device=device) for name in FRAME_STATISTICS}
    out["bad"] = wp.empty(n_frames, dtype=wp.int32, device=device)
    if n_frames == 0:
        return out

    # The values, their float32 sort keys and slots; the sort buffers' second halves are the radix sort's scratch.
    values = wp.empty(count, dtype=wp.float64, device=device)
    keys = wp.empty(2 * count, dtype=wp.float32, device=device)
    slots = wp.empty(2 * count, dtype=wp.int32, device=device)
    parts = (n_frames, (h + _BAND - 1) // _BAND, w)  # one per column of each band of each frame
    col_min = wp.empty(parts, dtype=wp.float64, device=device)
    col_max = wp.empty(parts, dtype=wp.float64, device=device)
    col_count = wp.empty(parts, dtype=wp.int32, device=device)
    col_sum = wp.empty(parts, dtype=wp.float64, device=device)
    col_flags = wp.empty(parts, dtype=wp.int32, device=device)
    lags = wp.empty(parts, dtype=wp.vec4d, device=device)
    mean = wp.empty(n_frames, dtype=wp.float64, device=device)
    frame_flags = wp.empty(n_frames, dtype=wp.int32, device=device)

    wp.launch(
        column_pass,
        dim=parts,
        inputs=[img, _BAND, row_step, n_noise, n_frame],
        outputs=[values, keys, slots, col_min, col_max, col_count, col_sum, col_flags],
        device=device,
    )
    bands = (n_frames, parts[1], 1)  # each band reduced to one column: the frames' threads read a few
    band = [wp.empty(bands, dtype=a.dtype, device=device) for a in (col_min, col_max, col_count, col_sum, col_flags)]
    wp.launch(band_moments, dim=parts[:2], inputs=[col_min, col_max, col_count, col_sum, col_flags], outputs=band,
              device=device)  # fmt: skip
    wp.launch(
        frame_moments,
        dim=n_frames,
        inputs=[*band, float(h * w)],
        outputs=[out["lo"], out["hi"], out["bad"], out["saturation"], mean, frame_flags],
        device=device,
    )
    wp.launch(column_lags, dim=parts, inputs=[img, _BAND, mean], outputs=[lags], device=device)
    band_lag = wp.empty(bands, dtype=wp.vec4d, device=device)
    wp.launch(band_lags, dim=parts[:2], inputs=[lags], outputs=[band_lag], device=device)
    # The slots by float32 key, then stably by segment: every segment in order (float32 keys and int32
    # slots: six radix passes over 8 bytes an entry, against ten over 12 for float64 values and segments).
    wp.utils.radix_sort_pairs(keys, slots, count)
    segment = keys.view(wp.int32)  # the keys are not needed again: their storage holds the segments
    wp.launch(segment_of_slot, dim=count, inputs=[slots, n_frame, n_noise], outputs=[segment], device=device)
    wp.utils.radix_sort_pairs(segment, slots, count, 0, max(1, (2 * n_frames - 1).bit_length()))
    pos = 0.25 * (n_noise - 1)  # as tracking.identify._lower_quartile: exact, 0.25 is a power of two
    q_index = int(pos)
    wp.launch(
        frame_results,
        dim=n_frames,
        inputs=[slots, values, frame_flags, band_lag, n_frame, n_noise, n_fill, q_index, pos - q_index, _NOISE_SCALE],
        outputs=[out["fill"], out["noise"], out["diameter"]],
        device=device,
    )
    return out


#: Entries per thread of the count of values taking part per segment (``stats_kernels.segment_counts``).
COUNT_CHUNK = 32


def segment_medians(values, valid, *, length, segments, device):
    """NumPy's median of each run of ``length`` values where ``valid`` (NaN for none), on the device.

    Parameters
    ----------
    values : (segments * length,) float64 Warp array
        The values, segment after segment (a stack's per-pair runs).
    valid : (segments * length,) int32 Warp array
        Nonzero where a value takes part.
    length, segments : int, keyword-only
        Values per segment and the number of segments.
    device : warp.context.Device or str, keyword-only
        The arrays' device.

    Returns
    -------
    (segments,) float64 Warp array
        Each segment's median (the mean of the middle two for an even count), NaN where none takes part.

    Notes
    -----
    The values are sorted per segment by float32 keys (Warp's segmented radix sort); the k-th value is
    then found among those that share its key (``stats_kernels.order_statistic``), so the median is
    NumPy's to the bit.
    """
    n = segments * length
    keys = wp.empty(2 * n, dtype=wp.float32, device=device)
    order = wp.empty(2 * n, dtype=wp.int32, device=device)
    count = wp.zeros(segments, dtype=wp.int32, device=device)
    if n:
        wp.launch(segment_keys, dim=n, inputs=[values, valid, keys, order], device=device)
        chunk = COUNT_CHUNK
        wp.launch(segment_counts, dim=(n + chunk - 1) // chunk, inputs=[valid, length, chunk, count], device=device)
    starts = wp.array(np.arange(segments, dtype=np.int32) * length, dtype=wp.int32, device=device)
    ends = wp.array((np.arange(segments, dtype=np.int32) + 1) * length, dtype=wp.int32, device=device)
    wp.utils.segmented_sort_pairs(keys, order, n, starts, ends)
    median = wp.empty(segments, dtype=wp.float64, device=device)
    if segments:
        wp.launch(segment_median, dim=segments, inputs=[order, values, count, length, median], device=device)
    return median
