"""Warp kernels of the shared-kernel step: the dots' light split by non-parametric ray-landing kernels.

The elliptical step (:mod:`tracking.ellipse_kernels`) gives each distorted dot a Gaussian shape; the
rays of a dot seen through a sharp interface land in a shape no Gaussian follows, and in a crowded
pattern the light a Gaussian share hands to the wrong dot is most of the error left. Neighbouring dots
see nearly the same flow, so they can share one **kernel**: dot ``i``'s kernel ``a_i`` is ``T x T``
weights on a sub-pixel grid of offsets ``s_k`` (``KER_TAPS``, ``KER_STEP``), and a dot ``j`` drawn with it
is

``F_j sum_k a_k G(x - m_j - s_k + mu(a))``

with ``G`` the pixel-integrated spot (width ``sigma_j``, the reference's), ``F_j`` its flux in units of
the unit-peak spot and ``mu(a)`` the kernel's mean, so that the kernel's mean sits at the dot's position
``m_j``. Per row (``fit_rows_setup``, then an engine by device), the kernel fit fits ``a_i`` by weighted ridge
least squares to the window of pixels about ``m_i``, every dot within ``KER_REACH`` of it drawn with ``a_i``.
Window weight and pixel grid are separable, so the normal matrix is a sum over neighbour pairs ``(j, k)`` of
Kronecker products ``Y_jk (x) X_jk`` of ``T x T`` factors; it is solved by a Cholesky factorisation in a
chunked global scratch. ``kernel_render`` draws every row's model with its own kernel on its stamp,
``kernel_accumulate`` the stamps times their multipliers into the fixed-point model image, ``kernel_hold``
fits the multipliers, and ``kernel_moment`` moves each row to the first moment of its held share.

Rows are compact: row ``p`` of the step is the tracker's row ``rows[p]``; frame ``f`` is image ``f % 2``
(0 the reference, 1 the gradient image) of pair ``f // 2``. The host code is
:func:`tracking.kernel_step.kernel_step`; the NumPy reference,
``tracking.reference.moment_shifts_numpy(..., kernel=True)``, defines the result.
"""

import warp as wp

from .ellipse_kernels import ellipse_fit_step, round_start, vec6d
from .fit_kernels import profile_pixel, profile_start, to_fixed
from .kernel_constants import (
    KER_FLUX_BOUND,
    KER_FLUX_STEP,
    KER_MAX_NEIGHBOURS,
    KER_PRIOR_MIN_VAR,
    KER_REACH,
    KER_RIDGE,
    KER_STEP,
    KER_TAPS,
    KER_UNKNOWNS,
    KER_WINDOW,
    KER_WINDOW_HALF,
    KER_WINDOW_SIGMA,
)
from .moment_kernels import DISTORTED_CODE, SHARE_FLOOR, moves, reference_background

wp.set_module_options({"enable_backward": False, "max_unroll": 1})
#: The GPU's engine of the fit (``fit_rows_normal`` .. ``fit_rows_solve``, a thread per entry) is a Warp module of
#: its own: the CPU fits a row in one thread (``fit_rows_one_thread``) and never builds it.
GPU_MODULE = f"{__name__}.gpu"
wp.set_module_options({"enable_backward": False, "max_unroll": 1}, module=GPU_MODULE)

TWELFTH = wp.constant(wp.float64(1.0 / 12.0))
mat_taps = wp.types.matrix(shape=(KER_TAPS, KER_TAPS), dtype=wp.float64)
vec_taps = wp.types.vector(length=KER_TAPS, dtype=wp.float64)
vec_window = wp.types.vector(length=KER_WINDOW, dtype=wp.float64)


