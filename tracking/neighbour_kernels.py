# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of the neighbour tests: the local linear fit of scattered vectors from each point's
nearest neighbours, for many image pairs in every launch (one pair: a stack of one; host code in
:mod:`tracking.neighbours`).

The arrays are laid out per pair: a ``(B, N)`` array holds dot ``i`` of pair ``b`` at
``[b, i]``, its flat view at the dot's global index ``g = b * N + i``. A dot's ``role`` says what it is to
one neighbour fit: ``POINT`` (one of the fitted points), ``QUERY`` (a place to fit at), both, or neither
(0). Each pair has a cell grid over the box of its dots with a role (``grid_params_kernel``); pair ``b``'s
cell ``c = row * nx + col`` is ``b * stride + c`` of the stack, so that one exclusive scan of all the
cells' counts gives every pair's runs at once. The k-nearest search (``nearest_in_grid``) and the fit
(``plane_fit``) read the grid per pair.
"""

import warp as wp
from synthbos.correlation.median_test import residual_limit_wp

from synthbos.device import quiet_warp

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile


# --- the local linear fit of scattered vectors from each point's nearest neighbours -----------------


@wp.func
def keep_nearest(
    d: wp.float64, p: wp.float64, found: int, base: int, step: int, k: int, near: wp.array(dtype=wp.vec2d)
) -> int:
    """Insert point ``p`` at squared distance ``d`` into the ascending list of the ``k`` nearest
    ``near[base + j step]``, ``j < k`` (``(squared distance, index)``, ties broken by the lower index, so the
    set does not depend on the visiting order); return the new count. The caller has checked that ``p`` belongs
    there (``found < k`` or it comes before the last entry)."""
    m = wp.min(found, k - 1)
    while m > 0:
        e = near[base + (m - 1) * step]
        if not (e[0] > d or (e[0] == d and e[1] > p)):
            break
        near[base + m * step] = e
        m -= 1
    near[base + m * step] = wp.vec2d(d, p)
    return wp.min(found + 1, k)


@wp.func
def scan_cells(
    j0: int,
    j1: int,
    qx: wp.float64,
    qy: wp.float64,
    own: int,
    cell_points: wp.array(dtype=wp.int32),
    cell_xy: wp.array(dtype=wp.vec2d),
    limit: wp.float64,
    found: int,
    base: int,
    step: int,
    k: int,
    near: wp.array(dtype=wp.vec2d),
) -> int:
    """Offer the points ``j0 <= j < j1`` of the cell order that lie within squared distance ``limit`` of
    ``(qx, qy)`` to the k nearest list (``keep_nearest``); return the new count. While the list is full,
    a point must also come before its last entry (held in registers, reloaded after an insertion)."""
    f = found
    worst = wp.vec2d(limit, wp.float64(0.0))
    if f == k:
        worst = near[base + (k - 1) * step]
    j = int(j0)
    while j < j1:  # (cheaper than a range with a step of either sign)
        c = cell_xy[j]
        dx = c[0] - qx
        dy = c[1] - qy
        d = dx * dx + dy * dy
        if d <= worst[0]:
            p = int(cell_points[j])
            if p != own:
                pf = wp.float64(p)
                if f < k or d < worst[0] or pf < worst[1]:
                    f = keep_nearest(d, pf, f, base, step, k, near)
                    if f == k:
                        worst = near[base + (k - 1) * step]
        j += 1
    return f


@wp.func
def nearest_in_grid(
    qx: wp.float64,
    qy: wp.float64,
    own: int,
    first_cell: int,
    x0: wp.float64,
    y0: wp.float64,
    cell: wp.float64,
    nx: int,
    ny: int,
    cell_start: wp.array(dtype=wp.int32),
    cell_points: wp.array(dtype=wp.int32),
    cell_xy: wp.array(dtype=wp.vec2d),
    base: int,
    step: int,
    k: int,
    near: wp.array(dtype=wp.vec2d),
) -> int:
    """The ``k`` nearest points of ``(qx, qy)`` but ``own`` into ``near[base + j step]``, ``j < k`` (squared
    distance, index; ascending, ties to the lower index), from the grid whose cell ``c`` is
    ``first_cell + c`` of ``cell_start``; return how many were found.

    The points are sorted into square cells of side ``cell`` from ``(x0, y0)`` (``cell_points``
    ``[cell_start[c]:cell_start[c + 1]]`` lie in cell ``c = row * nx + col``, so a row of cells is one
    run; ``cell_xy`` holds their positions in that order, read without a gather). The block of
    ``(2 r + 1)^2`` cells around q's, r = 1, 2, ..., holds every point within the distance from q to its
    nearest edge that is not the edge of the grid; only the points within that distance are kept
    (``scan_cells``), and the first block with ``k`` of them has the k nearest (a larger block is searched
    afresh; the whole grid at the latest)."""
    cx = wp.clamp(int(wp.floor((qx - x0) / cell)), 0, nx - 1)
    cy = wp.clamp(int(wp.floor((qy - y0) / cell)), 0, ny - 1)
    found = int(0)
    r = int(1)
    while found < k:
        # distance from q to the nearest edge of the block that is not the edge of the grid
        edge = wp.float64(1.0e300)
        if cx - r > 0:
            edge = wp.min(edge, qx - (x0 + wp.float64(cx - r) * cell))
        if cx + r < nx - 1:
            edge = wp.min(edge, x0 + wp.float64(cx + r + 1) * cell - qx)
        if cy - r > 0:
            edge = wp.min(edge, qy - (y0 + wp.float64(cy - r) * cell))
        if cy + r < ny - 1:
            edge = wp.min(edge, y0 + wp.float64(cy + r + 1) * cell - qy)
        limit = edge * edge
        ix0 = wp.max(cx - r, 0)
        ix1 = wp.min(cx + r, nx - 1)
        found = int(0)
        for t in range(2 * r + 1):
            iy = cy + (t + 1) / 2  # rows cy, cy + 1, cy - 1, cy + 2, ...
            if t % 2 == 0:
                iy = cy - t / 2
            if iy >= 0 and iy < ny:
                row = first_cell + iy * nx
                found = scan_cells(
                    cell_start[row + ix0],
                    cell_start[row + ix1 + 1],
                    qx,
                    qy,
                    own,
                    cell_points,
                    cell_xy,
                    limit,
                    found,
                    base,
                    step,
                    k,
                    near,
                )
        if cx - r <= 0 and cy - r <= 0 and cx + r >= nx - 1 and cy + r >= ny - 1:
            break  # the block holds every point
        r += 1
    return found


@wp.func
def plane_fit(
    qx: wp.float64,
    qy: wp.float64,
    xy: wp.array(dtype=wp.vec2d),
    uv: wp.array(dtype=wp.vec2d),
    base: int,
    step: int,
    k: int,
    near: wp.array(dtype=wp.vec2d),
    work: wp.array(dtype=wp.vec4d),
    resid: wp.array(dtype=wp.float64),
    network: wp.array2d(dtype=wp.int32),
) -> wp.vec3d:
    """Least squares plane ``f = c + G d`` through the vectors of the ``k`` points ``near[base + j step]``
    (offsets ``d`` from q): ``(f_u(q), f_v(q), median distance of their vectors from the plane)``, with
    ``work`` and ``resid`` as scratch rows of length k (the points' offsets from q and vectors, the
    squared distances of their vectors from the fit); ``network`` is ``median_network(k)``."""
    kf = wp.float64(k)
    dmx = wp.float64(0.0)
    dmy = wp.float64(0.0)
    fmu = wp.float64(0.0)
    fmv = wp.float64(0.0)
    j = int(0)
    while j < k:
        p = int(near[base + j * step][1])
        pxy = xy[p]
        puv = uv[p]
        w = wp.vec4d(pxy[0] - qx, pxy[1] - qy, puv[0], puv[1])
        work[base + j * step] = w
        dmx += w[0]
        dmy += w[1]
        fmu += w[2]
        fmv += w[3]
        j += 1
    dmx = dmx / kf
    dmy = dmy / kf
    fmu = fmu / kf
    fmv = fmv / kf
    sxx = wp.float64(0.0)
    syy = wp.float64(0.0)
    sxy = wp.float64(0.0)
    bxu = wp.float64(0.0)
    byu = wp.float64(0.0)
    bxv = wp.float64(0.0)
    byv = wp.float64(0.0)
    j = int(0)
    while j < k:
        w = work[base + j * step]
        ex = w[0] - dmx
        ey = w[1] - dmy
        gu = w[2] - fmu
        gv = w[3] - fmv
        sxx += ex * ex
        syy += ey * ey
        sxy += ex * ey
        bxu += ex * gu
        byu += ey * gu
        bxv += ex * gv
        byv += ey * gv
        j += 1
    ridge = wp.float64(1.0e-6) * (kf + sxx + syy)
    sxx += ridge
    syy += ridge
    det = sxx * syy - sxy * sxy
    gxu = (syy * bxu - sxy * byu) / det
    gyu = (sxx * byu - sxy * bxu) / det
    gxv = (syy * bxv - sxy * byv) / det
    gyv = (sxx * byv - sxy * bxv) / det
    j = int(0)
    while j < k:
        w = work[base + j * step]
        ex = w[0] - dmx
        ey = w[1] - dmy
        gu = w[2] - fmu - ex * gxu - ey * gyu
        gv = w[3] - fmv - ex * gxv - ey * gyv
        resid[base + j * step] = gu * gu + gv * gv
        j += 1
    # median of the distances: the middle squares put in place by the compare-exchange network
    t = int(0)
    while t < network.shape[0]:
        a = base + network[t, 0] * step
        c = base + network[t, 1] * step
        va = resid[a]
        vc = resid[c]
        resid[a] = wp.min(va, vc)
        resid[c] = wp.max(va, vc)
        t += 1
    spread = wp.float64(0.0)
    if k % 2 == 1:
        spread = wp.sqrt(resid[base + (k / 2) * step])
    else:
        upper = wp.sqrt(resid[base + (k / 2) * step])
        spread = wp.float64(0.5) * (wp.sqrt(resid[base + (k / 2 - 1) * step]) + upper)
    return wp.vec3d(fmu - dmx * gxu - dmy * gyu, fmv - dmx * gxv - dmy * gyv, spread)


# --- the stacked form: many pairs in every launch -------------------------------------------------

POINT = wp.constant(1)
QUERY = wp.constant(2)

#: Options of the tests' kernels: their own modules, compiled without floating-point contraction, so that
#: ``sqrt(du * du + dv * dv)`` rounds as NumPy's in the host functions' tests (on a GPU it would become
#: a fused multiply-add). The fit keeps the default.
_UNFUSED = {"module": "unique", "module_options": {"fuse_fp": False, "enable_backward": False}}


# --- each pair's cell grid: the box, the cells, a counting sort ------------------------------------


@wp.kernel
def pair_stats_init_kernel(
    count: wp.array2d(dtype=wp.int32), lo: wp.array(dtype=wp.vec2d), hi: wp.array(dtype=wp.vec2d)
):
    """Pair ``b``'s counts of points and queries to zero, its box to empty (``lo = +inf, hi = -inf``)."""
    b = wp.tid()
    count[b, 0] = 0
    count[b, 1] = 0
    inf = wp.float64(wp.inf)
    lo[b] = wp.vec2d(inf, inf)
    hi[b] = wp.vec2d(-inf, -inf)


