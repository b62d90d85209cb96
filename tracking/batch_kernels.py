# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of batched dot tracking (:mod:`tracking.batch`) after identification: the predictor's
hand-over, the model fit, the table and medians of segments, for many image pairs in each launch.

Kernels and ``@wp.func`` steps only; the host code lives in :mod:`tracking.batch`. Dots are held flat:
dot ``i`` of a call belongs to frame ``i // per_frame`` (pair ``b``'s ``per_frame`` prior dots, in the
prior's order). Identification's rounds of claims are in :mod:`tracking.claim_kernels`; the model-fit
step is the single-pair tracker's (:mod:`tracking.fit_kernels`: ``fit_dot_step``), here reading one frame
of an image stack. Status bits and rule constants come from :mod:`tracking.kernel_constants`, which
reads them from :mod:`tracking.settings`, their one home.
"""

import warp as wp

from .fit_kernels import fit_dot_step
from .kernel_constants import (
    CC_FLAGGED,
    CC_VALID,
    DIAMETER_WIDTHS,
    DISTORTED,
    EDGE_CUT,
    EDGE_CUT_MAX,
    FIT_FALLBACK,
    FOUND_GRADIENT,
    FOUND_REFERENCE,
    MATCHED,
    MODEL_HI,
    MODEL_LO,
    OUTLIER,
    OUTSIDE_IMAGE,
    PIXEL_EDGE,
    PREDICTOR_MISMATCH,
    PREDICTOR_WEAK,
)
from .moment_kernels import moment_shift, moves, reference_background, reference_spread2

wp.config.quiet = True
wp.config.log_level = wp.LOG_WARNING
wp.set_module_options({"enable_backward": False})


@wp.kernel
def repeat_rows(one: wp.array(dtype=wp.vec2d), per_frame: int, out: wp.array(dtype=wp.vec2d)):
    """One set of positions for every pair: ``out[i] = one[i % per_frame]``."""
    i = wp.tid()
    out[i] = one[i % per_frame]


# --- predictor hand-over ----------------------------------------------------------------------------


@wp.kernel
def reference_or_prior(
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    prior: wp.array(dtype=wp.vec2d),
    base: wp.array(dtype=wp.vec2d),
):
    """Where the reference dot was found its position, else the prior."""
    i = wp.tid()
    if wp.isfinite(x[i]):
        base[i] = wp.vec2d(x[i], y[i])
    else:
        base[i] = prior[i]


@wp.kernel
def count_inside(
    base: wp.array(dtype=wp.vec2d), per_frame: int, height: int, width: int, count: wp.array(dtype=wp.int32)
):
    """Dots per pair inside the image (``tracking.predict.dots_inside``), which set the predictor's passes."""
    i = wp.tid()
    p = base[i]
    h = wp.float64(height)
    w = wp.float64(width)
    half = wp.float64(0.5)
    in_x = wp.abs(p[0] - (w - wp.float64(1.0)) * half) <= w * half
    if in_x and wp.abs(p[1] - (h - wp.float64(1.0)) * half) <= h * half:  # (NaN: never)
        wp.atomic_add(count, i // per_frame, 1)


@wp.kernel
def predicted_position(
    base: wp.array(dtype=wp.vec2d),
    uv: wp.array(dtype=wp.vec2d),
    pred: wp.array(dtype=wp.vec2d),
):
    """``base + nan_to_num(uv)`` (the gradient-image prediction)."""
    i = wp.tid()
    u = uv[i]
    du = u[0]
    dv = u[1]
    if not wp.isfinite(du):
        du = wp.float64(0.0)
    if not wp.isfinite(dv):
        dv = wp.float64(0.0)
    pred[i] = wp.vec2d(base[i][0] + du, base[i][1] + dv)


@wp.kernel
def list_misses(
    x_g: wp.array(dtype=wp.float64),
    x_r: wp.array(dtype=wp.float64),
    per_frame: int,
    count: wp.array(dtype=wp.int32),
    ids: wp.array(dtype=wp.int32),
    pair_has_miss: wp.array(dtype=wp.int32),
):
    """Dots found in the reference image but not by the narrow window in the gradient image (any order:
    each is measured on its own)."""
    i = wp.tid()
    if wp.isfinite(x_r[i]) and not wp.isfinite(x_g[i]):
        slot = wp.atomic_add(count, 0, 1)
        ids[slot] = i
        pair_has_miss[i // per_frame] = 1


# --- the model fit ----------------------------------------------------------------------------------


@wp.kernel
def model_starts(
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    i0: wp.array(dtype=wp.float64),
    per_frame: int,
    sigma0: wp.array(dtype=wp.float64),
    frame_base: int,
    frame_step: int,
    row0: int,
    params: wp.array2d(dtype=wp.float64),
    live: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32),
):
    """Starting parameters ``(x, y, I0 (1 + 1 / (12 s0^2)), s0, 0)`` of every found dot (``_model_start``);
    rows of dots not found get a harmless dot of no intensity (drawn as zero, never used)."""
    i = wp.tid()
    b = i // per_frame
    s0 = sigma0[b]
    j = row0 + i
    frame[j] = frame_base + frame_step * b
    if wp.isfinite(x[i]):
        params[j, 0] = x[i]
        params[j, 1] = y[i]
        params[j, 2] = i0[i] * (wp.float64(1.0) + wp.float64(1.0) / (wp.float64(12.0) * s0 * s0))
        params[j, 3] = s0
        params[j, 4] = wp.float64(0.0)
        live[j] = 1
    else:
        params[j, 0] = wp.float64(0.0)
        params[j, 1] = wp.float64(0.0)
        params[j, 2] = wp.float64(0.0)
        params[j, 3] = s0
        params[j, 4] = wp.float64(0.0)
        live[j] = 0


@wp.kernel
def pair_partners(live: wp.array(dtype=wp.int32), n: int, partner: wp.array(dtype=wp.int32)):
    """Row ``i`` (reference) and ``n + i`` (gradient) are one dot's pair where both were found."""
    i = wp.tid()
    if live[i] != 0 and live[n + i] != 0:
        partner[i] = n + i
        partner[n + i] = i
    else:
        partner[i] = -1
        partner[n + i] = -1


@wp.kernel
def largest_peak(
    params: wp.array2d(dtype=wp.float64), live: wp.array(dtype=wp.int32), peak: wp.array(dtype=wp.float64)
):
    i = wp.tid()
    if live[i] != 0:
        wp.atomic_max(peak, 0, wp.abs(params[i, 2]))


@wp.kernel
def fit_step_batch(
    references: wp.array3d(dtype=wp.float64),
    gradients: wp.array3d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    params: wp.array2d(dtype=wp.float64),
    start: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    live: wp.array(dtype=wp.int32),
    saturation: wp.array(dtype=wp.float64),
    eta0: wp.array(dtype=wp.float64),
    half: int,
    render_half: int,
    common: int,
    max_move: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
    out: wp.array2d(dtype=wp.float64),
    ok: wp.array(dtype=wp.int32),
    shared_xy: wp.array2d(dtype=wp.float64),
):
    """``fit_dot_step`` of row i; model frame ``2 b`` is pair b's reference image, ``2 b + 1`` its gradient
    image; the width's range is ``MODEL_WIDTH_RANGE`` eta0 of the pair."""
    i = wp.tid()
    if live[i] == 0:
        for k in range(5):
            out[i, k] = params[i, k]
        return
    f = frame[i]
    b = f // 2
    e0 = eta0[b]
    has_partner = int(partner[i] >= 0)
    lo = MODEL_LO * e0
    hi = MODEL_HI * e0
    if f % 2 == 0:
        fit_dot_step(
            references[b], models, inv_scale, params, start, f, i, has_partner, saturation[f], half, render_half,
            common, max_move, lo, hi, prof, out, ok, shared_xy,
        )  # fmt: skip
    else:
        fit_dot_step(
            gradients[b], models, inv_scale, params, start, f, i, has_partner, saturation[f], half, render_half,
            common, max_move, lo, hi, prof, out, ok, shared_xy,
        )  # fmt: skip


# --- the table ------------------------------------------------------------------------------------


@wp.struct
class TrackRow:
    """One row of ``tracking.settings.TRACK_DTYPE``, field for field (the same bytes: an array of rows
    comes back as the table itself)."""

    x: wp.float64
    y: wp.float64
    u: wp.float64
    v: wp.float64
    u_cc: wp.float64
    v_cc: wp.float64
    x_gradient: wp.float64
    y_gradient: wp.float64
    diameter: wp.float64
    peak: wp.float64
    status: wp.int32
    iteration: wp.int16
    iteration_gradient: wp.int16
    u_pred: wp.float64
    v_pred: wp.float64
    pred_correlation: wp.float64
    dot_id: wp.int64


@wp.kernel
def moment_shift_batch(
    references: wp.array3d(dtype=wp.float64),
    gradients: wp.array3d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    params: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    live: wp.array(dtype=wp.int32),
    saturation: wp.array(dtype=wp.float64),
    noise: wp.array(dtype=wp.float64),
    half: int,
    chi2: wp.float64,
    max_shift: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
    shift: wp.array(dtype=wp.vec3d),
):
    """``moment_shift`` of row i (model frame ``2 b``: pair b's reference image, ``2 b + 1`` its gradient
    image; ``noise`` per frame); ``apply_moment_shift`` then moves the rows."""
    i = wp.tid()
    shift[i] = wp.vec3d()
    if live[i] == 0:
        return
    f = frame[i]
    b = f // 2
    bg = reference_background(params, partner, i, f % 2 == 1)
    s2 = reference_spread2(params, partner, i)
    if f % 2 == 0:
        shift[i] = moment_shift(
            references[b], models, inv_scale, f, params, i, half, bg, s2, saturation[f], noise[f], chi2, max_shift,
            prof,
        )  # fmt: skip
    else:
        shift[i] = moment_shift(
            gradients[b], models, inv_scale, f, params, i, half, bg, s2, saturation[f], noise[f], chi2, max_shift,
            prof,
        )  # fmt: skip


@wp.kernel
def apply_moment_shift(
    shift: wp.array(dtype=wp.vec3d),
    partner: wp.array(dtype=wp.int32),
    params: wp.array2d(dtype=wp.float64),
    shared_xy: wp.array2d(dtype=wp.float64),
    moved: wp.array(dtype=wp.int32),
):
    """``tracking.pipeline._fit_models``' first-moment step, in place: where row i ``moves``, its position
    and its common-shape position move by its shift."""
    i = wp.tid()
    moved[i] = 0
    if moves(shift, partner, i):
        d = shift[i]
        params[i, 0] = params[i, 0] + d[0]
        params[i, 1] = params[i, 1] + d[1]
        shared_xy[i, 0] = shared_xy[i, 0] + d[0]
        shared_xy[i, 1] = shared_xy[i, 1] + d[1]
        moved[i] = 1


@wp.kernel
def take_model(
    params: wp.array2d(dtype=wp.float64),
    ok: wp.array(dtype=wp.int32),
    moved: wp.array(dtype=wp.int32),
    live: wp.array(dtype=wp.int32),
    row0: int,
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    eta: wp.array(dtype=wp.float64),
    i0: wp.array(dtype=wp.float64),
    flags: wp.array(dtype=wp.int32),
):
    """``_take_model``: the fit's position, width and peak (a refused last step flagged FIT_FALLBACK, a
    dot moved to its first moment DISTORTED)."""
    i = wp.tid()
    j = row0 + i
    if live[j] == 0 or not wp.isfinite(params[j, 0]):
        return
    x[i] = params[j, 0]
    y[i] = params[j, 1]
    eta[i] = params[j, 3]
    i0[i] = params[j, 2]
    if ok[j] == 0:
        flags[i] = flags[i] | FIT_FALLBACK
    if moved[j] != 0:
        flags[i] = flags[i] | DISTORTED


@wp.func
def overshoot(x: wp.float64, y: wp.float64, radius: wp.float64, height: int, width: int) -> wp.vec2d:
    """How far (px) a disk of ``radius`` at (x, y) reaches past the image, along x and y (``_overshoot``)."""
    half = PIXEL_EDGE
    zero = wp.float64(0.0)
    ox = wp.max(wp.max(-half - (x - radius), (x + radius) - (wp.float64(width) - half)), zero)
    oy = wp.max(wp.max(-half - (y - radius), (y + radius) - (wp.float64(height) - half)), zero)
    return wp.vec2d(ox, oy)


@wp.kernel
def first_status(
    x_r: wp.array(dtype=wp.float64),
    y_r: wp.array(dtype=wp.float64),
    flags_r: wp.array(dtype=wp.int32),
    x_g: wp.array(dtype=wp.float64),
    y_g: wp.array(dtype=wp.float64),
    flags_g: wp.array(dtype=wp.int32),
    uv_pred: wp.array(dtype=wp.vec2d),
    quality: wp.array(dtype=wp.float64),
    use_pred: int,
    tolerance: wp.float64,
    min_correlation: wp.float64,
    status: wp.array(dtype=wp.int32),
    xy: wp.array(dtype=wp.vec2d),
    uv: wp.array(dtype=wp.vec2d),
    good: wp.array(dtype=wp.int32),
    query: wp.array(dtype=wp.int32),
):
    """Status bits up to the predictor's check: found, the predictor's mismatch and weakness; the dots that
    vouch for their neighbours (``good``) and those whose mismatch the neighbours may overrule
    (``query``)."""
    i = wp.tid()
    s = flags_r[i] | (flags_g[i] & ~OUTSIDE_IMAGE)
    found_r = wp.isfinite(x_r[i])
    found_g = wp.isfinite(x_g[i])
    if found_r:
        s = s | FOUND_REFERENCE
    if found_g:
        s = s | FOUND_GRADIENT
    xy[i] = wp.vec2d(x_r[i], y_r[i])
    uv[i] = wp.vec2d(x_g[i] - x_r[i], y_g[i] - y_r[i])
    matched = found_r and found_g
    off = False
    weak = False
    if use_pred != 0:
        du = x_g[i] - x_r[i] - uv_pred[i][0]
        dv = y_g[i] - y_r[i] - uv_pred[i][1]
        off = found_r and found_g and not (wp.sqrt(du * du + dv * dv) <= tolerance)
        weak = found_r and not (quality[i] >= min_correlation)
    good[i] = int(matched and not off and not weak)
    query[i] = int(off and not weak)
    if off:
        s = s | PREDICTOR_MISMATCH  # cleared below where the neighbours confirm it
    if weak:
        s = s | PREDICTOR_WEAK
    status[i] = s


@wp.kernel
def second_status(
    confirmed: wp.array(dtype=wp.int32),
    query: wp.array(dtype=wp.int32),
    per_frame: int,
    height: int,
    width: int,
    diameter: wp.array(dtype=wp.float64),
    x_r: wp.array(dtype=wp.float64),
    y_r: wp.array(dtype=wp.float64),
    x_g: wp.array(dtype=wp.float64),
    y_g: wp.array(dtype=wp.float64),
    status: wp.array(dtype=wp.int32),
    matched: wp.array(dtype=wp.int32),
):
    """A mismatch the neighbours confirm is kept; then EDGE_CUT (``EDGE_CUT_PX``); the matched dots left
    go to the outlier test."""
    i = wp.tid()
    s = status[i]
    if query[i] != 0 and confirmed[i] != 0:
        s = s & ~PREDICTOR_MISMATCH
    m = (s & FOUND_REFERENCE) != 0 and (s & FOUND_GRADIENT) != 0
    m = m and (s & (PREDICTOR_MISMATCH | PREDICTOR_WEAK)) == 0
    if m:
        r = wp.float64(0.5) * diameter[i // per_frame]
        a = overshoot(x_r[i], y_r[i], r, height, width)
        c = overshoot(x_g[i], y_g[i], r, height, width)
        if wp.abs(a[0] - c[0]) > EDGE_CUT_MAX or wp.abs(a[1] - c[1]) > EDGE_CUT_MAX:
            s = s | EDGE_CUT
            m = False
    status[i] = s
    matched[i] = int(m)


@wp.kernel
def write_table(
    x_r: wp.array(dtype=wp.float64),
    y_r: wp.array(dtype=wp.float64),
    eta_r: wp.array(dtype=wp.float64),
    i0_r: wp.array(dtype=wp.float64),
    it_r: wp.array(dtype=wp.int32),
    x_g: wp.array(dtype=wp.float64),
    y_g: wp.array(dtype=wp.float64),
    it_g: wp.array(dtype=wp.int32),
    matched: wp.array(dtype=wp.int32),
    outlier: wp.array(dtype=wp.int32),
    shared_xy: wp.array2d(dtype=wp.float64),
    n: int,
    uv_pred: wp.array(dtype=wp.vec2d),
    quality: wp.array(dtype=wp.float64),
    use_pred: int,
    cc_threshold: wp.float64,
    status: wp.array(dtype=wp.int32),
    n_dots: int,
    table: wp.array(dtype=TrackRow),
):
    """The table's row i: the outlier test's verdict, MATCHED, the displacements and the model
    correction (``track_pair``'s last steps)."""
    i = wp.tid()
    nan = wp.float64(wp.nan)
    s = status[i]
    m = matched[i] != 0
    if m and outlier[i] != 0:
        s = s | OUTLIER
        m = False
    found_g = (s & FOUND_GRADIENT) != 0
    row = TrackRow()
    row.u = nan
    row.v = nan
    row.u_cc = nan
    row.v_cc = nan
    if m:
        s = s | MATCHED
        u = x_g[i] - x_r[i]
        v = y_g[i] - y_r[i]
        # the model correction: both positions refitted with the pair's common peak and width
        ucc = shared_xy[n + i, 0] - shared_xy[i, 0]
        vcc = shared_xy[n + i, 1] - shared_xy[i, 1]
        if wp.isfinite(ucc) and wp.isfinite(vcc):
            s = s | CC_VALID
        else:
            ucc = u
            vcc = v
        du = ucc - u
        dv = vcc - v
        if wp.sqrt(du * du + dv * dv) > cc_threshold:
            s = s | CC_FLAGGED
        row.u = u
        row.v = v
        row.u_cc = ucc
        row.v_cc = vcc
    row.x = x_r[i]
    row.y = y_r[i]
    row.x_gradient = nan
    row.y_gradient = nan
    row.iteration_gradient = wp.int16(0)
    if found_g:
        row.x_gradient = x_g[i]
        row.y_gradient = y_g[i]
        row.iteration_gradient = wp.int16(it_g[i])
    row.diameter = DIAMETER_WIDTHS * eta_r[i]
    row.peak = i0_r[i]
    row.status = s
    row.iteration = wp.int16(it_r[i])
    row.u_pred = nan
    row.v_pred = nan
    row.pred_correlation = nan
    if use_pred != 0:
        row.u_pred = uv_pred[i][0]
        row.v_pred = uv_pred[i][1]
        row.pred_correlation = quality[i]
    row.dot_id = wp.int64(i % n_dots)
    table[i] = row


# --- medians of segments ----------------------------------------------------------------------------


@wp.kernel
def segment_keys(
    values: wp.array(dtype=wp.float64),
    valid: wp.array(dtype=wp.int32),
    length: int,
    keys: wp.array(dtype=wp.float32),
    order: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """Sort keys (the values rounded to float32, +inf where not taking part) and the count per segment."""
    i = wp.tid()
    order[i] = i
    if valid[i] != 0:
        keys[i] = wp.float32(values[i])
        wp.atomic_add(count, i // length, 1)
    else:
        keys[i] = wp.float32(wp.inf)


@wp.func
def order_statistic(
    keys: wp.array(dtype=wp.float32),
    order: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.float64),
    base: int,
    count: int,
    k: int,
) -> wp.float64:
    """The k-th smallest (from 0) float64 value of a segment sorted by its float32 keys: rounding to float32
    keeps the order but for values that round alike, so the k-th lies among those sharing its key."""
    key = keys[base + k]
    g0 = k
    while g0 > 0 and keys[base + g0 - 1] == key:
        g0 -= 1
    g1 = k + 1
    while g1 < count and keys[base + g1] == key:
        g1 += 1
    lo = values[order[base + g0]]
    hi = lo
    for p in range(g0 + 1, g1):
        v = values[order[base + p]]
        lo = wp.min(lo, v)
        hi = wp.max(hi, v)
    if lo == hi:
        return lo
    want = k - g0
    for p in range(g0, g1):
        v = values[order[base + p]]
        rank = int(0)
        for q in range(g0, g1):
            u = values[order[base + q]]
            if u < v or (u == v and q < p):
                rank += 1
        if rank == want:
            return v
    return lo


@wp.kernel
def segment_median(
    keys: wp.array(dtype=wp.float32),
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
    upper = order_statistic(keys, order, values, base, c, k)
    if c % 2 == 1:
        median[s] = upper
    else:
        median[s] = (order_statistic(keys, order, values, base, c, k - 1) + upper) / wp.float64(2.0)


@wp.kernel
def interleave_pairs(
    first: wp.array(dtype=wp.float64),
    second: wp.array(dtype=wp.float64),
    x_first: wp.array(dtype=wp.float64),
    x_second: wp.array(dtype=wp.float64),
    per_frame: int,
    values: wp.array(dtype=wp.float64),
    valid: wp.array(dtype=wp.int32),
):
    """Pair b's segment of ``2 per_frame`` values: its dots' ``first`` then ``second`` (taking part where
    the matching ``x`` is finite)."""
    i = wp.tid()
    b = i // per_frame
    j = i % per_frame
    at = b * 2 * per_frame + j
    values[at] = first[i]
    valid[at] = int(wp.isfinite(x_first[i]))
    values[at + per_frame] = second[i]
    valid[at + per_frame] = int(wp.isfinite(x_second[i]))


@wp.kernel
def measured_peaks(
    ids: wp.array(dtype=wp.int32),
    out_int: wp.array2d(dtype=wp.int32),
    out_float: wp.array2d(dtype=wp.float64),
    values: wp.array(dtype=wp.float64),
    valid: wp.array(dtype=wp.int32),
):
    """The peaks of the blobs chosen in a call's first round, at their dots' places."""
    t = wp.tid()
    i = ids[t]
    if out_int[t, 0] >= 0:
        values[i] = out_float[t, 1]
        valid[i] = 1