@wp.func
def tap(a: int) -> wp.float64:
    """Offset (px) of grid tap ``a`` from the kernel's centre."""
    return wp.float64(a - KER_TAPS // 2) * KER_STEP


@wp.func
def pixel(refs: wp.array3d(dtype=wp.float64), grads: wp.array3d(dtype=wp.float64), f: int, y: int, x: int):
    """Pixel ``(y, x)`` of frame f's image."""
    if f % 2 == 1:
        return grads[f // 2, y, x]
    return refs[f // 2, y, x]


@wp.func
def kernel_mean(a: wp.array2d(dtype=wp.float64), p: int) -> wp.vec2d:
    """Mean offset ``mu(a)`` (x, y) of row p's kernel."""
    total = wp.float64(0.0)
    sx = wp.float64(0.0)
    sy = wp.float64(0.0)
    for b in range(KER_TAPS):
        for c in range(KER_TAPS):
            v = a[p, b * KER_TAPS + c]
            total += v
            sx += v * tap(c)
            sy += v * tap(b)
    return wp.vec2d(sx / total, sy / total)


@wp.func
def store_profile(
    out: wp.array3d(dtype=wp.float64), t: int, row: int, c: wp.float64, s: wp.float64, first: int, n: int,
    gain: wp.float64,
):  # fmt: skip
    """``gain`` times the pixel profile of a unit-peak spot of width ``s`` centred at ``c`` on pixels
    ``first .. first + n - 1``, into ``out[t, row, :n]``."""
    inv = wp.float64(1.0) / s
    z, g, e, ratio, direct = profile_start(first, c, inv)
    step = wp.exp(-inv * inv)
    scale = wp.float64(1.2533141373155003) * s
    for k in range(n):
        z, g, e, ratio, v, _dc, _ds = profile_pixel(z, g, e, ratio, direct, inv, step, scale)
        out[t, row, k] = gain * v


@wp.kernel
def kernel_frames(
    shift: wp.array(dtype=wp.vec3d), partner: wp.array(dtype=wp.int32), live: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32), busy: wp.array(dtype=wp.int32),
):  # fmt: skip
    """Frame of a live row that the first-moment step ``moves`` takes part."""
    i = wp.tid()
    if live[i] != 0 and moves(shift, partner, i):
        busy[frame[i]] = 1


@wp.kernel
def row_points(
    params: wp.array2d(dtype=wp.float64), frame: wp.array(dtype=wp.int32), live: wp.array(dtype=wp.int32),
    z_step: float, points: wp.array(dtype=wp.vec3),
):  # fmt: skip
    """Hash-grid point of row i: its fitted position, frames apart along z (a row not live far below)."""
    i = wp.tid()
    z = float(frame[i]) * z_step
    if live[i] == 0:
        z = -1.0e9
    points[i] = wp.vec3(wp.float32(params[i, 0]), wp.float32(params[i, 1]), z)


@wp.kernel
def kernel_rows(
    grid: wp.uint64, z_step: float, params: wp.array2d(dtype=wp.float64), shift: wp.array(dtype=wp.vec3d),
    partner: wp.array(dtype=wp.int32), live: wp.array(dtype=wp.int32), frame: wp.array(dtype=wp.int32),
    busy: wp.array(dtype=wp.int32), part: wp.array(dtype=wp.int32),
):  # fmt: skip
    """A live row takes part where a moving row of its frame lies within ``KER_REACH`` of it (itself too; no
    row of a frame without one, ``busy``, looks)."""
    i = wp.tid()
    part[i] = 0
    if live[i] == 0 or busy[frame[i]] == 0:
        return
    f = frame[i]
    centre = wp.vec3(wp.float32(params[i, 0]), wp.float32(params[i, 1]), float(f) * z_step)
    for q in wp.hash_grid_query(grid, centre, float(KER_REACH) + 0.5):
        if live[q] != 0 and frame[q] == f and moves(shift, partner, q):
            dx = params[q, 0] - params[i, 0]
            dy = params[q, 1] - params[i, 1]
            if dx * dx + dy * dy <= KER_REACH * KER_REACH:
                part[i] = 1


@wp.kernel
def not_taking_part(
    live: wp.array(dtype=wp.int32), part: wp.array(dtype=wp.int32), frame: wp.array(dtype=wp.int32),
    busy: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32),
):  # fmt: skip
    """A live row of a frame with a moving row (``busy``, ``kernel_frames``) that does not take part: its
    symmetric model stays in the model image (no other frame's image is read)."""
    i = wp.tid()
    out[i] = int(live[i] != 0 and part[i] == 0 and busy[frame[i]] != 0)


@wp.kernel
def prior_start(
    params: wp.array2d(dtype=wp.float64), rows: wp.array(dtype=wp.int32), ell: wp.array2d(dtype=wp.float64)
):
    """Row's elliptical model starts as the symmetric fit's (as ``ellipse_start``)."""
    round_start(params, rows[wp.tid()], ell)


@wp.kernel
def prior_fit(
    refs: wp.array3d(dtype=wp.float64), grads: wp.array3d(dtype=wp.float64), models: wp.array(dtype=wp.int64),
    scales: wp.array(dtype=wp.float64), params: wp.array2d(dtype=wp.float64), frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int32), half: int, ell: wp.array2d(dtype=wp.float64),
):  # fmt: skip
    """``ellipse_fit_step`` of a row in either image (a gradient-image row on its partner's background)."""
    i = rows[wp.tid()]
    f = frame[i]
    b = reference_background(params, partner, i, f % 2 == 1)
    inv = wp.float64(1.0) / scales[f]
    if f % 2 == 1:
        ellipse_fit_step(grads[f // 2], models, inv, f, params, i, half, b, ell)
    else:
        ellipse_fit_step(refs[f // 2], models, inv, f, params, i, half, b, ell)


@wp.kernel
def kernel_start(
    params: wp.array2d(dtype=wp.float64), frame: wp.array(dtype=wp.int32), partner: wp.array(dtype=wp.int32),
    shift: wp.array(dtype=wp.vec3d), rows: wp.array(dtype=wp.int32), ell: wp.array2d(dtype=wp.float64),
    pos: wp.array(dtype=wp.vec2d), flux: wp.array(dtype=wp.float64), sigma: wp.array(dtype=wp.float64),
    background: wp.array(dtype=wp.float64), prior: wp.array2d(dtype=wp.float64), kern: wp.array2d(dtype=wp.float64),
):  # fmt: skip
    """Row p's state: its position (the fit's, moved by the earlier steps where it moves), the spot's
    width and flux (its partner's for a gradient-image row: a dot sends the same rays in both images; the
    flux in units of the unit-peak spot, its fitted peak), its background, and its prior kernel: the
    elliptical fit's covariance less the pixel's and the spot's (eigenvalues at least ``KER_PRIOR_MIN_VAR``)
    as a Gaussian on the grid, summing to 1; its kernel starts there."""
    p = wp.tid()
    i = rows[p]
    gradient = frame[i] % 2 == 1
    j = partner[i]
    s = params[i, 3]
    if gradient and j >= 0:
        s = params[j, 3]
    sigma[p] = s
    flux[p] = params[i, 2]  # the reference flux, in units of the unit-peak spot of width s
    if gradient and j >= 0:
        flux[p] = params[j, 2]
    background[p] = reference_background(params, partner, i, gradient)
    pos[p] = wp.vec2d(params[i, 0], params[i, 1])
    if moves(shift, partner, i):
        pos[p] = wp.vec2d(params[i, 0] + shift[i][0], params[i, 1] + shift[i][1])
    r1 = ell[i, 3]
    r2 = ell[i, 4]
    r3 = ell[i, 5]
    det = r1 * r1 * r3 * r3
    extra = TWELFTH + s * s
    cxx = (r2 * r2 + r3 * r3) / det - extra
    cxy = -r1 * r2 / det
    cyy = r1 * r1 / det - extra
    # eigenvalues at least KER_PRIOR_MIN_VAR: add (floor - ev) v v^T, v v^T = (C - other I) / (ev - other)
    mid = wp.float64(0.5) * (cxx + cyy)
    rad = wp.sqrt(wp.float64(0.25) * (cxx - cyy) * (cxx - cyy) + cxy * cxy)
    lo = mid - rad
    hi = mid + rad
    if hi < KER_PRIOR_MIN_VAR:
        cxx = KER_PRIOR_MIN_VAR
        cyy = KER_PRIOR_MIN_VAR
        cxy = wp.float64(0.0)
    elif lo < KER_PRIOR_MIN_VAR:
        g = (KER_PRIOR_MIN_VAR - lo) / (lo - hi)
        cxx = cxx + g * (cxx - hi)
        cyy = cyy + g * (cyy - hi)
        cxy = cxy + g * cxy
    d = cxx * cyy - cxy * cxy
    total = wp.float64(0.0)
    for b in range(KER_TAPS):
        for c in range(KER_TAPS):
            gx = tap(c)
            gy = tap(b)
            q = (cyy * gx * gx - wp.float64(2.0) * cxy * gx * gy + cxx * gy * gy) / d
            v = wp.exp(wp.float64(-0.5) * q)
            prior[p, b * KER_TAPS + c] = v
            total += v
    for k in range(KER_UNKNOWNS):
        prior[p, k] = prior[p, k] / total
        kern[p, k] = prior[p, k]


@wp.kernel
def kernel_points(
    pos: wp.array(dtype=wp.vec2d), rows: wp.array(dtype=wp.int32), frame: wp.array(dtype=wp.int32),
    z_step: float, points: wp.array(dtype=wp.vec3),
):  # fmt: skip
    """Hash-grid point of row p: its position, frames apart along z."""
    p = wp.tid()
    points[p] = wp.vec3(wp.float32(pos[p][0]), wp.float32(pos[p][1]), float(frame[rows[p]]) * z_step)


@wp.func
def before(pos: wp.array(dtype=wp.vec2d), a: int, b: int) -> bool:
    """Whether row a's position comes before row b's in raster order (y, then x)."""
    return pos[a][1] < pos[b][1] or (pos[a][1] == pos[b][1] and pos[a][0] < pos[b][0])


@wp.func
def gather_neighbours(
    grid: wp.uint64, pos: wp.array(dtype=wp.vec2d), rows: wp.array(dtype=wp.int32), frame: wp.array(dtype=wp.int32),
    z_step: float, p: int, t: int, nbr: wp.array2d(dtype=wp.int32),
) -> int:  # fmt: skip
    """The rows of row p's frame within ``KER_REACH`` of it (itself too) into ``nbr[t]``; their count
    (more than ``KER_MAX_NEIGHBOURS``: that many plus one, the list cut)."""
    f = frame[rows[p]]
    centre = wp.vec3(wp.float32(pos[p][0]), wp.float32(pos[p][1]), float(f) * z_step)
    count = int(0)  # noqa: UP018, RUF046 (a Warp variable, not a constant)
    for q in wp.hash_grid_query(grid, centre, float(KER_REACH) + 0.5):
        if frame[rows[q]] == f:
            dx = pos[q][0] - pos[p][0]
            dy = pos[q][1] - pos[p][1]
            if dx * dx + dy * dy <= KER_REACH * KER_REACH:
                if count < KER_MAX_NEIGHBOURS:
                    nbr[t, count] = q
                count += 1
    count = wp.min(count, KER_MAX_NEIGHBOURS + 1)
    # in raster order of their positions (insertion sort): the fit's sums then do not depend on the rows'
    # order or the grid's, and a pair tracked alone and in a stack agree to the bit
    for k in range(1, wp.min(count, KER_MAX_NEIGHBOURS)):
        q = nbr[t, k]
        j = k
        while j > 0 and before(pos, q, nbr[t, j - 1]):
            nbr[t, j] = nbr[t, j - 1]
            j -= 1
        nbr[t, j] = q
    return count


@wp.func
def window_weight(at: int, centre: wp.float64, size: int) -> wp.float64:
    """The window's separable weight along one axis at pixel ``at`` (0 outside the image)."""
    if at < 0 or at >= size:
        return wp.float64(0.0)
    d = wp.float64(at) - centre
    return wp.exp(wp.float64(-0.5) * d * d / (KER_WINDOW_SIGMA * KER_WINDOW_SIGMA))


@wp.func
def neighbour_profiles(
    pos: wp.array(dtype=wp.vec2d), flux: wp.array(dtype=wp.float64), sigma: wp.array(dtype=wp.float64),
    mu: wp.vec2d, ox: int, oy: int, t: int, count: int, nbr: wp.array2d(dtype=wp.int32),
    prof: wp.array3d(dtype=wp.float64),
):  # fmt: skip
    """Each neighbour's window profiles per tap, drawn with the row's kernel: ``prof[t, (2 s) T + a]`` its
    x profile (times its flux) at tap a, ``prof[t, (2 s + 1) T + b]`` its y profile at tap b."""
    for s in range(count):
        q = nbr[t, s]
        for a in range(KER_TAPS):
            store_profile(prof, t, 2 * s * KER_TAPS + a, pos[q][0] - mu[0] + tap(a), sigma[q], ox, KER_WINDOW, flux[q])
            store_profile(prof, t, (2 * s + 1) * KER_TAPS + a, pos[q][1] - mu[1] + tap(a), sigma[q], oy, KER_WINDOW,
                          wp.float64(1.0))  # fmt: skip


@wp.func
def factor(prof: wp.array3d(dtype=wp.float64), t: int, r0: int, r1: int, w: vec_window):
    """``sum_x prof[t, r0 + a, x] w[x] prof[t, r1 + c, x]`` for every tap pair ``(a, c)`` (a row of sums at
    a time: the sums of a row do not wait on each other)."""
    out = mat_taps()
    for a in range(KER_TAPS):
        acc = vec_taps()
        for x in range(KER_WINDOW):
            pa = prof[t, r0 + a, x] * w[x]
            for c in range(KER_TAPS):
                acc[c] += pa * prof[t, r1 + c, x]
        for c in range(KER_TAPS):
            out[a, c] = acc[c]
    return out


@wp.func
def normal_equations(
    prof: wp.array3d(dtype=wp.float64), t: int, count: int, wx: vec_window, wy: vec_window, first: int,
    rows_x: wp.array2d(dtype=vec_taps), cols_x: wp.array2d(dtype=vec_taps), y: wp.array2d(dtype=wp.float64),
    normal: wp.array3d(dtype=wp.float64),
):  # fmt: skip
    """The lower triangle of the normal matrix ``sum_(j, k) Y_jk (x) X_jk`` into ``normal[t]``: the factors
    of the pairs ``k >= j`` into the scratch from ``first`` on (pair q: ``rows_x[q, a]`` row a of X,
    ``cols_x[q, a]`` its column a, ``y[q, b T + b']`` Y; X halved where ``k = j``), then each row of a
    ``T x T`` block of N summed over them as a vector, the pairs ``k > j`` with their transposes
    (``Y_kj (x) X_kj = (Y_jk (x) X_jk)^T``)."""
    q = first
    for s in range(count):
        for r in range(s, count):
            fx = factor(prof, t, 2 * s * KER_TAPS, 2 * r * KER_TAPS, wx)
            fy = factor(prof, t, (2 * s + 1) * KER_TAPS, (2 * r + 1) * KER_TAPS, wy)
            if r == s:
                fx = fx * wp.float64(0.5)
            for a in range(KER_TAPS):
                rows_x[q, a] = fx[a]
                col = vec_taps()
                for c in range(KER_TAPS):
                    col[c] = fx[c, a]
                    y[q, a * KER_TAPS + c] = fy[a, c]
                cols_x[q, a] = col
            q += 1
    for b in range(KER_TAPS):
        for b2 in range(b + 1):
            for a in range(KER_TAPS):
                acc = vec_taps()
                for k in range(first, q):
                    acc = acc + y[k, b * KER_TAPS + b2] * rows_x[k, a] + y[k, b2 * KER_TAPS + b] * cols_x[k, a]
                top = KER_TAPS
                if b2 == b:
                    top = a + 1
                for a2 in range(top):
                    normal[t, b * KER_TAPS + a, b2 * KER_TAPS + a2] = acc[a2]


@wp.func
def right_side(
    refs: wp.array3d(dtype=wp.float64), grads: wp.array3d(dtype=wp.float64), f: int, level: wp.float64,
    ox: int, oy: int, prof: wp.array3d(dtype=wp.float64), t: int, count: int,
    wx: vec_window, wy: vec_window,
    rhs: wp.array2d(dtype=wp.float64),
):  # fmt: skip
    """``sum_pixels A W (I - level)`` into ``rhs[t]`` (``A`` the design of every neighbour)."""
    for u in range(KER_UNKNOWNS):
        rhs[t, u] = wp.float64(0.0)
    for y in range(KER_WINDOW):
        if wy[y] == wp.float64(0.0):
            continue
        for s in range(count):
            for a in range(KER_TAPS):
                v = wp.float64(0.0)
                for x in range(KER_WINDOW):
                    if wx[x] != wp.float64(0.0):
                        v += prof[t, 2 * s * KER_TAPS + a, x] * wx[x] * (pixel(refs, grads, f, oy + y, ox + x) - level)
                for b in range(KER_TAPS):
                    rhs[t, b * KER_TAPS + a] += prof[t, (2 * s + 1) * KER_TAPS + b, y] * wy[y] * v


@wp.func
def add_ridge(normal: wp.array3d(dtype=wp.float64), rhs: wp.array2d(dtype=wp.float64), t: int,
              prior: wp.array2d(dtype=wp.float64), p: int):  # fmt: skip
    """``N + l I`` and ``r + l prior`` in place, ``l = KER_RIDGE`` times N's mean diagonal."""
    n = KER_UNKNOWNS
    trace = wp.float64(0.0)
    for u in range(n):
        trace += normal[t, u, u]
    lam = KER_RIDGE * trace / wp.float64(n)
    for u in range(n):
        normal[t, u, u] = normal[t, u, u] + lam
        rhs[t, u] = rhs[t, u] + lam * prior[p, u]


@wp.func
def dot4(a: wp.array3d(dtype=wp.float64), ta: int, ra: int, b: wp.array3d(dtype=wp.float64), tb: int, rb: int,
         start: int, stop: int) -> wp.float64:  # fmt: skip
    """``sum_(start <= k < stop) a[ta, ra, k] b[tb, rb, k]`` in four partial sums (no sum waits on the one
    before it; the CPU's one-thread solve was bound by that wait)."""
    v0 = wp.float64(0.0)
    v1 = wp.float64(0.0)
    v2 = wp.float64(0.0)
    v3 = wp.float64(0.0)
    k = start
    while k + 3 < stop:
        v0 += a[ta, ra, k] * b[tb, rb, k]
        v1 += a[ta, ra, k + 1] * b[tb, rb, k + 1]
        v2 += a[ta, ra, k + 2] * b[tb, rb, k + 2]
        v3 += a[ta, ra, k + 3] * b[tb, rb, k + 3]
        k += 4
    while k < stop:
        v0 += a[ta, ra, k] * b[tb, rb, k]
        k += 1
    return (v0 + v1) + (v2 + v3)


@wp.func
def dot4_vector(a: wp.array3d(dtype=wp.float64), ta: int, ra: int, b: wp.array2d(dtype=wp.float64), tb: int,
                start: int, stop: int) -> wp.float64:  # fmt: skip
    """:func:`dot4` of a row of ``a`` and one of the 2-D ``b``: ``sum_k a[ta, ra, k] b[tb, k]``."""
    v0 = wp.float64(0.0)
    v1 = wp.float64(0.0)
    v2 = wp.float64(0.0)
    v3 = wp.float64(0.0)
    k = start
    while k + 3 < stop:
        v0 += a[ta, ra, k] * b[tb, k]
        v1 += a[ta, ra, k + 1] * b[tb, k + 1]
        v2 += a[ta, ra, k + 2] * b[tb, k + 2]
        v3 += a[ta, ra, k + 3] * b[tb, k + 3]
        k += 4
    while k < stop:
        v0 += a[ta, ra, k] * b[tb, k]
        k += 1
    return (v0 + v1) + (v2 + v3)


@wp.func
def cholesky_entry(normal: wp.array3d(dtype=wp.float64), t: int, j: int, r: int) -> wp.float64:
    """Column j's entry in row r >= j of the Cholesky factor before the division by its pivot (for r = j the
    pivot's square): ``N[r, j] - sum_(k < j) L[r, k] L[j, k]``, with the columns before j done in place
    (below the diagonal; the pivots are kept apart, in ``diag``)."""
    return normal[t, r, j] - dot4(normal, t, r, normal, t, j, 0, j)


@wp.func
def substitute(normal: wp.array3d(dtype=wp.float64), diag: wp.array2d(dtype=wp.float64),
               rhs: wp.array2d(dtype=wp.float64), t: int, out: wp.array2d(dtype=wp.float64), p: int):  # fmt: skip
    """``L L^T a = rhs`` by forward and back substitution (L: ``normal[t]`` below the diagonal, its pivots
    ``diag[t]``); ``a`` into ``out[p]``, ``rhs[t]`` overwritten."""
    n = KER_UNKNOWNS
    for j in range(n):
        rhs[t, j] = (rhs[t, j] - dot4_vector(normal, t, j, rhs, t, 0, j)) / diag[t, j]
    for jj in range(n):
        j = n - 1 - jj
        v0 = wp.float64(0.0)
        v1 = wp.float64(0.0)
        k = j + 1
        while k + 1 < n:
            v0 += normal[t, k, j] * out[p, k]
            v1 += normal[t, k + 1, j] * out[p, k + 1]
            k += 2
        if k < n:
            v0 += normal[t, k, j] * out[p, k]
        out[p, j] = (rhs[t, j] - (v0 + v1)) / diag[t, j]


@wp.func
def ridge_solve(
    normal: wp.array3d(dtype=wp.float64), rhs: wp.array2d(dtype=wp.float64), diag: wp.array2d(dtype=wp.float64),
    t: int, prior: wp.array2d(dtype=wp.float64), p: int, out: wp.array2d(dtype=wp.float64),
) -> bool:  # fmt: skip
    """``(N + l I) a = r + l prior`` (:func:`add_ridge`) by a Cholesky factorisation of the lower triangle in
    place, one thread (the CPU's engine; a GPU's takes a column a launch, ``fit_column``); ``a`` into
    ``out[p]``. False where N is not positive definite (nothing written)."""
    add_ridge(normal, rhs, t, prior, p)
    for j in range(KER_UNKNOWNS):
        s = cholesky_entry(normal, t, j, j)
        if not (s > wp.float64(0.0)):
            return False
        d = wp.sqrt(s)
        diag[t, j] = d
        for r in range(j + 1, KER_UNKNOWNS):
            normal[t, r, j] = cholesky_entry(normal, t, j, r) / d
    substitute(normal, diag, rhs, t, out, p)
    return True


@wp.func
def fit_setup(
    offset: int, t: int, grid: wp.uint64, z_step: float, refs: wp.array3d(dtype=wp.float64),
    grads: wp.array3d(dtype=wp.float64), rows: wp.array(dtype=wp.int32), frame: wp.array(dtype=wp.int32),
    level: wp.array(dtype=wp.float64), pos: wp.array(dtype=wp.vec2d), flux: wp.array(dtype=wp.float64),
    sigma: wp.array(dtype=wp.float64), last: wp.array2d(dtype=wp.float64), nbr: wp.array2d(dtype=wp.int32),
    prof: wp.array3d(dtype=wp.float64), rhs: wp.array2d(dtype=wp.float64), shift: wp.array(dtype=wp.vec3d),
    weights: wp.array3d(dtype=wp.float64),
) -> int:  # fmt: skip
    """Row ``p = offset + t``'s fit up to its normal matrix: its neighbours (``nbr[t]``), their window
    profiles (``prof[t]``), its window weights (``weights[t]``: x then y) and the right side (``rhs[t]``).
    Returns the neighbours' count, 0 where the row is not fitted (not distorted itself, or too many
    neighbours)."""
    p = offset + t
    if shift[rows[p]][2] != DISTORTED_CODE:
        return 0
    count = gather_neighbours(grid, pos, rows, frame, z_step, p, t, nbr)
    if count > KER_MAX_NEIGHBOURS:
        return 0
    mu = kernel_mean(last, p)
    ox = int(wp.rint(pos[p][0])) - KER_WINDOW_HALF
    oy = int(wp.rint(pos[p][1])) - KER_WINDOW_HALF
    wx = vec_window()
    wy = vec_window()
    for k in range(KER_WINDOW):
        wx[k] = window_weight(ox + k, pos[p][0], refs.shape[2])
        wy[k] = window_weight(oy + k, pos[p][1], refs.shape[1])
        weights[t, 0, k] = wx[k]
        weights[t, 1, k] = wy[k]
    neighbour_profiles(pos, flux, sigma, mu, ox, oy, t, count, nbr, prof)
    right_side(refs, grads, frame[rows[p]], level[frame[rows[p]]], ox, oy, prof, t, count, wx, wy, rhs)
    return count


@wp.func
def window_of(weights: wp.array3d(dtype=wp.float64), t: int, axis: int) -> vec_window:
    """Row t's window weights along ``axis`` (0: x, 1: y), as ``fit_setup`` stored them."""
    w = vec_window()
    for k in range(KER_WINDOW):
        w[k] = weights[t, axis, k]
    return w


@wp.func
def keep_last(last: wp.array2d(dtype=wp.float64), fitted: wp.array2d(dtype=wp.float64), p: int):
    """Row p keeps its last kernel (not fitted, or its fit failed)."""
    for k in range(KER_UNKNOWNS):
        fitted[p, k] = last[p, k]


@wp.kernel
def fit_rows_one_thread(
    offset: int, count: wp.array(dtype=wp.int32), prof: wp.array3d(dtype=wp.float64),
    weights: wp.array3d(dtype=wp.float64), normal: wp.array3d(dtype=wp.float64), rhs: wp.array2d(dtype=wp.float64),
    diag: wp.array2d(dtype=wp.float64), prior: wp.array2d(dtype=wp.float64), last: wp.array2d(dtype=wp.float64),
    fitted: wp.array2d(dtype=wp.float64), first: wp.array(dtype=wp.int32), rows_x: wp.array2d(dtype=vec_taps),
    cols_x: wp.array2d(dtype=vec_taps), y: wp.array2d(dtype=wp.float64),
):  # fmt: skip
    """The CPU's engine, after ``fit_rows_setup``: row ``p = offset + t``'s kernel, one thread: its normal
    matrix (``normal_equations``, its neighbour pairs' factors in the scratch from ``first[t]`` on) and the
    ridge solve; the last kernel kept where the row is not fitted or the fit fails."""
    t = wp.tid()
    p = offset + t
    ok = False
    if count[t] > 0:
        wx = window_of(weights, t, 0)
        normal_equations(prof, t, count[t], wx, window_of(weights, t, 1), first[t], rows_x, cols_x, y, normal)
        ok = ridge_solve(normal, rhs, diag, t, prior, p, fitted)
    if not ok:
        keep_last(last, fitted, p)


@wp.kernel
def fit_rows_setup(
    offset: int, grid: wp.uint64, z_step: float, refs: wp.array3d(dtype=wp.float64),
    grads: wp.array3d(dtype=wp.float64), rows: wp.array(dtype=wp.int32), frame: wp.array(dtype=wp.int32),
    level: wp.array(dtype=wp.float64), pos: wp.array(dtype=wp.vec2d), flux: wp.array(dtype=wp.float64),
    sigma: wp.array(dtype=wp.float64), last: wp.array2d(dtype=wp.float64), nbr: wp.array2d(dtype=wp.int32),
    prof: wp.array3d(dtype=wp.float64), rhs: wp.array2d(dtype=wp.float64), shift: wp.array(dtype=wp.vec3d),
    weights: wp.array3d(dtype=wp.float64), count: wp.array(dtype=wp.int32),
):  # fmt: skip
    """Both engines' first launch: ``fit_setup`` of row ``offset + t``, its neighbours' count into
    ``count[t]`` (0: not fitted)."""
    t = wp.tid()
    count[t] = fit_setup(offset, t, grid, z_step, refs, grads, rows, frame, level, pos, flux, sigma, last, nbr, prof,
                         rhs, shift, weights)  # fmt: skip


@wp.kernel(module=GPU_MODULE)
def fit_rows_normal(
    prof: wp.array3d(dtype=wp.float64), weights: wp.array3d(dtype=wp.float64), count: wp.array(dtype=wp.int32),
    normal: wp.array3d(dtype=wp.float64),
):  # fmt: skip
    """A GPU's engine: row u of the lower triangle of row t's normal matrix, one thread each (t, u):
    ``N[u, v] = sum_(s, r) Y_sr[b, b'] X_sr[a, a']`` for ``u = b T + a``, ``v = b' T + a' <= u``, over every
    ordered pair of neighbours (the CPU's ``normal_equations`` sums the same terms in another order)."""
    t, u = wp.tid()
    n = count[t]
    if n == 0:
        return
    b = u // KER_TAPS
    a = u - b * KER_TAPS
    for v in range(u + 1):
        normal[t, u, v] = wp.float64(0.0)
    for s in range(n):
        for r in range(n):
            ys = vec_taps()
            xs = vec_taps()
            for c in range(KER_TAPS):
                vy = wp.float64(0.0)
                vx = wp.float64(0.0)
                for k in range(KER_WINDOW):
                    ry = (2 * r + 1) * KER_TAPS + c
                    vy += prof[t, (2 * s + 1) * KER_TAPS + b, k] * weights[t, 1, k] * prof[t, ry, k]
                    vx += prof[t, 2 * s * KER_TAPS + a, k] * weights[t, 0, k] * prof[t, 2 * r * KER_TAPS + c, k]
                ys[c] = vy
                xs[c] = vx
            for v in range(u + 1):
                b2 = v // KER_TAPS
                normal[t, u, v] += ys[b2] * xs[v - b2 * KER_TAPS]


@wp.kernel(module=GPU_MODULE)
def fit_rows_ridge(
    offset: int, count: wp.array(dtype=wp.int32), normal: wp.array3d(dtype=wp.float64),
    rhs: wp.array2d(dtype=wp.float64), prior: wp.array2d(dtype=wp.float64), failed: wp.array(dtype=wp.int32),
):  # fmt: skip
    """A GPU's engine: :func:`add_ridge` of row t (not failed yet)."""
    t = wp.tid()
    failed[t] = 0
    if count[t] > 0:
        add_ridge(normal, rhs, t, prior, offset + t)


@wp.kernel(module=GPU_MODULE)
def fit_column(
    j: int, count: wp.array(dtype=wp.int32), normal: wp.array3d(dtype=wp.float64), diag: wp.array2d(dtype=wp.float64),
    failed: wp.array(dtype=wp.int32),
):  # fmt: skip
    """A GPU's engine: column j of row t's Cholesky factor, entry r a thread (t, r): as ``ridge_solve`` does it
    (:func:`cholesky_entry`), the columns before j done by the launches before; row t fails where the
    pivot is not positive."""
    t, r = wp.tid()
    if count[t] == 0 or failed[t] != 0 or r < j:
        return
    s = cholesky_entry(normal, t, j, j)
    if not (s > wp.float64(0.0)):
        failed[t] = 1
        return
    d = wp.sqrt(s)
    if r == j:
        diag[t, j] = d
    else:
        normal[t, r, j] = cholesky_entry(normal, t, j, r) / d


@wp.kernel(module=GPU_MODULE)
def fit_rows_solve(
    offset: int, count: wp.array(dtype=wp.int32), normal: wp.array3d(dtype=wp.float64),
    diag: wp.array2d(dtype=wp.float64), rhs: wp.array2d(dtype=wp.float64), failed: wp.array(dtype=wp.int32),
    last: wp.array2d(dtype=wp.float64), fitted: wp.array2d(dtype=wp.float64),
):  # fmt: skip
    """A GPU's engine, last launch: row t's kernel by :func:`substitute`; its last one where not fitted."""
    t = wp.tid()
    p = offset + t
    if count[t] > 0 and failed[t] == 0:
        substitute(normal, diag, rhs, t, fitted, p)
    else:
        keep_last(last, fitted, p)


@wp.kernel
def kernel_render(
    pos: wp.array(dtype=wp.vec2d), flux: wp.array(dtype=wp.float64), sigma: wp.array(dtype=wp.float64),
    kern: wp.array2d(dtype=wp.float64), half: int, prof: wp.array3d(dtype=wp.float64),
    stamp: wp.array3d(dtype=wp.float64),
):  # fmt: skip
    """Row p's model with its own kernel on its ``2 half + 1`` stamp about its position, into ``stamp[p]``
    (``kernel_accumulate`` draws the stamps into the model image)."""
    p = wp.tid()
    n = 2 * half + 1
    ox = int(wp.rint(pos[p][0])) - half
    oy = int(wp.rint(pos[p][1])) - half
    mu = kernel_mean(kern, p)
    for a in range(KER_TAPS):
        store_profile(prof, p, a, pos[p][0] - mu[0] + tap(a), sigma[p], ox, n, flux[p])
        store_profile(prof, p, KER_TAPS + a, pos[p][1] - mu[1] + tap(a), sigma[p], oy, n, wp.float64(1.0))
    for r in range(n):
        for c in range(n):
            v = wp.float64(0.0)
            for b in range(KER_TAPS):
                row = wp.float64(0.0)
                for a in range(KER_TAPS):
                    row += kern[p, b * KER_TAPS + a] * prof[p, a, c]
                v += prof[p, KER_TAPS + b, r] * row
            stamp[p, r, c] = v


@wp.func
def held_sums(
    refs: wp.array3d(dtype=wp.float64), grads: wp.array3d(dtype=wp.float64), models: wp.array(dtype=wp.int64),
    scales: wp.array(dtype=wp.float64), params: wp.array2d(dtype=wp.float64), rows: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32), half: int, stamp: wp.array3d(dtype=wp.float64),
    background: wp.array(dtype=wp.float64), pos: wp.array(dtype=wp.vec2d), alpha: wp.array(dtype=wp.float64),
    p: int, moments: bool,
):  # fmt: skip
    """Row p's sums over its stamp: its held share of the light ``L = w (I - b)``, ``w = alpha m_p / M``
    (``M`` at least ``SHARE_FLOOR`` of its fitted peak, ``w`` within [0, 1]; outside the image its own
    model): with ``moments`` ``(sum L, sum (x - x_p) L, sum (y - y_p) L, 0, 0, 0)`` (``kernel_moment``),
    else ``(0, 0, 0, sum L inside the image, sum m_p outside it, sum m_p)`` (``kernel_hold``)."""
    i = rows[p]
    f = frame[i]
    height = refs.shape[1]
    width = refs.shape[2]
    n = 2 * half + 1
    ox = int(wp.rint(pos[p][0])) - half
    oy = int(wp.rint(pos[p][1])) - half
    inv = wp.float64(1.0) / scales[f]
    floor = SHARE_FLOOR * wp.abs(params[i, 2])
    out = vec6d()
    a = alpha[p]
    b = background[p]
    for r in range(n):
        for c in range(n):
            light = stamp[p, r, c]
            if not moments:
                out[5] += light
            if oy + r >= 0 and oy + r < height and ox + c >= 0 and ox + c < width:
                at = (f * height + oy + r) * width + ox + c
                share = wp.clamp(a * light / wp.max(wp.float64(models[at]) * inv, floor), wp.float64(0.0),
                                 wp.float64(1.0))  # fmt: skip
                light = share * (pixel(refs, grads, f, oy + r, ox + c) - b)
                if not moments:
                    out[3] += light
            elif not moments:
                out[4] += light
            if moments:
                out[0] += light
                out[1] += (wp.float64(ox + c) - pos[p][0]) * light
                out[2] += (wp.float64(oy + r) - pos[p][1]) * light
    return out


@wp.func
def redraw_stamp(
    rows: wp.array(dtype=wp.int32), frame: wp.array(dtype=wp.int32), pos: wp.array(dtype=wp.vec2d), half: int,
    stamp: wp.array3d(dtype=wp.float64), p: int, out_of: wp.float64, into: wp.float64,
    scales: wp.array(dtype=wp.float64), height: int, width: int, models: wp.array(dtype=wp.int64),
):  # fmt: skip
    """Row p's model on its stamp, drawn times ``out_of``, redrawn times ``into``: each pixel of its frame's
    fixed-point model image gets the difference of the two fixed-point values (0 draws nothing: in with 0
    and ``alpha`` draws the stamp, out with ``alpha`` and 0 takes it out to the bit)."""
    f = frame[rows[p]]
    n = 2 * half + 1
    ox = int(wp.rint(pos[p][0])) - half
    oy = int(wp.rint(pos[p][1])) - half
    for r in range(n):
        for c in range(n):
            if oy + r >= 0 and oy + r < height and ox + c >= 0 and ox + c < width:
                s = stamp[p, r, c]
                d = to_fixed(into * s, scales[f]) - to_fixed(out_of * s, scales[f])
                if d != wp.int64(0):
                    wp.atomic_add(models, (f * height + oy + r) * width + ox + c, d)


@wp.kernel
def kernel_accumulate(
    rows: wp.array(dtype=wp.int32), frame: wp.array(dtype=wp.int32), pos: wp.array(dtype=wp.vec2d), half: int,
    stamp: wp.array3d(dtype=wp.float64), alpha: wp.array(dtype=wp.float64), scales: wp.array(dtype=wp.float64),
    height: int, width: int, models: wp.array(dtype=wp.int64), sign: int,
):  # fmt: skip
    """Row p's model on its stamp times its multiplier ``alpha`` into its frame's model image (fixed point),
    or with ``sign`` -1 out of it again, to the bit (the integer sums do not depend on the order)."""
    p = wp.tid()
    zero = wp.float64(0.0)
    if sign > 0:
        redraw_stamp(rows, frame, pos, half, stamp, p, zero, alpha[p], scales, height, width, models)
    else:
        redraw_stamp(rows, frame, pos, half, stamp, p, alpha[p], zero, scales, height, width, models)


@wp.kernel
def kernel_reweigh(
    rows: wp.array(dtype=wp.int32), frame: wp.array(dtype=wp.int32), pos: wp.array(dtype=wp.vec2d), half: int,
    stamp: wp.array3d(dtype=wp.float64), alpha: wp.array(dtype=wp.float64), alpha_new: wp.array(dtype=wp.float64),
    scales: wp.array(dtype=wp.float64), height: int, width: int, models: wp.array(dtype=wp.int64),
):  # fmt: skip
    """Row p's model on its stamp, drawn times ``alpha``, redrawn times ``alpha_new`` in one pass: the image
    is to the bit what ``kernel_accumulate`` out with ``alpha`` and in with ``alpha_new`` leave (integers:
    the sums do not depend on the order)."""
    p = wp.tid()
    if alpha_new[p] != alpha[p]:
        redraw_stamp(rows, frame, pos, half, stamp, p, alpha[p], alpha_new[p], scales, height, width, models)


@wp.kernel
def kernel_hold(
    refs: wp.array3d(dtype=wp.float64), grads: wp.array3d(dtype=wp.float64), models: wp.array(dtype=wp.int64),
    scales: wp.array(dtype=wp.float64), params: wp.array2d(dtype=wp.float64), rows: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32), half: int, stamp: wp.array3d(dtype=wp.float64),
    background: wp.array(dtype=wp.float64), pos: wp.array(dtype=wp.vec2d), kern: wp.array2d(dtype=wp.float64),
    alpha: wp.array(dtype=wp.float64), alpha_out: wp.array(dtype=wp.float64),
):  # fmt: skip
    """One sweep of iterative proportional fitting, into ``alpha_out``: row p's multiplier ``alpha`` times
    the ratio of the reference flux its model puts on its stamp inside the image (its model's share of the
    stamp times the flux, less the model's light outside the image) to the light its share holds there (the
    ratio within ``1 / KER_FLUX_STEP`` and ``KER_FLUX_STEP``, ``alpha`` within ``1 / KER_FLUX_BOUND`` and
    ``KER_FLUX_BOUND``); unchanged where either is not positive."""
    p = wp.tid()
    sums = held_sums(refs, grads, models, scales, params, rows, frame, half, stamp, background, pos, alpha, p,
                     False)
    ksum = wp.float64(0.0)
    for k in range(KER_UNKNOWNS):
        ksum += kern[p, k]
    target = sums[5] / ksum - sums[4]
    alpha_out[p] = alpha[p]
    if target > wp.float64(0.0) and sums[3] > wp.float64(0.0):
        ratio = wp.clamp(target / sums[3], wp.float64(1.0) / KER_FLUX_STEP, KER_FLUX_STEP)
        alpha_out[p] = wp.clamp(alpha[p] * ratio, wp.float64(1.0) / KER_FLUX_BOUND, KER_FLUX_BOUND)


@wp.kernel
def kernel_moment(
    refs: wp.array3d(dtype=wp.float64), grads: wp.array3d(dtype=wp.float64), models: wp.array(dtype=wp.int64),
    scales: wp.array(dtype=wp.float64), params: wp.array2d(dtype=wp.float64), rows: wp.array(dtype=wp.int32),
    frame: wp.array(dtype=wp.int32), half: int, stamp: wp.array3d(dtype=wp.float64),
    background: wp.array(dtype=wp.float64), pos: wp.array(dtype=wp.vec2d), alpha: wp.array(dtype=wp.float64),
    failed: wp.array(dtype=wp.int32), pos_out: wp.array(dtype=wp.vec2d),
):  # fmt: skip
    """Row p's next position, into ``pos_out``: the first moment of its held share of the light
    (:func:`held_sums`); its position, marked failed, where it holds none."""
    p = wp.tid()
    sums = held_sums(refs, grads, models, scales, params, rows, frame, half, stamp, background, pos, alpha, p,
                     True)
    pos_out[p] = pos[p]
    if sums[0] > wp.float64(0.0):
        pos_out[p] = wp.vec2d(pos[p][0] + sums[1] / sums[0], pos[p][1] + sums[2] / sums[0])
    else:
        failed[p] = 1


@wp.kernel
def kernel_finish(
    params: wp.array2d(dtype=wp.float64), partner: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int32),
    pos: wp.array(dtype=wp.vec2d), failed: wp.array(dtype=wp.int32), max_shift: wp.float64,
    shift: wp.array(dtype=wp.vec3d),
):  # fmt: skip
    """A row that ``moves`` takes the shift from its fitted centre to its last position, its code kept,
    where that is finite and at most ``max_shift`` and its moments held light."""
    p = wp.tid()
    i = rows[p]
    if failed[p] != 0 or not moves(shift, partner, i):
        return
    dx = pos[p][0] - params[i, 0]
    dy = pos[p][1] - params[i, 1]
    if dx * dx + dy * dy <= max_shift * max_shift:  # also false for NaN
        shift[i] = wp.vec3d(dx, dy, shift[i][2])