@wp.kernel
def pair_stats_kernel(
    xy: wp.array2d(dtype=wp.vec2d),
    role: wp.array2d(dtype=wp.int32),
    step: int,
    count: wp.array2d(dtype=wp.int32),
    lo: wp.array(dtype=wp.vec2d),
    hi: wp.array(dtype=wp.vec2d),
):
    """Thread ``(b, c)`` of a ``(B, step)`` launch takes the dots ``c, c + step, ...`` of pair ``b``: their
    numbers of points and queries are added to ``count[b]`` and the box of those with a role joins
    ``lo[b], hi[b]`` (one atomic per thread and quantity; a minimum or maximum is exact in any order)."""
    b, c = wp.tid()
    n = role.shape[1]
    npt = int(0)
    nq = int(0)
    inf = wp.float64(wp.inf)
    x0 = inf
    y0 = inf
    x1 = -inf
    y1 = -inf
    i = int(c)
    while i < n:
        r = role[b, i]
        if r != 0:
            p = xy[b, i]
            x0 = wp.min(x0, p[0])
            y0 = wp.min(y0, p[1])
            x1 = wp.max(x1, p[0])
            y1 = wp.max(y1, p[1])
            if (r & POINT) != 0:
                npt += 1
            if (r & QUERY) != 0:
                nq += 1
        i += step
    if npt + nq > 0:
        wp.atomic_add(count, b, 0, npt)
        wp.atomic_add(count, b, 1, nq)
        wp.atomic_min(lo, b, wp.vec2d(x0, y0))
        wp.atomic_max(hi, b, wp.vec2d(x1, y1))


