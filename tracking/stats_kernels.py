# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of the per-frame image statistics of a stack of frames.

Kernels only; the host code that allocates, launches and sorts lives next to it in
:mod:`tracking.frame_stats`; ``tracking.reference.frame_statistics_numpy`` (the host functions of the
tracker, frame by frame) defines what they compute. Frames are ``images[f]`` of an ``(F, H, W)`` array,
cut into bands of
``band`` rows; one thread walks one column of one band down its rows (neighbouring threads read
neighbouring pixels), one thread per band reduces its columns' partial results, and one thread per
frame its bands'.

The order statistics (the median of every fourth row and column, the lower quartile of the horizontal
differences) come from one sorted buffer: each frame owns ``n_frame`` slots, first its ``n_noise``
differences, then its ``n_fill`` sub-sampled pixels. The slots are sorted by the values' float32 keys and
then (stably) by segment, so that the ``k``-th smallest value of a segment lies at a known index, or
among the few values beside it that share its key (:func:`order_statistic`). NaN never enters the buffer
(it is written as +inf and the segment flagged), so the sort's placement of NaN does not matter.

The last section takes the median of each segment of a flat array (a stack's per-pair medians: the
first round's peaks, the fit's starting widths), sorted by float32 keys.

Floating-point contraction is off in this module: the quartile's interpolation and the median's mean
must round as NumPy's separate multiply and add do.
"""

import warp as wp

from synthbos.device import quiet_warp

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False, "fuse_fp": False})
#: The frame statistics' kernels are the GPU's engine, a Warp module of their own: the CPU computes the
#: statistics as host code (``tracking.frame_stats``) and builds only the segment medians below.
GPU_MODULE = f"{__name__}.gpu"
wp.set_module_options({"enable_backward": False, "fuse_fp": False}, module=GPU_MODULE)

# Bits of the per-column and per-frame flags.
NONFINITE = wp.constant(1)  # a pixel is NaN or +-inf
ANY_NAN = wp.constant(2)  # a pixel is NaN
FILL_NAN = wp.constant(4)  # a pixel of every fourth row and column is NaN
NOISE_NAN = wp.constant(8)  # a horizontal difference of the rows used by the noise estimate is NaN


@wp.kernel(module=GPU_MODULE)
def column_pass(
    images: wp.array3d(dtype=wp.float64),
    band: int,
    row_step: int,
    n_noise: int,
    n_frame: int,
    values: wp.array(dtype=wp.float64),
    keys: wp.array(dtype=wp.float32),
    slots: wp.array(dtype=wp.int32),
    col_min: wp.array3d(dtype=wp.float64),
    col_max: wp.array3d(dtype=wp.float64),
    col_count: wp.array3d(dtype=wp.int32),
    col_sum: wp.array3d(dtype=wp.float64),
    col_flags: wp.array3d(dtype=wp.int32),
):
    """Column ``j`` of band ``b`` of frame ``f``: its extremes, how many pixels equal its maximum, its sum
    and flags; and the values it owns (the differences ``|I[i, j+1] - I[i, j]|`` of every ``row_step``-th
    row, segment ``2 f``, and the pixels of every fourth row when ``j % 4 == 0``, segment ``2 f + 1``), each
    with its float32 sort key and its slot."""
    f, b, j = wp.tid()
    h = images.shape[1]
    w = images.shape[2]
    base = f * n_frame
    fill_cols = (w + 3) // 4
    vmin = wp.float64(wp.inf)
    vmax = wp.float64(-wp.inf)
    count = int(0)
    total = wp.float64(0.0)
    flags = int(0)
    i0 = b * band
    noise_row = ((i0 + row_step - 1) // row_step) * row_step  # the next row the noise estimate uses
    for i in range(i0, wp.min(h, i0 + band)):
        v = images[f, i, j]
        if not wp.isfinite(v):
            flags = flags | NONFINITE
            if wp.isnan(v):
                flags = flags | ANY_NAN
        # every comparison with NaN is false: NaN changes neither extreme (the flag reports it)
        if v < vmin:
            vmin = v
        if v > vmax:
            vmax = v
            count = 1
        elif v == vmax:
            count += 1
        total += v
        if i == noise_row:
            noise_row += row_step
            if j < w - 1:
                d = wp.abs(images[f, i, j + 1] - v)
                if wp.isnan(d):
                    flags = flags | NOISE_NAN
                    d = wp.float64(wp.inf)
                k = base + (i // row_step) * (w - 1) + j
                values[k] = d
                keys[k] = wp.float32(d)
                slots[k] = k
        if (i & 3) == 0 and (j & 3) == 0:
            s = v
            if wp.isnan(s):
                flags = flags | FILL_NAN
                s = wp.float64(wp.inf)
            k = base + n_noise + (i >> 2) * fill_cols + (j >> 2)
            values[k] = s
            keys[k] = wp.float32(s)
            slots[k] = k
    col_min[f, b, j] = vmin
    col_max[f, b, j] = vmax
    col_count[f, b, j] = count
    col_sum[f, b, j] = total
    col_flags[f, b, j] = flags


@wp.func
def reduce_columns(
    col_min: wp.array3d(dtype=wp.float64),
    col_max: wp.array3d(dtype=wp.float64),
    col_count: wp.array3d(dtype=wp.int32),
    col_sum: wp.array3d(dtype=wp.float64),
    col_flags: wp.array3d(dtype=wp.int32),
    f: int,
    b0: int,
    b1: int,
) -> tuple[wp.float64, wp.float64, int, wp.float64, int]:
    """Frame ``f``'s columns of bands ``b0 ... b1 - 1`` (in order): min, max, how many pixels equal the
    max (those of the columns whose max it is), sum and flags."""
    vmin = wp.float64(wp.inf)
    vmax = wp.float64(-wp.inf)
    total = wp.float64(0.0)
    flags = int(0)
    for b in range(b0, b1):
        for j in range(col_min.shape[2]):
            vmin = wp.min(vmin, col_min[f, b, j])
            vmax = wp.max(vmax, col_max[f, b, j])
            total += col_sum[f, b, j]
            flags = flags | col_flags[f, b, j]
    count = int(0)
    for b in range(b0, b1):
        for j in range(col_min.shape[2]):
            if col_max[f, b, j] == vmax:
                count += col_count[f, b, j]
    return vmin, vmax, count, total, flags


@wp.kernel(module=GPU_MODULE)
def band_moments(
    col_min: wp.array3d(dtype=wp.float64),
    col_max: wp.array3d(dtype=wp.float64),
    col_count: wp.array3d(dtype=wp.int32),
    col_sum: wp.array3d(dtype=wp.float64),
    col_flags: wp.array3d(dtype=wp.int32),
    band_min: wp.array3d(dtype=wp.float64),
    band_max: wp.array3d(dtype=wp.float64),
    band_count: wp.array3d(dtype=wp.int32),
    band_sum: wp.array3d(dtype=wp.float64),
    band_flags: wp.array3d(dtype=wp.int32),
):
    """Band ``b`` of frame ``f`` from its columns, as one column ``(f, b, 0)`` of the same kind: extremes,
    how many pixels equal its maximum (those of the columns whose maximum it is), sum and flags. One
    thread per band, so that :func:`frame_moments` reduces a few bands instead of every column."""
    f, b = wp.tid()
    vmin, vmax, count, total, flags = reduce_columns(col_min, col_max, col_count, col_sum, col_flags, f, b, b + 1)
    band_min[f, b, 0] = vmin
    band_max[f, b, 0] = vmax
    band_count[f, b, 0] = count
    band_sum[f, b, 0] = total
    band_flags[f, b, 0] = flags


@wp.kernel(module=GPU_MODULE)
def frame_moments(
    col_min: wp.array3d(dtype=wp.float64),
    col_max: wp.array3d(dtype=wp.float64),
    col_count: wp.array3d(dtype=wp.int32),
    col_sum: wp.array3d(dtype=wp.float64),
    col_flags: wp.array3d(dtype=wp.int32),
    n_pixels: wp.float64,
    lo: wp.array(dtype=wp.float64),
    hi: wp.array(dtype=wp.float64),
    bad: wp.array(dtype=wp.int32),
    saturation: wp.array(dtype=wp.float64),
    mean: wp.array(dtype=wp.float64),
    frame_flags: wp.array(dtype=wp.int32),
):
    """Frame ``f`` from its bands (:func:`band_moments`): min and max (NaN if a pixel is NaN, as NumPy's),
    the check of the tracker's ``_check_image`` (1 non-finite, 2 all zero, else 0), the saturation level
    (the maximum if five or more pixels equal it, else +inf) and the mean (exactly ``lo`` for a constant
    frame)."""
    f = wp.tid()
    vmin, vmax, count, total, flags = reduce_columns(
        col_min, col_max, col_count, col_sum, col_flags, f, 0, col_min.shape[1]
    )
    sat = wp.float64(wp.inf)
    if (flags & ANY_NAN) != 0:
        vmin = wp.float64(wp.nan)
        vmax = wp.float64(wp.nan)
    elif count >= 5:
        sat = vmax
    state = int(0)
    if (flags & NONFINITE) != 0:
        state = 1
    elif vmin == wp.float64(0.0) and vmax == wp.float64(0.0):
        state = 2
    m = total / n_pixels
    if vmin == vmax:
        m = vmin
    lo[f] = vmin
    hi[f] = vmax
    bad[f] = state
    saturation[f] = sat
    mean[f] = m
    frame_flags[f] = flags


@wp.kernel(module=GPU_MODULE)
def column_lags(
    images: wp.array3d(dtype=wp.float64),
    band: int,
    mean: wp.array(dtype=wp.float64),
    lags: wp.array3d(dtype=wp.vec4d),
):
    """Column ``j`` of band ``b`` of frame ``f``: its share of the four lag sums of the mean-subtracted frame:
    ``sum I'[i, j] I'[i, j+1]``, ``I'[i, j] I'[i+1, j]``, ``I'[i, j] I'[i, j+2]``, ``I'[i, j] I'[i+2, j]``
    over the pixels where both lie in the frame (``I' = I - mean``)."""
    f, b, j = wp.tid()
    h = images.shape[1]
    w = images.shape[2]
    m = mean[f]
    s01 = wp.float64(0.0)
    s10 = wp.float64(0.0)
    s02 = wp.float64(0.0)
    s20 = wp.float64(0.0)
    for i in range(b * band, wp.min(h, (b + 1) * band)):
        a = images[f, i, j] - m
        if j + 1 < w:
            s01 += a * (images[f, i, j + 1] - m)
        if j + 2 < w:
            s02 += a * (images[f, i, j + 2] - m)
        if i + 1 < h:
            s10 += a * (images[f, i + 1, j] - m)
        if i + 2 < h:
            s20 += a * (images[f, i + 2, j] - m)
    lags[f, b, j] = wp.vec4d(s01, s10, s02, s20)


@wp.func
def summed_lags(lags: wp.array3d(dtype=wp.vec4d), f: int, b0: int, b1: int) -> wp.vec4d:
    """The sum of frame ``f``'s lag sums over the columns of bands ``b0 ... b1 - 1`` (in order)."""
    s = wp.vec4d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for b in range(b0, b1):
        for j in range(lags.shape[2]):
            s = s + lags[f, b, j]
    return s


@wp.kernel(module=GPU_MODULE)
def band_lags(lags: wp.array3d(dtype=wp.vec4d), band_total: wp.array3d(dtype=wp.vec4d)):
    """Band ``b`` of frame ``f``: the sum of its columns' lag sums, as one column ``(f, b, 0)``."""
    f, b = wp.tid()
    band_total[f, b, 0] = summed_lags(lags, f, b, b + 1)


@wp.kernel(module=GPU_MODULE)
def segment_of_slot(slots: wp.array(dtype=wp.int32), n_frame: int, n_noise: int, segment: wp.array(dtype=wp.int32)):
    """The segment of the value in each sorted position: ``2 f`` for frame f's differences, ``2 f + 1``
    for its sub-sampled pixels."""
    p = wp.tid()
    k = slots[p]
    f = k // n_frame
    segment[p] = 2 * f + wp.where(k - f * n_frame < n_noise, 0, 1)


@wp.kernel(module=GPU_MODULE)
def frame_results(
    slots: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.float64),
    frame_flags: wp.array(dtype=wp.int32),
    lags: wp.array3d(dtype=wp.vec4d),
    n_frame: int,
    n_noise: int,
    n_fill: int,
    q_index: int,
    q_frac: wp.float64,
    noise_scale: wp.float64,
    fill: wp.array(dtype=wp.float64),
    noise: wp.array(dtype=wp.float64),
    diameter: wp.array(dtype=wp.float64),
):
    """Frame ``f``'s order statistics from the sorted slots, and its dot diameter from the lag sums.

    ``slots``: the values' slots sorted by segment, then by float32 key (:func:`order_statistic`).
    ``noise``: the lower quartile of the differences (``q_index = int(0.25 (n_noise - 1))``, ``q_frac``
    the remainder), interpolated as ``tracking.identify._lower_quartile`` does, over ``noise_scale``.
    ``fill``: the median of the sub-sampled pixels (mean of the middle two for an even count). Either is
    NaN where its values hold a NaN, as NumPy's percentile and median are. ``diameter``: the formula of
    ``tracking.diameter.estimate_dot_diameter``; NaN for a non-finite frame or one without a peak.
    """
    f = wp.tid()
    flags = frame_flags[f]
    base = f * n_frame

    q = wp.float64(0.0)
    if (flags & NOISE_NAN) != 0:
        q = wp.float64(wp.nan)
    elif n_noise > 0:
        a = order_statistic(slots, values, base, n_noise, q_index)
        b = a
        if q_index + 1 < n_noise:
            b = order_statistic(slots, values, base, n_noise, q_index + 1)
        if q_frac >= wp.float64(0.5):
            q = b - (b - a) * (wp.float64(1.0) - q_frac)
        else:
            q = a + (b - a) * q_frac
        q = q / noise_scale
    noise[f] = q

    med = wp.float64(0.0)
    k = n_fill // 2
    start = base + n_noise
    if (flags & FILL_NAN) != 0:
        med = wp.float64(wp.nan)
    elif n_fill % 2 == 1:
        med = order_statistic(slots, values, start, n_fill, k)
    else:
        lower = order_statistic(slots, values, start, n_fill, k - 1)
        med = (lower + order_statistic(slots, values, start, n_fill, k)) / wp.float64(2.0)
    fill[f] = med

    s = summed_lags(lags, f, 0, lags.shape[1])
    r1 = wp.float64(0.5) * (s[0] + s[1])
    r2 = wp.float64(0.5) * (s[2] + s[3])
    d = wp.float64(wp.nan)
    if (flags & NONFINITE) == 0 and r1 > wp.float64(0.0) and r2 > wp.float64(0.0) and r1 > r2:
        s2 = wp.float64(3.0) / (wp.float64(2.0) * wp.log(r1 / r2))
        d = wp.float64(4.0) * wp.sqrt(s2) / wp.sqrt(wp.float64(2.0))
    diameter[f] = d


# --- medians of segments (a stack's per-pair medians) ---------------------------------------------


@wp.kernel
def segment_keys(
    values: wp.array(dtype=wp.float64),
    valid: wp.array(dtype=wp.int32),
    keys: wp.array(dtype=wp.float32),
    order: wp.array(dtype=wp.int32),
):
    """Sort keys (the values rounded to float32, +inf where not taking part)."""
    i = wp.tid()
    order[i] = i
    if valid[i] != 0:
        keys[i] = wp.float32(values[i])
    else:
        keys[i] = wp.float32(wp.inf)


@wp.kernel
def segment_counts(valid: wp.array(dtype=wp.int32), length: int, chunk: int, count: wp.array(dtype=wp.int32)):
    """The count of values taking part per segment: thread t counts entries ``t chunk`` .. ``(t + 1) chunk -
    1`` and adds each segment's share once (one atomic per segment it meets, not one per value)."""
    t = wp.tid()
    n = valid.shape[0]
    s = int(-1)
    c = int(0)
    for i in range(t * chunk, wp.min((t + 1) * chunk, n)):
        if i // length != s:
            if c > 0:
                wp.atomic_add(count, s, c)
            s = i // length
            c = 0
        if valid[i] != 0:
            c += 1
    if c > 0:
        wp.atomic_add(count, s, c)


@wp.func
def count_at_most(order: wp.array(dtype=wp.int32), values: wp.array(dtype=wp.float64), at: int, g0: int, g1: int,
                  v: wp.float64) -> int:  # fmt: skip
    """How many of ``values[order[at + p]]``, ``g0 <= p < g1``, are at most ``v``."""
    c = int(0)
    for p in range(g0, g1):
        if values[order[at + p]] <= v:
            c += 1
    return c


@wp.func
def order_statistic(
    order: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.float64),
    base: int,
    count: int,
    k: int,
) -> wp.float64:
    """The k-th smallest (from 0) of a segment's ``count`` float64 values ``values[order[base + p]]``, the
    order sorted by their float32 keys (the values rounded to float32): rounding keeps the order but for
    values that round alike, so the k-th lies among those sharing its key, a group found by the keys
    and searched by counting. A large group is first narrowed by bisecting its value range; then the group's
    values are stepped through from below. Exact: the value NumPy's sort puts there."""
    key = wp.float32(values[order[base + k]])
    g0 = k
    while g0 > 0 and wp.float32(values[order[base + g0 - 1]]) == key:
        g0 -= 1
    g1 = k + 1
    while g1 < count and wp.float32(values[order[base + g1]]) == key:
        g1 += 1
    lo = values[order[base + g0]]
    hi = lo
    for p in range(g0 + 1, g1):
        v = values[order[base + p]]
        lo = wp.min(lo, v)
        hi = wp.max(hi, v)
    want = k - g0
    if lo == hi or count_at_most(order, values, base, g0, g1, lo) > want:
        return lo
    # count_at_most(a) <= want < count_at_most(hi) from here on
    a = lo
    b = hi
    steps = int(0)
    while g1 - g0 > 32 and steps < 2200:
        mid = a * wp.float64(0.5) + b * wp.float64(0.5)
        if not (mid > a and mid < b):
            break
        if count_at_most(order, values, base, g0, g1, mid) > want:
            b = mid
        else:
            a = mid
        steps += 1
    while True:
        m = hi
        for p in range(g0, g1):
            v = values[order[base + p]]
            if v > a and v < m:
                m = v
        if m == hi or count_at_most(order, values, base, g0, g1, m) > want:
            return m
        a = m
    return hi


@wp.kernel
def segment_median(
    order: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.float64),
    count: wp.array(dtype=wp.int32),
    length: int,
    median: wp.array(dtype=wp.float64),
):
    """NumPy's median of each segment's values taking part (the mean of the middle two for an even count;
    NaN for none)."""
    s = wp.tid()
    c = count[s]
    if c == 0:
        median[s] = wp.float64(wp.nan)
        return
    base = s * length
    k = c // 2
    upper = order_statistic(order, values, base, c, k)
    if c % 2 == 1:
        median[s] = upper
    else:
        median[s] = (order_statistic(order, values, base, c, k - 1) + upper) / wp.float64(2.0)
