"""Warp kernels of the table: the status bits of a stack of pairs' dots and their rows of the table.

Kernels and ``@wp.func`` steps only; the host code, :mod:`tracking.table`, launches them
(:func:`first_status` before the neighbours confirm the predictor's mismatches, :func:`second_status`
after, :func:`write_table` after the outlier test) and copies the table back. Dots are held flat: dot
``i`` of a call belongs to pair ``i // per_frame``. Status bits and rule constants come from
:mod:`tracking.kernel_constants`, which reads them from :mod:`tracking.settings`, their one home;
:class:`TrackRow` is one row of ``TRACK_DTYPE``.
"""

import warp as wp

from synthbos.device import quiet_warp

from .kernel_constants import (
    CC_FLAGGED,
    CC_VALID,
    DIAMETER_WIDTHS,
    EDGE_CUT,
    EDGE_CUT_MAX,
    FOUND_GRADIENT,
    FOUND_REFERENCE,
    MASKED,
    MATCHED,
    MISREGISTERED,
    OUTLIER,
    PIXEL_EDGE,
    PREDICTOR_MISMATCH,
    PREDICTOR_WEAK,
)

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})


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
    g_bits: int,
    uv_pred: wp.array(dtype=wp.vec2d),
    quality: wp.array(dtype=wp.float64),
    use_pred: int,
    tolerance: wp.float64,
    min_correlation: wp.float64,
    hidden: wp.array(dtype=wp.int32),
    status: wp.array(dtype=wp.int32),
    xy: wp.array(dtype=wp.vec2d),
    uv: wp.array(dtype=wp.vec2d),
    good: wp.array(dtype=wp.int32),
    query: wp.array(dtype=wp.int32),
):
    """Status bits up to the predictor's check: found, MASKED (``hidden``: :func:`masked_rows`), the
    predictor's mismatch and weakness; the dots that vouch for their neighbours (``good``) and those whose
    mismatch the neighbours may overrule (``query``). The gradient dot's flags ``g_bits`` join the status
    (:func:`tracking.table.gradient_bits`)."""
    i = wp.tid()
    s = flags_r[i] | (flags_g[i] & g_bits)
    found_r = wp.isfinite(x_r[i])
    found_g = wp.isfinite(x_g[i])
    if found_r:
        s = s | FOUND_REFERENCE
    if found_g:
        s = s | FOUND_GRADIENT
    xy[i] = wp.vec2d(x_r[i], y_r[i])
    uv[i] = wp.vec2d(x_g[i] - x_r[i], y_g[i] - y_r[i])
    matched = found_r and found_g
    if hidden[i] != 0:
        s = s | MASKED
        matched = False
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


@wp.func
def touches(near: wp.array3d(dtype=wp.int32), b: int, x: wp.float64, y: wp.float64) -> bool:
    """Whether the rounded position lies on pair b's ``near`` (outside the image: False; ``mask.touches``)."""
    if not (wp.isfinite(x) and wp.isfinite(y)):
        return False
    c = wp.rint(x)
    r = wp.rint(y)
    if c < wp.float64(0.0) or r < wp.float64(0.0):
        return False
    if c >= wp.float64(near.shape[2]) or r >= wp.float64(near.shape[1]):
        return False
    return near[b, int(r), int(c)] != 0


@wp.kernel
def masked_rows(
    near: wp.array3d(dtype=wp.int32),
    per_frame: int,
    prior: wp.array(dtype=wp.vec2d),
    x_r: wp.array(dtype=wp.float64),
    y_r: wp.array(dtype=wp.float64),
    x_g: wp.array(dtype=wp.float64),
    y_g: wp.array(dtype=wp.float64),
    hidden: wp.array(dtype=wp.int32),
):
    """The dots whose reference, gradient or prior position (without one: ``prior`` of no rows) lies
    within a dot radius of pair b's excluded pixels (``near``: ``mask.mask_reach``): MASKED."""
    i = wp.tid()
    b = i // per_frame
    h = touches(near, b, x_r[i], y_r[i]) or touches(near, b, x_g[i], y_g[i])
    if prior.shape[0] > 0:
        h = h or touches(near, b, prior[i][0], prior[i][1])
    hidden[i] = int(h)


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
    m = m and (s & (PREDICTOR_MISMATCH | PREDICTOR_WEAK | MASKED)) == 0
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
    misregistered: wp.array(dtype=wp.int32),
    shared_xy: wp.array2d(dtype=wp.float64),
    cc_valid: wp.array(dtype=wp.int32),
    n: int,
    uv_pred: wp.array(dtype=wp.vec2d),
    quality: wp.array(dtype=wp.float64),
    use_pred: int,
    cc_threshold: wp.float64,
    status: wp.array(dtype=wp.int32),
    n_dots: int,
    with_prior: int,
    table: wp.array(dtype=TrackRow),
):
    """The table's row i: the outlier test's verdict, the registration's (``misregistered``; none given
    with a prior), MATCHED, the displacements and the correction: the difference of the two rows of
    ``shared_xy`` (the positions refitted with the pair's common peak and width, or the paper's
    correlation as :func:`tracking.correction.paper_correction_stack` writes it), valid where finite or,
    where ``cc_valid`` is given, where it says; a correction that is not finite gives way to the centroid
    difference. ``dot_id`` is the prior's row, -1 without a prior."""
    i = wp.tid()
    nan = wp.float64(wp.nan)
    s = status[i]
    m = matched[i] != 0
    if m and outlier[i] != 0:
        s = s | OUTLIER
        m = False
    if m and misregistered.shape[0] > 0:
        if misregistered[i] != 0:
            s = s | MISREGISTERED
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
        ucc = shared_xy[n + i, 0] - shared_xy[i, 0]
        vcc = shared_xy[n + i, 1] - shared_xy[i, 1]
        finite = wp.isfinite(ucc) and wp.isfinite(vcc)
        valid = finite
        if cc_valid.shape[0] > 0:
            valid = cc_valid[i] != 0
        if valid:
            s = s | CC_VALID
        if not finite:
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
    row.dot_id = wp.int64(-1)
    if with_prior != 0:
        row.dot_id = wp.int64(i % n_dots)
    table[i] = row


# --- medians of segments ----------------------------------------------------------------------------