@wp.kernel
def grid_params_kernel(
    count: wp.array2d(dtype=wp.int32),
    lo: wp.array(dtype=wp.vec2d),
    hi: wp.array(dtype=wp.vec2d),
    min_points: int,
    per_cell: wp.float64,
    origin: wp.array(dtype=wp.vec2d),
    side: wp.array(dtype=wp.float64),
    shape: wp.array(dtype=wp.vec2i),
):
    """Pair ``b``'s cell grid: square
    cells holding ``per_cell`` points on average over the box, at least 1/4096 of its longer side. A pair
    with fewer than ``min_points`` points or no query is left out: ``shape[b] = (0, 0)``."""
    b = wp.tid()
    m = count[b, 0]
    if m < min_points or count[b, 1] == 0:
        shape[b] = wp.vec2i(0, 0)
        return
    l = lo[b]
    h = hi[b]
    ex = wp.max(h[0] - l[0], wp.float64(1.0e-9))
    ey = wp.max(h[1] - l[1], wp.float64(1.0e-9))
    s = wp.sqrt(ex * ey * per_cell / wp.float64(m))
    s = wp.max(wp.max(s, wp.max(ex, ey) / wp.float64(4096.0)), wp.float64(1.0e-9))
    origin[b] = l
    side[b] = s
    shape[b] = wp.vec2i(int(wp.floor(ex / s)) + 1, int(wp.floor(ey / s)) + 1)


