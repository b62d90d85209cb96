# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of the neighbour tests: the local linear fit of scattered vectors from each point's
nearest neighbours (one thread per point; host code in :mod:`tracking.neighbours`, and the stacked
form in :mod:`tracking.neighbour_batch_kernels`, which reuses the search and the fit).
"""

import warp as wp

wp.config.quiet = True  # no banner or module-load lines from library code
wp.config.log_level = wp.LOG_WARNING
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile


# --- the local linear fit of scattered vectors from each point's nearest neighbours -----------------


@wp.func
def keep_nearest(d: wp.float64, p: wp.float64, found: int, base: int, k: int, near: wp.array(dtype=wp.vec2d)) -> int:
    """Insert point ``p`` at squared distance ``d`` into the ascending list of the ``k`` nearest
    ``near[base:base + k]`` (``(squared distance, index)``, ties broken by the lower index, so the set does
    not depend on the visiting order); return the new count. The caller has checked that ``p`` belongs
    there (``found < k`` or it comes before the last entry)."""
    m = wp.min(found, k - 1)
    while m > 0:
        e = near[base + m - 1]
        if not (e[0] > d or (e[0] == d and e[1] > p)):
            break
        near[base + m] = e
        m -= 1
    near[base + m] = wp.vec2d(d, p)
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
    k: int,
    near: wp.array(dtype=wp.vec2d),
) -> int:
    """Offer the points ``j0 <= j < j1`` of the cell order that lie within squared distance ``limit`` of
    ``(qx, qy)`` to the k nearest list (``keep_nearest``); return the new count. While the list is full,
    a point must also come before its last entry (held in registers, reloaded after an insertion)."""
    f = found
    worst = wp.vec2d(limit, wp.float64(0.0))
    if f == k:
        worst = near[base + k - 1]
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
                    f = keep_nearest(d, pf, f, base, k, near)
                    if f == k:
                        worst = near[base + k - 1]
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
    k: int,
    near: wp.array(dtype=wp.vec2d),
) -> int:
    """The ``k`` nearest points of ``(qx, qy)`` but ``own`` into ``near[base:base + k]`` (squared
    distance, index; ascending, ties to the lower index), from the grid whose cell ``c`` is
    ``first_cell + c`` of ``cell_start``: growing blocks of cells searched as
    ``neighbour_fit_kernel`` describes (``scan_cells``); return how many were found."""
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
    k: int,
    near: wp.array(dtype=wp.vec2d),
    work: wp.array(dtype=wp.vec4d),
    resid: wp.array(dtype=wp.float64),
    network: wp.array2d(dtype=wp.int32),
) -> wp.vec3d:
    """Least squares plane ``f = c + G d`` through the vectors of the ``k`` points in ``near[base:]``
    (offsets ``d`` from q): ``(f_u(q), f_v(q), median distance of their vectors from the plane)``, with
    ``work`` and ``resid`` as scratch rows (see ``neighbour_fit_kernel``)."""
    kf = wp.float64(k)
    dmx = wp.float64(0.0)
    dmy = wp.float64(0.0)
    fmu = wp.float64(0.0)
    fmv = wp.float64(0.0)
    j = int(0)
    while j < k:
        p = int(near[base + j][1])
        pxy = xy[p]
        puv = uv[p]
        w = wp.vec4d(pxy[0] - qx, pxy[1] - qy, puv[0], puv[1])
        work[base + j] = w
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
        w = work[base + j]
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
        w = work[base + j]
        ex = w[0] - dmx
        ey = w[1] - dmy
        gu = w[2] - fmu - ex * gxu - ey * gyu
        gv = w[3] - fmv - ex * gxv - ey * gyv
        resid[base + j] = gu * gu + gv * gv
        j += 1
    # median of the distances: the middle squares put in place by the compare-exchange network
    t = int(0)
    while t < network.shape[0]:
        a = base + network[t, 0]
        c = base + network[t, 1]
        va = resid[a]
        vc = resid[c]
        resid[a] = wp.min(va, vc)
        resid[c] = wp.max(va, vc)
        t += 1
    spread = wp.float64(0.0)
    if k % 2 == 1:
        spread = wp.sqrt(resid[base + k / 2])
    else:
        spread = wp.float64(0.5) * (wp.sqrt(resid[base + k / 2 - 1]) + wp.sqrt(resid[base + k / 2]))
    return wp.vec3d(fmu - dmx * gxu - dmy * gyu, fmv - dmx * gxv - dmy * gyv, spread)


@wp.kernel
def neighbour_fit_kernel(
    query_order: wp.array(dtype=wp.int32),
    xy: wp.array(dtype=wp.vec2d),
    uv: wp.array(dtype=wp.vec2d),
    query: wp.array(dtype=wp.vec2d),
    self_index: wp.array(dtype=wp.int32),
    cell_start: wp.array(dtype=wp.int32),
    cell_points: wp.array(dtype=wp.int32),
    cell_xy: wp.array(dtype=wp.vec2d),
    x0: wp.float64,
    y0: wp.float64,
    cell: wp.float64,
    nx: int,
    ny: int,
    rows: int,
    near: wp.array(dtype=wp.vec2d),
    work: wp.array(dtype=wp.vec4d),
    resid: wp.array(dtype=wp.float64),
    value: wp.array2d(dtype=wp.float64),
    spread: wp.array(dtype=wp.float64),
    neighbours: wp.array2d(dtype=wp.int32),
    network: wp.array2d(dtype=wp.int32),
):
    """Local linear fit of ``uv`` at query point q from its ``k`` nearest points of ``xy`` (its own index
    ``self_index[q]`` left out; ``k = neighbours.shape[1]``): the fit's value at q and the median distance
    of the neighbours' vectors from the fit (see ``tracking.reference.neighbour_fit_numpy``);
    ``neighbours[q]`` gets the ``k`` points' indices, nearest first (ties: the lower index first).

    The points are sorted into square cells of side ``cell`` from ``(x0, y0)`` (``cell_points``
    ``[cell_start[c]:cell_start[c + 1]]`` lie in cell ``c = row * nx + col``, so a row of cells is one
    run; ``cell_xy`` holds their positions in that order, read without a gather). The block of
    ``(2 r + 1)^2`` cells around q's, r = 1, 2, ..., holds every point within the distance from q to its
    nearest edge that is not the edge of the grid; only the points within that distance are kept, and
    the first block with ``k`` of them has the k nearest (a larger block is searched afresh; the whole
    grid at the latest). Thread t takes query ``query_order[t]`` (queries in the order of their cells:
    neighbouring threads read the same points). ``near`` (the k nearest: squared distance and index),
    ``work`` (their offsets from q and vectors) and ``resid`` (the squared distances of their vectors from
    the fit) are scratch rows of length k: query q's start at ``(q % rows) * k``. ``network`` is
    ``tracking.sorting.median_network(k)``.
    """
    q = query_order[wp.tid()]
    k = neighbours.shape[1]
    base = wp.max((q % rows) * k, 0)
    qxy = query[q]
    nearest_in_grid(
        qxy[0], qxy[1], self_index[q], 0, x0, y0, cell, nx, ny, cell_start, cell_points, cell_xy, base, k, near
    )
    for j in range(k):
        neighbours[q, j] = int(near[base + j][1])
    fit = plane_fit(qxy[0], qxy[1], xy, uv, base, k, near, work, resid, network)
    value[q, 0] = fit[0]
    value[q, 1] = fit[1]
    spread[q] = fit[2]
