# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of the correlation predictor for a stack of pairs: the steps of each pass.

Host code: :func:`tracking.predict.predict_displacement_stack`. Which pairs run, tile grids and fields,
the deformation, peak fits, the median test and the end of a pass; the tile correlation is in
:mod:`tracking.predict_fft_kernels`; the hand-over of the prediction to identification (the
positions to search from, the dots inside each pair's image) is in :mod:`tracking.identify_kernels`, which
the CPU builds anyway (it runs this engine's host twin, not these kernels).

Kernels and ``@wp.func`` steps only. Each kernel does one step of a pass of
:func:`tracking.predict.predict_displacement` for every pair of a stack at once (threads indexed by pair
first), so that the number of launches does not depend on the number of pairs. Which pairs take part is
read from ``changed[pair, pass]`` (1 where the pass changed some tile of the pair's field by more than
0.25 px): a pair runs pass ``p`` while every earlier pass changed its field (:func:`runs`) and stops at the
first pass that did not, or at the last (:func:`stops`); the significance and the values at the dots are
computed at the pass where it stops.

Tile fields are float64 ``(pairs, tile rows, tile columns)`` arrays; a pass's tiles are described by
:class:`TileGrid`. Correlation planes are float32, each ``size x size`` plane stored in the rows
``k size ... k size + size - 1`` of a 2-D array (tile ``k = (pair * ny + i) * nx + j``), shifted: zero
displacement at ``(size // 2, size // 2)`` (as the host's planes).
"""

import warp as wp
from synthbos.correlation.median_test import median_scale_wp, median_sorted_wp, residual_limit_wp, vec8d
from synthbos.correlation.pass_kernels import three_point_offset

from synthbos.device import quiet_warp

from .settings import PREDICTOR_MIN_VALID_FRACTION, PREDICTOR_RESOLVED_PX

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile

#: The pass's field must change no tile by more than this (px) for a pair to stop.
RESOLVED = wp.constant(wp.float64(PREDICTOR_RESOLVED_PX))
#: A tile takes part where at least this fraction of its pixels does.
MIN_VALID_FRACTION = wp.constant(wp.float64(PREDICTOR_MIN_VALID_FRACTION))


@wp.struct
class TileGrid:
    """Tiles of a pass: tile (i, j) covers the ``size`` rows from ``top + i * row_step`` and the ``size``
    columns from ``left + j * col_step``, ``ny`` x ``nx`` tiles, centres ``(size - 1) / 2`` px further."""

    top: int
    left: int
    row_step: int
    col_step: int
    size: int
    ny: int
    nx: int


# --- which pairs take part -----------------------------------------------------------------------------


@wp.func
def runs(changed: wp.array2d(dtype=wp.int32), b: int, p: int) -> bool:
    """Whether pair ``b`` runs pass ``p``: every earlier pass changed its field."""
    for q in range(p):
        if changed[b, q] == 0:
            return False
    return True


@wp.func
def stops(changed: wp.array2d(dtype=wp.int32), b: int, p: int, last: int) -> bool:
    """Whether pair ``b`` ends at pass ``p`` (whose ``changed`` is known): it ran it and the pass changed
    no tile by more than ``RESOLVED``, or it is the last pass (``last`` not 0)."""
    return runs(changed, b, p) and (changed[b, p] == 0 or last != 0)


@wp.func
def takes_part(changed: wp.array2d(dtype=wp.int32), b: int, p: int, last: int, at_stop: int) -> bool:
    """:func:`runs` (``at_stop`` 0) or :func:`stops` (``at_stop`` 1)."""
    if at_stop == 0:
        return runs(changed, b, p)
    return stops(changed, b, p, last)


@wp.func
def row_runs(changed: wp.array2d(dtype=wp.int32), grid: TileGrid, g: int, p: int) -> bool:
    """:func:`runs` for the pair of row ``g`` of a pass's stacked tiles (tile ``g // size``)."""
    return runs(changed, (g // grid.size) // (grid.ny * grid.nx), p)


# --- tile grids and the bilinear interpolation of tile fields ------------------------------------------


@wp.func
def centre_row(g: TileGrid, i: int) -> wp.float64:
    """Row of the centre of tile row ``i``."""
    return wp.float64(g.top + i * g.row_step) + wp.float64(g.size - 1) / wp.float64(2.0)


@wp.func
def centre_col(g: TileGrid, j: int) -> wp.float64:
    """Column of the centre of tile column ``j``."""
    return wp.float64(g.left + j * g.col_step) + wp.float64(g.size - 1) / wp.float64(2.0)


@wp.func
def cell(t: wp.float64, first: wp.float64, step: int, count: int) -> wp.vec2d:
    """(cell index, fraction) of coordinate ``t`` on ``count`` centres from ``first``, ``step`` apart:
    ``predict._cell`` (fraction beyond [0, 1] at the ends: linear extrapolation; (0, 0) for one centre)."""
    if count == 1:
        return wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    f = (t - first) / wp.float64(step)
    i = wp.clamp(int(wp.floor(f)), 0, count - 2)
    return wp.vec2d(wp.float64(i), f - wp.float64(i))


@wp.func
def row_cell(g: TileGrid, y: wp.float64) -> wp.vec2d:
    """:func:`cell` of row ``y`` among the grid's centre rows."""
    return cell(y, centre_row(g, 0), g.row_step, g.ny)


@wp.func
def col_cell(g: TileGrid, x: wp.float64) -> wp.vec2d:
    """:func:`cell` of column ``x`` among the grid's centre columns."""
    return cell(x, centre_col(g, 0), g.col_step, g.nx)


@wp.func
def bilinear(f: wp.array3d(dtype=wp.float64), b: int, cy: wp.vec2d, cx: wp.vec2d) -> wp.float64:
    """Pair ``b``'s field bilinearly interpolated in the cells ``cy`` (row) and ``cx`` (column), the
    products and sums in the order of ``predict._bilinear``."""
    iy = int(cy[0])
    ix = int(cx[0])
    ty = cy[1]
    tx = cx[1]
    iy1 = wp.min(iy + 1, f.shape[1] - 1)
    ix1 = wp.min(ix + 1, f.shape[2] - 1)
    one = wp.float64(1.0)
    return (one - ty) * ((one - tx) * f[b, iy, ix] + tx * f[b, iy, ix1]) + ty * (
        (one - tx) * f[b, iy1, ix] + tx * f[b, iy1, ix1]
    )


@wp.func
def separable(f: wp.array3d(dtype=wp.float64), b: int, cy: wp.vec2d, cx: wp.vec2d) -> wp.float64:
    """The same interpolation in the order of ``deform_nearest_kernel`` (``field_at_row`` at the cell's two
    centre columns, then along the row), which the host's deformation rounds."""
    iy = int(cy[0])
    ix = int(cx[0])
    ty = cy[1]
    tx = cx[1]
    iy1 = wp.min(iy + 1, f.shape[1] - 1)
    ix1 = wp.min(ix + 1, f.shape[2] - 1)
    one = wp.float64(1.0)
    e0 = (one - ty) * f[b, iy, ix] + ty * f[b, iy1, ix]
    e1 = (one - ty) * f[b, iy, ix1] + ty * f[b, iy1, ix1]
    return (one - tx) * e0 + tx * e1


# --- the gradient image moved back by the coarser field --------------------------------------------------


@wp.kernel
def deform_tiles(
    gradients: wp.array3d(dtype=wp.float64),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    grid: TileGrid,
    has_field: int,
    coarse: TileGrid,
    field_u: wp.array3d(dtype=wp.float64),
    field_v: wp.array3d(dtype=wp.float64),
    run: int,
    moved: wp.array3d(dtype=wp.float32),
    weight: wp.array3d(dtype=wp.float32),
    shift: wp.array3d(dtype=wp.vec2f),
):
    """``run`` consecutive pixels of a row of the pass's tiles, laid side by side (tile (i, j) at rows
    ``i * size`` and columns ``j * size`` of ``moved``; one pixel per thread on a GPU, a tile's row on
    the CPU): the gradient image moved back by the ``coarse`` pass's field (where ``has_field``)
    interpolated bilinearly and rounded at the pixel (``deform_nearest_kernel``): the pixel
    (y + rint(v), x + rint(u)) as float32 (the edge pixel beyond the image), ``weight`` 1 where that lies
    inside the image, else 0, and ``shift`` the rounded (u, v)."""
    b, rr, t = wp.tid()
    if not runs(changed, b, p):
        return
    n = grid.size
    h = gradients.shape[1]
    w = gradients.shape[2]
    y = grid.top + (rr // n) * grid.row_step + rr % n
    cy = wp.vec2d()
    if has_field != 0:
        cy = row_cell(coarse, wp.float64(y))
    for cc in range(t * run, wp.min(t * run + run, moved.shape[2])):
        x = grid.left + (cc // n) * grid.col_step + cc % n
        su = int(0)
        sv = int(0)
        if has_field != 0:
            cx = col_cell(coarse, wp.float64(x))
            su = int(wp.rint(separable(field_u, b, cy, cx)))
            sv = int(wp.rint(separable(field_v, b, cy, cx)))
        ry = y + sv
        rx = x + su
        inside = wp.float32(0.0)
        if ry >= 0 and ry < h and rx >= 0 and rx < w:
            inside = wp.float32(1.0)
        moved[b, rr, cc] = wp.float32(gradients[b, wp.clamp(ry, 0, h - 1), wp.clamp(rx, 0, w - 1)])
        weight[b, rr, cc] = inside
        shift[b, rr, cc] = wp.vec2f(wp.float32(su), wp.float32(sv))


# --- peak fits and the tile field ----------------------------------------------------------------------------


@wp.kernel
def fit_tiles(
    planes: wp.array2d(dtype=wp.float32),
    peak: wp.array3d(dtype=wp.int32),
    norm: wp.array3d(dtype=wp.float64),
    count: wp.array3d(dtype=wp.float32),
    base: wp.array3d(dtype=wp.vec2d),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    grid: TileGrid,
    residual_u: wp.array3d(dtype=wp.float64),
    residual_v: wp.array3d(dtype=wp.float64),
    field_u: wp.array3d(dtype=wp.float64),
    field_v: wp.array3d(dtype=wp.float64),
    scaled: wp.array3d(dtype=wp.float32),
    usable: wp.array3d(dtype=wp.int32),
):
    """Tile (pair, i, j): the peak (kept a sample inside the plane's edge) refined by three-point
    Gaussian fits along the column and along the row of the plane divided by ``scaled`` (its norm as
    float32; 1 where 0): the residual (u, v) from zero displacement and the field ``base + residual``,
    NaN where the tile is not usable (too few pixels of weight 1, or a flat tile)."""
    b, i, j = wp.tid()
    if not runs(changed, b, p):
        return
    n = grid.size
    half = n // 2
    row0 = ((b * grid.ny + i) * grid.nx + j) * n
    at = peak[b, i, j]
    r = wp.clamp(at // n, 1, n - 2)
    c = wp.clamp(at % n, 1, n - 2)
    nm = norm[b, i, j]
    s = wp.float32(1.0)
    if nm > wp.float64(0.0):
        s = wp.float32(nm)
    centre = wp.float64(planes[row0 + r, c] / s)
    up = wp.float64(planes[row0 + r - 1, c] / s)
    down = wp.float64(planes[row0 + r + 1, c] / s)
    left = wp.float64(planes[row0 + r, c - 1] / s)
    right = wp.float64(planes[row0 + r, c + 1] / s)
    rv = wp.float64(r) + three_point_offset(up, centre, down, 0) - wp.float64(half)
    ru = wp.float64(c) + three_point_offset(left, centre, right, 0) - wp.float64(half)
    ok = wp.float64(count[b, i, j]) >= MIN_VALID_FRACTION * wp.float64(n * n) and nm > wp.float64(0.0)
    if not ok:
        ru = wp.float64(wp.nan)
        rv = wp.float64(wp.nan)
    residual_u[b, i, j] = ru
    residual_v[b, i, j] = rv
    field_u[b, i, j] = base[b, i, j][0] + ru
    field_v[b, i, j] = base[b, i, j][1] + rv
    scaled[b, i, j] = s
    usable[b, i, j] = int(ok)


# --- the normalised median test, medians of neighbours and the filling of holes ------------------------------


@wp.func
def sorted_neighbours(f: wp.array3d(dtype=wp.float64), b: int, i: int, j: int) -> tuple[vec8d, int]:
    """The finite values among the (up to) eight neighbours of tile (i, j), ascending, then NaN; and
    their number."""
    v = vec8d()
    cnt = int(0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            y = i + dy
            x = j + dx
            if (dy != 0 or dx != 0) and y >= 0 and y < f.shape[1] and x >= 0 and x < f.shape[2]:
                val = f[b, y, x]
                if wp.isfinite(val):
                    q = cnt
                    while q > 0 and v[q - 1] > val:
                        v[q] = v[q - 1]
                        q -= 1
                    v[q] = val
                    cnt += 1
    for q in range(cnt, 8):
        v[q] = wp.float64(wp.nan)
    return v, cnt


@wp.func
def neighbour_median(f: wp.array3d(dtype=wp.float64), b: int, i: int, j: int) -> wp.float64:
    """Median of the finite neighbours of tile (i, j) (NaN where none): ``predict._neighbour_median``."""
    v, cnt = sorted_neighbours(f, b, i, j)
    return median_sorted_wp(v, cnt)


@wp.func
def median_test(f: wp.array3d(dtype=wp.float64), b: int, i: int, j: int) -> wp.float64:
    """Tile (i, j)'s value, or its neighbours' median where it fails the normalised median test
    (threshold 3, epsilon 0.5 px; a NaN tile fails where the median exists): ``predict._replace_outliers``."""
    v, cnt = sorted_neighbours(f, b, i, j)
    ms = median_scale_wp(v, cnt)
    med = ms[0]
    x = f[b, i, j]
    if not wp.isfinite(med):
        return x
    if wp.abs(x - med) <= residual_limit_wp(ms[1], wp.float64(0.5), wp.float64(3.0)):
        return x
    return med


@wp.kernel
def replace_outliers(
    field_u: wp.array3d(dtype=wp.float64),
    field_v: wp.array3d(dtype=wp.float64),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    out_u: wp.array3d(dtype=wp.float64),
    out_v: wp.array3d(dtype=wp.float64),
):
    """Tile (pair, i, j) of both fields after the normalised median test (:func:`median_test`)."""
    b, i, j = wp.tid()
    if not runs(changed, b, p):
        return
    out_u[b, i, j] = median_test(field_u, b, i, j)
    out_v[b, i, j] = median_test(field_v, b, i, j)


@wp.kernel
def neighbour_medians(
    residual_u: wp.array3d(dtype=wp.float64),
    residual_v: wp.array3d(dtype=wp.float64),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    last: int,
    out_u: wp.array3d(dtype=wp.float64),
    out_v: wp.array3d(dtype=wp.float64),
):
    """Of the pairs that stop at this pass: the median of each tile's neighbours' residuals u and v (NaN
    where none is finite)."""
    b, i, j = wp.tid()
    if not stops(changed, b, p, last):
        return
    out_u[b, i, j] = neighbour_median(residual_u, b, i, j)
    out_v[b, i, j] = neighbour_median(residual_v, b, i, j)


@wp.kernel
def nearest_in_columns(
    src: wp.array3d(dtype=wp.float64),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    last: int,
    at_stop: int,
    feature: wp.array3d(dtype=wp.int32),
):
    """First stage of ``scipy.ndimage.distance_transform_edt``'s feature transform (the nearest finite
    node of ``src``) along tile column (pair, j): the row of the nearest finite node in the column
    (the upper one of two as near; -1 where the column has none)."""
    b, j = wp.tid()
    if not takes_part(changed, b, p, last, at_stop):
        return
    ny = src.shape[1]
    above = int(-1)
    for i in range(ny):
        if wp.isfinite(src[b, i, j]):
            above = i
        feature[b, i, j] = above
    below = int(-1)
    for q in range(ny):
        i = ny - 1 - q
        if wp.isfinite(src[b, i, j]):
            below = i
        a = feature[b, i, j]
        if below >= 0 and (a < 0 or below - i < i - a):
            feature[b, i, j] = below


@wp.kernel
def nearest_in_rows(
    src_u: wp.array3d(dtype=wp.float64),
    src_v: wp.array3d(dtype=wp.float64),
    feature: wp.array3d(dtype=wp.int32),
    stack: wp.array3d(dtype=wp.int32),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    last: int,
    at_stop: int,
    out_u: wp.array3d(dtype=wp.float64),
    out_v: wp.array3d(dtype=wp.float64),
):
    """Second stage along tile row (pair, i): each node takes the values of the nearest finite node
    (``predict._fill_nan``; 0 where no node is finite), chosen among the columns' nearest
    (:func:`nearest_in_columns`) by the partial Voronoi diagram of Maurer et al. (2003) as
    ``scipy.ndimage``'s ``_VoronoiFT`` builds it, ties resolved alike. ``stack`` is scratch."""
    b, i = wp.tid()
    if not takes_part(changed, b, p, last, at_stop):
        return
    nx = src_u.shape[2]
    fi = wp.float64(i)
    l = int(-1)
    for col in range(nx):
        fr = feature[b, i, col]
        if fr >= 0:
            tw = wp.float64(fr) - fi
            w_r = tw * tw
            while l >= 1:
                idx1 = stack[b, i, l]
                idx2 = stack[b, i, l - 1]
                a = wp.float64(idx1 - idx2)
                bb = wp.float64(col - idx1)
                c = a + bb
                tu = wp.float64(feature[b, i, idx2]) - fi
                tv = wp.float64(feature[b, i, idx1]) - fi
                u_r = tu * tu
                v_r = tv * tv
                if c * v_r - bb * u_r - a * w_r - a * bb * c <= wp.float64(0.0):
                    break
                l -= 1
            l += 1
            stack[b, i, l] = col
    maxl = l
    if maxl < 0:  # no finite node anywhere
        for col in range(nx):
            out_u[b, i, col] = wp.float64(0.0)
            out_v[b, i, col] = wp.float64(0.0)
        return
    l = int(0)
    for col in range(nx):
        g = stack[b, i, l]
        t0 = wp.float64(feature[b, i, g]) - fi
        t1 = wp.float64(g - col)
        d1 = t0 * t0 + t1 * t1
        while l < maxl:
            g2 = stack[b, i, l + 1]
            s0 = wp.float64(feature[b, i, g2]) - fi
            s1 = wp.float64(g2 - col)
            d2 = s0 * s0 + s1 * s1
            if d1 <= d2:
                break
            d1 = d2
            l += 1
        g = stack[b, i, l]
        r = feature[b, i, g]
        out_u[b, i, col] = src_u[b, r, g]
        out_v[b, i, col] = src_v[b, r, g]


# --- the end of a pass: the field's change, the significance and the values at the dots -----------------------


@wp.kernel
def field_change(
    field_u: wp.array3d(dtype=wp.float64),
    field_v: wp.array3d(dtype=wp.float64),
    grid: TileGrid,
    has_coarse: int,
    coarse: TileGrid,
    coarse_u: wp.array3d(dtype=wp.float64),
    coarse_v: wp.array3d(dtype=wp.float64),
    p: int,
    changed: wp.array2d(dtype=wp.int32),
):
    """Sets ``changed[pair, p]`` where tile (pair, i, j) differs by more than ``RESOLVED`` in u or v from
    the coarser field (where ``has_coarse``, else 0) interpolated to its centre."""
    b, i, j = wp.tid()
    if not runs(changed, b, p):
        return
    pu = wp.float64(0.0)
    pv = wp.float64(0.0)
    if has_coarse != 0:
        cy = row_cell(coarse, centre_row(grid, i))
        cx = col_cell(coarse, centre_col(grid, j))
        pu = bilinear(coarse_u, b, cy, cx)
        pv = bilinear(coarse_v, b, cy, cx)
    if not (wp.abs(field_u[b, i, j] - pu) <= RESOLVED and wp.abs(field_v[b, i, j] - pv) <= RESOLVED):
        changed[b, p] = 1


@wp.func
def log_float32(x: wp.float32, ok: bool) -> wp.float32:
    """``log(x)`` in float32 where ``ok``, else 0."""
    if ok:
        return wp.log(x)
    return wp.float32(0.0)


@wp.func
def gaussian_sample(
    planes: wp.array2d(dtype=wp.float32), row0: int, n: int, row: wp.float64, col: wp.float64, s: wp.float32
) -> wp.float64:
    """Value of the plane in rows ``row0 ...`` divided by ``s`` at the sub-pixel position (row, col) by a
    separable three-point Gaussian around the nearest sample (the sample itself where one of the five
    is not positive; 0 off the plane): ``predict._gaussian_sample``, the logs of the side samples in
    float32 as there."""
    r = int(wp.rint(row))
    c = int(wp.rint(col))
    on = r >= 1 and r <= n - 2 and c >= 1 and c <= n - 2
    if not on:
        return wp.float64(0.0)
    tr = row - wp.float64(r)
    tc = col - wp.float64(c)
    centre = wp.float64(planes[row0 + r, c] / s)
    up = planes[row0 + r - 1, c] / s
    down = planes[row0 + r + 1, c] / s
    left = planes[row0 + r, c - 1] / s
    right = planes[row0 + r, c + 1] / s
    zero = wp.float32(0.0)
    ok = centre > wp.float64(0.0) and up > zero and down > zero and left > zero and right > zero
    if not ok:
        return centre
    lc = wp.log(centre)
    half = wp.float32(0.5)
    factor = wp.float64(0.0)
    ll = log_float32(up, ok)
    lh = log_float32(down, ok)
    slope = wp.float64(half * (lh - ll))
    curve = wp.min(wp.float64(half * (lh + ll)) - lc, wp.float64(0.0))
    factor += slope * tr + curve * tr * tr
    ll = log_float32(left, ok)
    lh = log_float32(right, ok)
    slope = wp.float64(half * (lh - ll))
    curve = wp.min(wp.float64(half * (lh + ll)) - lc, wp.float64(0.0))
    factor += slope * tc + curve * tc * tc
    return centre * wp.exp(factor)


@wp.kernel
def tile_coefficients(
    planes: wp.array2d(dtype=wp.float32),
    median_u: wp.array3d(dtype=wp.float64),
    median_v: wp.array3d(dtype=wp.float64),
    scaled: wp.array3d(dtype=wp.float32),
    usable: wp.array3d(dtype=wp.int32),
    energy: wp.array3d(dtype=wp.vec2d),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    last: int,
    grid: TileGrid,
    terms: wp.array3d(dtype=wp.vec4d),
):
    """Of the pairs that stop at this pass: tile (pair, i, j)'s normalised correlation at its neighbours'
    median residual (:func:`gaussian_sample`), as the terms that the pooling sums: (covariance, energy
    of the reference tile, energy of the moved tile, 1), all 0 where the tile is not usable."""
    b, i, j = wp.tid()
    if not stops(changed, b, p, last):
        return
    n = grid.size
    half = wp.float64(n // 2)
    zero = wp.float64(0.0)
    if usable[b, i, j] == 0:
        terms[b, i, j] = wp.vec4d(zero, zero, zero, zero)
        return
    row0 = ((b * grid.ny + i) * grid.nx + j) * n
    coef = gaussian_sample(planes, row0, n, median_v[b, i, j] + half, median_u[b, i, j] + half, scaled[b, i, j])
    e = energy[b, i, j]
    terms[b, i, j] = wp.vec4d(coef * wp.sqrt(e[0] * e[1]), e[0], e[1], wp.float64(1.0))


@wp.kernel
def pool_coefficients(
    terms: wp.array3d(dtype=wp.vec4d),
    k: int,
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    last: int,
    coefficient: wp.array3d(dtype=wp.float64),
):
    """Of the pairs that stop at this pass: the coefficient pooled over the k x k tiles around tile
    (pair, i, j) (means over the block, tiles beyond the field counting 0: ``ndimage.uniform_filter``,
    mode constant): sum of covariances over the root of the product of the sums of energies, 0 where
    the block has no usable tile or no energy."""
    b, i, j = wp.tid()
    if not stops(changed, b, p, last):
        return
    ny = terms.shape[1]
    nx = terms.shape[2]
    h = k // 2
    total = wp.vec4d()
    for y in range(wp.max(i - h, 0), wp.min(i + h + 1, ny)):
        for x in range(wp.max(j - h, 0), wp.min(j + h + 1, nx)):
            total = total + terms[b, y, x]
    area = wp.float64(k * k)
    cov = total[0] / area
    ea = total[1] / area
    eb = total[2] / area
    share = total[3] / area
    den = wp.sqrt(wp.max(ea * eb, wp.float64(0.0)))
    q = wp.float64(0.0)
    if share > wp.float64(0.5) / area and den > wp.float64(0.0):
        q = cov / den
    coefficient[b, i, j] = q


@wp.kernel
def values_at_dots(
    xy: wp.array2d(dtype=wp.vec2d),
    field_u: wp.array3d(dtype=wp.float64),
    field_v: wp.array3d(dtype=wp.float64),
    coefficient: wp.array3d(dtype=wp.float64),
    grid: TileGrid,
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    last: int,
    uv: wp.array2d(dtype=wp.vec2d),
    quality: wp.array2d(dtype=wp.float64),
):
    """Of the pairs that stop at this pass: dot (pair, q)'s displacement and significance, the tile fields
    interpolated bilinearly (linearly extrapolated beyond the outer centres); NaN for a non-finite
    position."""
    b, q = wp.tid()
    if not stops(changed, b, p, last):
        return
    pt = xy[b, q]
    fin = wp.isfinite(pt[0]) and wp.isfinite(pt[1])
    x = wp.float64(0.0)
    y = wp.float64(0.0)
    if fin:
        x = pt[0]
        y = pt[1]
    cy = row_cell(grid, y)
    cx = col_cell(grid, x)
    if fin:
        uv[b, q] = wp.vec2d(bilinear(field_u, b, cy, cx), bilinear(field_v, b, cy, cx))
        quality[b, q] = bilinear(coefficient, b, cy, cx)
    else:
        nan = wp.float64(wp.nan)
        uv[b, q] = wp.vec2d(nan, nan)
        quality[b, q] = nan