@wp.func
def cell_of(p: wp.vec2d, x0: wp.vec2d, side: wp.float64, nx: int, ny: int) -> wp.vec2i:
    """Column and row of the cell holding ``p`` (clamped to the grid)."""
    cx = wp.clamp(int(wp.floor((p[0] - x0[0]) / side)), 0, nx - 1)
    cy = wp.clamp(int(wp.floor((p[1] - x0[1]) / side)), 0, ny - 1)
    return wp.vec2i(cx, cy)


@wp.kernel
def count_cells_kernel(
    xy: wp.array2d(dtype=wp.vec2d),
    role: wp.array2d(dtype=wp.int32),
    origin: wp.array(dtype=wp.vec2d),
    side: wp.array(dtype=wp.float64),
    shape: wp.array(dtype=wp.vec2i),
    stride: int,
    sort_queries: int,
    cell: wp.array2d(dtype=wp.int32),
    point_count: wp.array(dtype=wp.int32),
    point_slot: wp.array2d(dtype=wp.int32),
    query_count: wp.array(dtype=wp.int32),
    query_slot: wp.array2d(dtype=wp.int32),
):
    """Dot ``(b, i)`` with a role in a pair that has a grid: its stack cell into ``cell``; a point takes
    the next slot of its cell's ``point_count`` (atomically: the order within a cell is arbitrary and
    does not matter), and with ``sort_queries`` a query that of ``query_count``."""
    b, i = wp.tid()
    r = role[b, i]
    s = shape[b]
    if r == 0 or s[0] == 0:
        return
    q = cell_of(xy[b, i], origin[b], side[b], s[0], s[1])
    c = b * stride + q[1] * s[0] + q[0]
    cell[b, i] = c
    if (r & POINT) != 0:
        point_slot[b, i] = wp.atomic_add(point_count, c, 1)
    if sort_queries != 0 and (r & QUERY) != 0:
        query_slot[b, i] = wp.atomic_add(query_count, c, 1)


