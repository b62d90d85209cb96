# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of identification over a stack of pairs: rounds of claims that give each blob to one dot.

Host code: :class:`tracking.identify.StackIdentification`. After the per-window measurement
(:mod:`tracking.identify_kernels`' ``measure_stack``): rounds of claims that give each blob to one dot,
the subtraction of waiting neighbours; one prior repeated for every pair and the peaks of the
first round (whose median sets the relative peak threshold).

Dots are held flat: dot ``i`` of a call belongs to frame ``i // per_frame``. Status bits and rule
constants come from :mod:`tracking.kernel_constants`.
"""

import warp as wp
from synthbos.correlation.pass_kernels import three_point_offset

from synthbos.device import quiet_warp

from .fit_kernels import to_fixed
from .kernel_constants import (
    AMBIGUOUS,
    CLIP_HI,
    CLIP_LO,
    FIT_FALLBACK,
    NEAR_BORDER,
    OUTSIDE_IMAGE,
    OVERLAPPED,
    PIXEL_EDGE,
    SATURATED,
    STAMP_WIDTHS,
    WIDTH_HI,
    WIDTH_LO,
)

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile
#: The claim board's rounds are the GPU's engine of identification, a Warp module of their own: the CPU
#: identifies pair by pair as host code (``identify_near_predictions``) and builds only ``release_claims`` (the
#: wide search's) and ``repeat_rows`` (a stack's prior) here.
GPU_MODULE = f"{__name__}.gpu"
wp.set_module_options({"enable_backward": False}, module=GPU_MODULE)


#: Largest int32: an unclaimed blob.
NO_CLAIM = wp.constant(2147483647)


# --- identification -------------------------------------------------------------------------------


@wp.kernel(module=GPU_MODULE)
def start_identification(
    pred: wp.array(dtype=wp.vec2d),
    ids: wp.array(dtype=wp.int32),
    height: int,
    width: int,
    half: int,
    origin: wp.array2d(dtype=wp.int32),
    todo: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """Window origin, OUTSIDE_IMAGE and NEAR_BORDER of dot ``ids[t]``; it is to do where inside."""
    i = ids[wp.tid()]
    p = pred[i]
    nan_or_out = not (p[0] > -PIXEL_EDGE and p[0] < wp.float64(width) - PIXEL_EDGE)
    nan_or_out = nan_or_out or not (p[1] > -PIXEL_EDGE and p[1] < wp.float64(height) - PIXEL_EDGE)
    if nan_or_out:
        flags[i] = OUTSIDE_IMAGE
        origin[i, 0] = -half
        origin[i, 1] = -half
        return
    ox = int(wp.rint(p[0])) - half
    oy = int(wp.rint(p[1])) - half
    origin[i, 0] = ox
    origin[i, 1] = oy
    todo[i] = 1
    if ox < 0 or oy < 0 or ox + 2 * half >= width or oy + 2 * half >= height:
        flags[i] = NEAR_BORDER


@wp.func
def claim_key(f: int, root_r: int, root_c: int, w: int, hp: int, wp_: int) -> int:
    """Flat index of a blob's peak pixel in the padded claim buffer (windows reach ``2 w`` past the edge)."""
    return (f * hp + root_r + 2 * w) * wp_ + root_c + 2 * w


@wp.kernel(module=GPU_MODULE)
def accept_blobs(
    ids: wp.array(dtype=wp.int32),
    per_frame: int,
    out_int: wp.array2d(dtype=wp.int32),
    out_float: wp.array2d(dtype=wp.float64),
    origin: wp.array2d(dtype=wp.int32),
    noise: wp.array(dtype=wp.float64),
    ref_peak: wp.array(dtype=wp.float64),
    snr: wp.float64,
    min_relative: wp.float64,
    w: int,
    hp: int,
    wp_: int,
    key: wp.array(dtype=wp.int32),
    claim_dist: wp.array(dtype=wp.float64),
):
    """A measured blob is a dot if its peak clears the noise and the frame's median peak; its key (-1 for
    none) and the smallest distance of a dot claiming its peak pixel."""
    t = wp.tid()
    i = ids[t]
    f = i // per_frame
    key[t] = -1
    chosen = out_int[t, 0]
    if chosen < 0:
        return
    cpeak = out_float[t, 1]
    rp = ref_peak[f]
    if not wp.isfinite(rp):
        rp = wp.float64(0.0)  # no blob in the first round
    if not (cpeak > snr * noise[f] and cpeak > min_relative * rp and cpeak > wp.float64(0.0)):
        return
    rr = chosen // w + origin[i, 1]
    rc = chosen % w + origin[i, 0]
    k = claim_key(f, rr, rc, w, hp, wp_)
    key[t] = k
    wp.atomic_min(claim_dist, k, out_float[t, 2])


@wp.kernel(module=GPU_MODULE)
def claim_nearest(
    ids: wp.array(dtype=wp.int32),
    out_float: wp.array2d(dtype=wp.float64),
    key: wp.array(dtype=wp.int32),
    claim_dist: wp.array(dtype=wp.float64),
    claim_id: wp.array(dtype=wp.int32),
):
    """Among the dots nearest a claimed blob, the one of the lowest index keeps it."""
    t = wp.tid()
    k = key[t]
    if k >= 0 and out_float[t, 2] == claim_dist[k]:
        wp.atomic_min(claim_id, k, ids[t])


@wp.kernel(module=GPU_MODULE)
def take_blobs(
    ids: wp.array(dtype=wp.int32),
    per_frame: int,
    it: int,
    out_int: wp.array2d(dtype=wp.int32),
    out_float: wp.array2d(dtype=wp.float64),
    cross: wp.array2d(dtype=wp.float64),
    origin: wp.array2d(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
    claim_id: wp.array(dtype=wp.int32),
    eta0: wp.array(dtype=wp.float64),
    w: int,
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    eta: wp.array(dtype=wp.float64),
    i0: wp.array(dtype=wp.float64),
    iteration: wp.array(dtype=wp.int32),
    root: wp.array2d(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
    todo: wp.array(dtype=wp.int32),
    won: wp.array(dtype=wp.int32),
):
    """The three-point Gaussian of each dot that keeps its blob (``tracking.identify.identify_near_predictions``); a dot
    that lost its blob to a nearer one is AMBIGUOUS and waits for the residual image."""
    t = wp.tid()
    k = key[t]
    if k < 0:
        return
    i = ids[t]
    if claim_id[k] != i:
        flags[i] = flags[i] | AMBIGUOUS
        return
    f = i // per_frame
    won[f] = 1
    cen = cross[t, 0]
    left = cross[t, 1]
    right = cross[t, 2]
    up = cross[t, 3]
    down = cross[t, 4]
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    dx = three_point_offset(left, cen, right, 0)
    dy = three_point_offset(up, cen, down, 0)
    fit_ok = cen > zero and left > zero and right > zero and up > zero and down > zero
    e = zero
    peak = cen
    if fit_ok:
        lc = wp.log(cen)
        cx = wp.log(left) - wp.float64(2.0) * lc + wp.log(right)
        cy = wp.log(up) - wp.float64(2.0) * lc + wp.log(down)
        fit_ok = cx < zero and cy < zero
        if fit_ok:
            e2 = wp.float64(0.5) * (-one / cx - one / cy)
            e = wp.sqrt(e2)
            peak = cen * wp.exp((dx * dx + dy * dy) / (wp.float64(2.0) * e2))
    # a three-point offset is within half a pixel: never wild; a failed fit keeps it (as the host)
    e0 = eta0[i // per_frame]
    if not (e > WIDTH_LO * e0 and e < WIDTH_HI * e0):
        e = e0
    if not (peak > zero and wp.isfinite(peak)):
        peak = out_float[t, 1]
    chosen = out_int[t, 0]
    rr = chosen // w + origin[i, 1]
    rc = chosen % w + origin[i, 0]
    x[i] = wp.float64(rc) + dx
    y[i] = wp.float64(rr) + dy
    eta[i] = e
    i0[i] = peak
    iteration[i] = it
    root[i, 0] = rc
    root[i, 1] = rr
    bits = int(0)
    if out_int[t, 1] > 1:
        bits = bits | OVERLAPPED
    if not fit_ok:
        bits = bits | FIT_FALLBACK
    if out_int[t, 2] >= 2:
        bits = bits | SATURATED
    flags[i] = (flags[i] & ~AMBIGUOUS) | bits
    todo[i] = 0


@wp.kernel
def release_claims(
    key: wp.array(dtype=wp.int32), claim_dist: wp.array(dtype=wp.float64), claim_id: wp.array(dtype=wp.int32)
):
    """Reset the claim buffers where this round wrote (for the next round and call)."""
    k = key[wp.tid()]
    if k >= 0:
        claim_dist[k] = wp.float64(wp.inf)
        claim_id[k] = NO_CLAIM


@wp.kernel(module=GPU_MODULE)
def next_round(won: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32)):
    """A frame in which a round found no dot stops (``identify_near_predictions``' ``break``)."""
    f = wp.tid()
    active[f] = active[f] * won[f]
    won[f] = 0


@wp.func
def grid_point(p: wp.vec2d, f: int, z_step: float) -> wp.vec3:
    return wp.vec3(wp.float32(p[0]), wp.float32(p[1]), float(f) * z_step)


@wp.kernel(module=GPU_MODULE)
def waiting_points(
    pred: wp.array(dtype=wp.vec2d),
    todo: wp.array(dtype=wp.int32),
    per_frame: int,
    z_step: float,
    points: wp.array(dtype=wp.vec3),
):
    """Hash-grid points of the dots still to find (others far away, spread over the grid's cells)."""
    i = wp.tid()
    if todo[i] != 0:
        points[i] = grid_point(pred[i], i // per_frame, z_step)
    else:
        points[i] = wp.vec3(-1.0e6 - 61.0 * float(i % 4093), -1.0e6 - 67.0 * float((i // 4093) % 4093), -1.0e6)


#: The residual's stamps are added in fixed point, ``STAMP_RANGE`` units per frame's median peak
#: (``stamp_scale``): integer sums do not depend on the order in which the threads add them, so the
#: residual image (and every dot measured on it) has the same bits on every run. A pixel holds a few
#: dots' stamps, far inside int64 (2**23 median peaks), resolved to 1e-12 of the peak.
STAMP_RANGE = wp.constant(wp.float64(2.0**40))


@wp.func
def stamp_scale(ref_peak: wp.float64) -> wp.float64:
    """Fixed-point units per intensity of a frame's stamps, from its median peak ``ref_peak`` (1 if it
    has none)."""
    p = wp.abs(ref_peak)
    if not (wp.isfinite(p) and p > wp.float64(0.0)):
        p = wp.float64(1.0)
    return STAMP_RANGE / p


@wp.func
def stamp_box(xi: wp.float64, yi: wp.float64, e0: wp.float64) -> wp.vec3i:
    """The stamp of a dot at ``(xi, yi)``: centre pixel (column, row) and half-width
    ceil(``STAMP_WIDTHS`` eta0)."""
    return wp.vec3i(int(wp.rint(xi)), int(wp.rint(yi)), int(wp.ceil(STAMP_WIDTHS * e0)))


@wp.func
def stamp_pixels(box: wp.vec3i, height: int, width: int) -> wp.vec4i:
    """The pixels of stamp ``box`` (:func:`stamp_box`) inside a ``height`` x ``width`` frame: rows
    ``[0, 1)`` and columns ``[2, 3)`` of the result."""
    return wp.vec4i(
        wp.max(box[1] - box[2], 0), wp.min(box[1] + box[2] + 1, height),
        wp.max(box[0] - box[2], 0), wp.min(box[0] + box[2] + 1, width),
    )  # fmt: skip


@wp.kernel(module=GPU_MODULE)
def stamp_near_waiting(
    grid: wp.uint64,
    ids: wp.array(dtype=wp.int32),
    per_frame: int,
    z_step: float,
    round_: int,
    active: wp.array(dtype=wp.int32),
    pred: wp.array(dtype=wp.vec2d),
    todo: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    eta: wp.array(dtype=wp.float64),
    i0: wp.array(dtype=wp.float64),
    eta0: wp.array(dtype=wp.float64),
    reach: wp.array(dtype=wp.float64),
    ref_peak: wp.array(dtype=wp.float64),
    subtracted: wp.array(dtype=wp.int32),
    stamps: wp.array3d(dtype=wp.int64),
):
    """Eq. 2 where it matters: a found dot within ``reach`` of a dot still to find is marked
    ``subtracted = round_`` and adds its sampled Gaussian (width clipped to ``RESIDUAL_WIDTH_CLIP`` eta0,
    stamp :func:`stamp_box`) to ``stamps`` in fixed point (:func:`stamp_scale`);
    :func:`apply_stamps` then takes them from the residual image."""
    i = ids[wp.tid()]
    f = i // per_frame
    if active[f] == 0 or subtracted[i] != 0 or not wp.isfinite(x[i]):
        return
    r = reach[f]
    xi = x[i]
    yi = y[i]
    q = wp.hash_grid_query(grid, grid_point(wp.vec2d(xi, yi), f, z_step), float(r) + 1.0)
    near = bool(False)
    for j in q:
        if j // per_frame == f and todo[j] != 0:
            dx = pred[j][0] - xi
            dy = pred[j][1] - yi
            if wp.sqrt(dx * dx + dy * dy) <= r:
                near = True
    if not near:
        return
    subtracted[i] = round_
    e0 = eta0[f]
    e = wp.clamp(eta[i], CLIP_LO * e0, CLIP_HI * e0)
    inv = wp.float64(1.0) / (wp.float64(2.0) * e * e)
    a = i0[i]
    scale = stamp_scale(ref_peak[f])
    px = stamp_pixels(stamp_box(xi, yi, e0), stamps.shape[1], stamps.shape[2])
    for rr in range(px[0], px[1]):
        ty = wp.float64(rr) - yi
        gy = wp.exp(-(ty * ty) * inv)
        for cc in range(px[2], px[3]):
            tx = wp.float64(cc) - xi
            wp.atomic_add(stamps, f, rr, cc, to_fixed(a * gy * wp.exp(-(tx * tx) * inv), scale))


@wp.kernel(module=GPU_MODULE)
def apply_stamps(
    ids: wp.array(dtype=wp.int32),
    per_frame: int,
    round_: int,
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    eta0: wp.array(dtype=wp.float64),
    ref_peak: wp.array(dtype=wp.float64),
    subtracted: wp.array(dtype=wp.int32),
    image: wp.array3d(dtype=wp.float64),
    stamps: wp.array3d(dtype=wp.int64),
    residual: wp.array3d(dtype=wp.float64),
):
    """The residual where the dots subtracted in ``round_`` lie: ``image`` less all the stamps so far.
    Every dot whose stamp covers a pixel writes the same value there, so the order does not matter."""
    i = ids[wp.tid()]
    f = i // per_frame
    if subtracted[i] != round_:
        return
    inv_scale = wp.float64(1.0) / stamp_scale(ref_peak[f])
    px = stamp_pixels(stamp_box(x[i], y[i], eta0[f]), stamps.shape[1], stamps.shape[2])
    for rr in range(px[0], px[1]):
        for cc in range(px[2], px[3]):
            residual[f, rr, cc] = image[f, rr, cc] - wp.float64(stamps[f, rr, cc]) * inv_scale


@wp.kernel(module=GPU_MODULE)
def clear_stamps(
    ids: wp.array(dtype=wp.int32),
    per_frame: int,
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    eta0: wp.array(dtype=wp.float64),
    subtracted: wp.array(dtype=wp.int32),
    stamps: wp.array3d(dtype=wp.int64),
):
    """``stamps`` zero again where the subtracted dots left theirs (ready for the next call)."""
    i = ids[wp.tid()]
    f = i // per_frame
    if subtracted[i] == 0:
        return
    px = stamp_pixels(stamp_box(x[i], y[i], eta0[f]), stamps.shape[1], stamps.shape[2])
    for rr in range(px[0], px[1]):
        for cc in range(px[2], px[3]):
            stamps[f, rr, cc] = wp.int64(0)


# --- a stack's priors and the first round's peaks ----------------------------------------------------


@wp.kernel
def repeat_rows(one: wp.array(dtype=wp.vec2d), per_frame: int, out: wp.array(dtype=wp.vec2d)):
    """One set of positions for every pair: ``out[i] = one[i % per_frame]``."""
    i = wp.tid()
    out[i] = one[i % per_frame]


@wp.kernel
def row_numbers(out: wp.array(dtype=wp.int32)):
    """Every row's own number: ``out[i] = i`` (the ids of all rows, made where they are used)."""
    i = wp.tid()
    out[i] = i


@wp.kernel(module=GPU_MODULE)
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