@wp.kernel
def fill_cells_kernel(
    xy: wp.array2d(dtype=wp.vec2d),
    role: wp.array2d(dtype=wp.int32),
    shape: wp.array(dtype=wp.vec2i),
    cell: wp.array2d(dtype=wp.int32),
    sort_queries: int,
    point_start: wp.array(dtype=wp.int32),
    point_slot: wp.array2d(dtype=wp.int32),
    query_start: wp.array(dtype=wp.int32),
    query_slot: wp.array2d(dtype=wp.int32),
    cell_points: wp.array(dtype=wp.int32),
    cell_xy: wp.array(dtype=wp.vec2d),
    query_order: wp.array(dtype=wp.int32),
):
    """The counting sort's scatter: a point's global index and position to its place in the cell order
    (``cell_points``, ``cell_xy``); with ``sort_queries`` a query's global index to ``query_order``."""
    b, i = wp.tid()
    r = role[b, i]
    if r == 0 or shape[b][0] == 0:
        return
    g = b * role.shape[1] + i
    c = cell[b, i]
    if (r & POINT) != 0:
        j = point_start[c] + point_slot[b, i]
        cell_points[j] = g
        cell_xy[j] = xy[b, i]
    if sort_queries != 0 and (r & QUERY) != 0:
        query_order[query_start[c] + query_slot[b, i]] = g


# --- the k nearest points and the local linear fit ---------------------------------------------------


@wp.kernel
def neighbour_fit_stack_kernel(
    query_order: wp.array(dtype=wp.int32),
    query_start: wp.array(dtype=wp.int32),
    n: int,
    stride: int,
    threads: int,
    exclude_self: int,
    origin: wp.array(dtype=wp.vec2d),
    side: wp.array(dtype=wp.float64),
    shape: wp.array(dtype=wp.vec2i),
    point_start: wp.array(dtype=wp.int32),
    cell_points: wp.array(dtype=wp.int32),
    cell_xy: wp.array(dtype=wp.vec2d),
    xy: wp.array(dtype=wp.vec2d),
    uv: wp.array(dtype=wp.vec2d),
    rows: int,
    near: wp.array(dtype=wp.vec2d),
    work: wp.array(dtype=wp.vec4d),
    resid: wp.array(dtype=wp.float64),
    network: wp.array2d(dtype=wp.int32),
    store_neighbours: int,
    value: wp.array(dtype=wp.vec2d),
    spread: wp.array(dtype=wp.float64),
    neighbours: wp.array2d(dtype=wp.int32),
):
    """Local linear fit at every sorted query of the stack from the ``k`` nearest points of its pair
    (``k = neighbours.shape[1]``; with ``exclude_self`` the query itself is not one of them): the value
    into ``value[g]`` and the median distance into ``spread[g]`` (``g``: the query's global index), and
    with ``store_neighbours`` the points' global indices, nearest first, into ``neighbours[g]``.

    Thread t of ``threads`` takes the queries ``query_order[t], query_order[t + threads], ...`` up to
    ``query_start[-1]`` (their number: queries in the order of their cells, so neighbouring threads
    read the same points). ``near``, ``work`` and ``resid`` hold ``rows`` scratch rows of length ``k``,
    interleaved: thread t's entry j at ``j rows + t % rows``, so that a warp's threads read and write
    neighbouring entries (on the CPU one row). ``network`` is ``tracking.windows.median_network(k)``."""
    tid = wp.tid()
    k = neighbours.shape[1]
    base = tid % rows
    step = rows
    total = query_start[query_start.shape[0] - 1]
    t = int(tid)
    while t < total:
        g = query_order[t]
        b = g / n
        s = shape[b]
        o = origin[b]
        qxy = xy[g]
        own = int(-1)
        if exclude_self != 0:
            own = g
        nearest_in_grid(
            qxy[0],
            qxy[1],
            own,
            b * stride,
            o[0],
            o[1],
            side[b],
            s[0],
            s[1],
            point_start,
            cell_points,
            cell_xy,
            base,
            step,
            k,
            near,
        )
        if store_neighbours != 0:
            j = int(0)
            while j < k:
                neighbours[g, j] = int(near[base + j * step][1])
                j += 1
        f = plane_fit(qxy[0], qxy[1], xy, uv, base, step, k, near, work, resid, network)
        value[g] = wp.vec2d(f[0], f[1])
        spread[g] = f[2]
        t += threads


# --- roles and tests -----------------------------------------------------------------------------------


@wp.kernel
def roles_kernel(
    points: wp.array2d(dtype=wp.int32), queries: wp.array2d(dtype=wp.int32), role: wp.array2d(dtype=wp.int32)
):
    """A dot's role from two masks: ``POINT`` where ``points``, ``QUERY`` where ``queries`` (nonzero)."""
    b, i = wp.tid()
    r = int(0)
    if points[b, i] != 0:
        r = r | POINT
    if queries[b, i] != 0:
        r = r | QUERY
    role[b, i] = r


@wp.func
def deviation(uv: wp.array2d(dtype=wp.vec2d), value: wp.array(dtype=wp.vec2d), b: int, i: int) -> wp.float64:
    """``|uv - value|`` of dot ``i`` of pair ``b`` from its neighbours' fitted value (``value`` flat, by
    global index): the distance of the normalised median test (unfused in the kernels that call it)."""
    d = uv[b, i] - value[b * uv.shape[1] + i]
    return wp.sqrt(d[0] * d[0] + d[1] * d[1])


@wp.kernel(**_UNFUSED)
def outlier_flags_kernel(
    uv: wp.array2d(dtype=wp.vec2d),
    value: wp.array(dtype=wp.vec2d),
    spread: wp.array(dtype=wp.float64),
    role: wp.array2d(dtype=wp.int32),
    shape: wp.array(dtype=wp.vec2i),
    threshold: wp.float64,
    epsilon: wp.float64,
    first_round: int,
    bad: wp.array2d(dtype=wp.int32),
    bad_count: wp.array(dtype=wp.int32),
):
    """The normalised median test at every fitted query: 1 in ``bad`` where ``|uv - value|`` exceeds
    ``threshold * (spread + epsilon)``, else 0. In the ``first_round`` every other dot gets 0 and the bad
    ones are counted per pair into ``bad_count``; later rounds change the queries' flags only."""
    b, i = wp.tid()
    if (role[b, i] & QUERY) == 0 or shape[b][0] == 0:
        if first_round != 0:
            bad[b, i] = 0
        return
    g = b * role.shape[1] + i
    far = deviation(uv, value, b, i) > residual_limit_wp(spread[g], epsilon, threshold)
    if far:
        bad[b, i] = 1
        if first_round != 0:
            wp.atomic_add(bad_count, b, 1)
    else:
        bad[b, i] = 0


@wp.kernel
def refit_roles_kernel(
    role: wp.array2d(dtype=wp.int32),
    shape: wp.array(dtype=wp.vec2i),
    count: wp.array2d(dtype=wp.int32),
    bad: wp.array(dtype=wp.int32),
    bad_count: wp.array(dtype=wp.int32),
    neighbours: wp.array2d(dtype=wp.int32),
    min_points: int,
    new_role: wp.array2d(dtype=wp.int32),
):
    """The second round's roles, in pairs where the first found a bad vector and kept at least
    ``min_points``: the kept points are its points, and the dots with a bad one among their neighbours
    (``bad``: flat, by global index) its queries. Elsewhere no role."""
    b, i = wp.tid()
    new_role[b, i] = 0
    nb = bad_count[b]
    if role[b, i] == 0 or shape[b][0] == 0 or nb == 0 or count[b, 0] - nb < min_points:
        return
    g = b * role.shape[1] + i
    r = int(0)
    if bad[g] == 0:
        r = POINT
    j = int(0)
    while j < neighbours.shape[1]:
        if bad[neighbours[g, j]] != 0:
            r = r | QUERY
            break
        j += 1
    new_role[b, i] = r


@wp.kernel(**_UNFUSED)
def confirm_flags_kernel(
    uv: wp.array2d(dtype=wp.vec2d),
    value: wp.array(dtype=wp.vec2d),
    spread: wp.array(dtype=wp.float64),
    role: wp.array2d(dtype=wp.int32),
    shape: wp.array(dtype=wp.vec2i),
    threshold: wp.float64,
    epsilon: wp.float64,
    tolerance: wp.float64,
    ok: wp.array2d(dtype=wp.int32),
):
    """1 in ``ok`` at a fitted query whose ``|uv - value|`` is at most ``min(threshold * (spread +
    epsilon), tolerance)``; 0 everywhere else."""
    b, i = wp.tid()
    ok[b, i] = 0
    if (role[b, i] & QUERY) == 0 or shape[b][0] == 0:
        return
    g = b * role.shape[1] + i
    limit = wp.min(residual_limit_wp(spread[g], epsilon, threshold), tolerance)
    if deviation(uv, value, b, i) <= limit:
        ok[b, i] = 1
