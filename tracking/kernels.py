# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of dot tracking.

Kernels and ``@wp.func`` steps only; the host code that allocates and launches lives next to it:
:mod:`tracking.windows` (identification: one thread measures the window around one predicted dot) and
:mod:`tracking.dotfit` (the joint least-squares fit of the pixel-integrated dot model: one thread per
dot). Their NumPy references (``measure_windows_numpy``, ``fit_dots_numpy``) define what the kernels
compute. Windows are held flat, pixel ``p`` of a ``w x w`` window at row ``p // w``, column ``p % w``.
"""

import warp as wp

from .settings import SMALL_WINDOW
from .sorting import median_network

wp.config.quiet = True  # no banner or module-load lines from library code
wp.config.log_level = wp.LOG_WARNING
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile

vec5d = wp.types.vector(length=5, dtype=wp.float64)
mat32d = wp.types.matrix(shape=(3, 2), dtype=wp.float64)


@wp.struct
class NormalEquations:
    """Normal equations of one dot, parameters split into position and background ``(x, y, b)`` and shape
    ``(I0, sigma)``: ``J^T J = [[p, q], [q^T, r]]``, ``J^T res = (g1, g2)``; ``h1`` is the position part
    of ``J^T res'`` against the common-shape model image."""

    p: wp.mat33d
    q: mat32d
    r: wp.mat22d
    g1: wp.vec3d
    g2: wp.vec2d
    h1: wp.vec3d


# --- identification: one window around one predicted position -------------------------------------


@wp.func
def load_window(
    image: wp.array2d(dtype=wp.float64),
    fill: wp.float64,
    ox: int,
    oy: int,
    w: int,
    i: int,
    win: wp.array2d(dtype=wp.float64),
) -> wp.vec2d:
    """Copy the window at column ``ox``, row ``oy`` into ``win[i]`` (``fill`` outside); return (min, max)."""
    vmin = wp.float64(1.0e300)
    vmax = wp.float64(-1.0e300)
    for r in range(w):
        y = oy + r
        row_in = y >= 0 and y < image.shape[0]
        for c in range(w):
            x = ox + c
            v = fill
            if row_in and x >= 0 and x < image.shape[1]:
                v = image[y, x]
            win[i, r * w + c] = v
            vmin = wp.min(vmin, v)
            vmax = wp.max(vmax, v)
    return wp.vec2d(vmin, vmax)


@wp.func
def edge_median(
    win: wp.array2d(dtype=wp.float64),
    i: int,
    w: int,
    ring: wp.array2d(dtype=wp.float64),
    network: wp.array2d(dtype=wp.int32),
) -> wp.float64:
    """Median of the window's ``n = 4 (w - 1)`` edge pixels: copied into ``ring[i]``, put in place by the
    compare-exchange ``network`` (rows ``(a, b)``: ``ring[a], ring[b] = min, max``; one that brings the
    middle two of any n values to ``n / 2 - 1`` and ``n / 2``, without data-dependent branches), and the
    middle two averaged."""
    n = int(0)
    for r in range(w):
        step = int(1)
        if r != 0 and r != w - 1:
            step = w - 1
        for c in range(0, w, step):
            ring[i, n] = win[i, r * w + c]
            n += 1
    for k in range(network.shape[0]):
        a = network[k, 0]
        b = network[k, 1]
        va = ring[i, a]
        vb = ring[i, b]
        ring[i, a] = wp.min(va, vb)
        ring[i, b] = wp.max(va, vb)
    h = n / 2
    return (ring[i, h - 1] + ring[i, h]) / wp.float64(2.0)


@wp.func
def segment_window(
    win: wp.array2d(dtype=wp.float64),
    i: int,
    w: int,
    thr: wp.float64,
    lab: wp.array2d(dtype=wp.int32),
    area: wp.array2d(dtype=wp.int32),
    roots: wp.array2d(dtype=wp.int32),
) -> int:
    """Label each pixel above ``thr`` with its blob's peak pixel by steepest ascent (-1 below).

    A pixel's uphill step goes to the brightest of it and its 8 neighbours (ties: the higher index),
    taken as the brightest of the three rows' brightest of three (``area`` holds those first).
    Fills ``area[i, root]`` with each blob's pixel count and ``roots[i, :nblobs]`` with the peak
    pixels in increasing order; returns the number of blobs.
    """
    for r in range(w):
        for c in range(w):
            p = r * w + c
            best = p
            bv = win[i, p]
            if c > 0:
                if win[i, p - 1] > bv:
                    best = p - 1
                    bv = win[i, p - 1]
            if c < w - 1:
                if win[i, p + 1] >= bv:
                    best = p + 1
            area[i, p] = best
    nblobs = int(0)
    for r in range(w):
        r0 = wp.max(r - 1, 0)
        r1 = wp.min(r + 1, w - 1)
        for c in range(w):
            p = r * w + c
            best = int(-1)
            bv = win[i, p]
            if bv > thr:
                best = p
                for rr in range(r0, r1 + 1):
                    q = area[i, rr * w + c]
                    vq = win[i, q]
                    if vq > bv or (vq == bv and q > best):
                        best = q
                        bv = vq
                if best == p:
                    roots[i, nblobs] = p
                    nblobs += 1
            lab[i, p] = best
    for p in range(w * w):
        area[i, p] = 0
    for p in range(w * w):
        if lab[i, p] >= 0:
            r = lab[i, p]
            while lab[i, r] != r:
                r = lab[i, r]
            lab[i, p] = r
            area[i, r] = area[i, r] + 1
    return nblobs


@wp.func
def peak_distance(p: int, w: int, lx: wp.float64, ly: wp.float64) -> wp.float64:
    """Distance of window pixel p from the point (lx, ly) in window coordinates."""
    ddx = wp.float64(p % w) - lx
    ddy = wp.float64(p // w) - ly
    return wp.sqrt(ddx * ddx + ddy * ddy)


@wp.func
def eq1_score(
    area: wp.float64,
    peak: wp.float64,
    dist: wp.float64,
    ma: wp.float64,
    mi: wp.float64,
    md: wp.float64,
    wa: wp.float64,
    wi: wp.float64,
    wd: wp.float64,
) -> wp.float64:
    """Eq. 1 of Rajendran, Bane and Vlachos (2019) for one blob: its area, peak above the background and
    peak distance scaled by their maxima ``ma``, ``mi``, ``md`` over the candidates (a term is 1 where
    its maximum is not positive), weighted by ``wa``, ``wi``, ``wd``."""
    ta = wp.float64(1.0)
    ti = wp.float64(1.0)
    td = wp.float64(1.0)
    if ma > wp.float64(0.0):
        ta = area / ma
    if mi > wp.float64(0.0):
        ti = peak / mi
    if md > wp.float64(0.0):
        td = wp.float64(1.0) - dist / md
    return (wa * ta + wi * ti + wd * td) / (wa + wi + wd)


@wp.func
def choose_blob(
    win: wp.array2d(dtype=wp.float64),
    area: wp.array2d(dtype=wp.int32),
    roots: wp.array2d(dtype=wp.int32),
    nblobs: int,
    i: int,
    w: int,
    bg: wp.float64,
    lx: wp.float64,
    ly: wp.float64,
    radius: wp.float64,
    wa: wp.float64,
    wi: wp.float64,
    wd: wp.float64,
) -> int:
    """Peak pixel of the blob with the best Eq. 1 score among those within ``radius``; -1 if none.

    Eq. 1 of Rajendran, Bane and Vlachos (2019); area, peak and distance are scaled by their maxima
    over the candidates, and the first best (in pixel order) wins.
    """
    ma = wp.float64(-1.0e300)
    mi = wp.float64(-1.0e300)
    md = wp.float64(-1.0e300)
    for k in range(nblobs):
        p = roots[i, k]
        dist = peak_distance(p, w, lx, ly)
        if dist <= radius:
            ma = wp.max(ma, wp.float64(area[i, p]))
            mi = wp.max(mi, win[i, p] - bg)
            md = wp.max(md, dist)
    chosen = int(-1)
    best = wp.float64(-1.0e300)
    for k in range(nblobs):
        p = roots[i, k]
        dist = peak_distance(p, w, lx, ly)
        if dist <= radius:
            score = eq1_score(wp.float64(area[i, p]), win[i, p] - bg, dist, ma, mi, md, wa, wi, wd)
            if score > best:
                best = score
                chosen = p
    return chosen


@wp.func
def count_saturated(
    win: wp.array2d(dtype=wp.float64), lab: wp.array2d(dtype=wp.int32), i: int, w: int, chosen: int, sat: wp.float64
) -> int:
    """Pixels of the chosen blob at or above the saturation level (none below 1e300, the level of an image
    without saturation: no pixel is read)."""
    nsat = int(0)
    if sat >= wp.float64(1.0e300):
        return nsat
    for p in range(w * w):
        if lab[i, p] == chosen and win[i, p] >= sat:
            nsat += 1
    return nsat


@wp.func
def touches_blob(lab: wp.array2d(dtype=wp.int32), i: int, w: int, qr: int, qc: int, blob: int) -> bool:
    """True where pixel (qr, qc) or one of its 8 neighbours belongs to ``blob``."""
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            r = qr + dy
            c = qc + dx
            if r >= 0 and r < w and c >= 0 and c < w:
                if lab[i, r * w + c] == blob:
                    return True
    return False


@wp.func
def cut_dot_map(
    win: wp.array2d(dtype=wp.float64),
    lab: wp.array2d(dtype=wp.int32),
    i: int,
    w: int,
    chosen: int,
    bg: wp.float64,
    hc: int,
    k: int,
    full: int,
    dotmap: wp.array3d(dtype=wp.float64),
):
    """Dot map ``dotmap[k]`` centred on the chosen peak: the blob and its rim minus background, others zero.

    Without ``full`` only the peak and its four neighbours are cut (what the three-point fit needs), the
    rest of the map is zero."""
    c = 2 * hc + 1
    rr = chosen // w
    rc = chosen % w
    for a in range(c):
        for b in range(c):
            qr = rr + a - hc
            qc = rc + b - hc
            val = wp.float64(0.0)
            wanted = full != 0 or (a == hc and b >= hc - 1 and b <= hc + 1) or (b == hc and a >= hc - 1 and a <= hc + 1)
            if wanted and chosen >= 0 and qr >= 0 and qr < w and qc >= 0 and qc < w:
                l = lab[i, qr * w + qc]
                if l == chosen or (l < 0 and touches_blob(lab, i, w, qr, qc, chosen)):
                    val = win[i, qr * w + qc] - bg
            dotmap[k, a, b] = val


@wp.func
def cross_offset(j: int) -> wp.vec2i:
    """(row, column) offset of sample ``j`` of the centre cross that the three-point fits read: the peak,
    then its left, right, upper and lower neighbours."""
    if j == 1:
        return wp.vec2i(0, -1)
    if j == 2:
        return wp.vec2i(0, 1)
    if j == 3:
        return wp.vec2i(-1, 0)
    if j == 4:
        return wp.vec2i(1, 0)
    return wp.vec2i(0, 0)


@wp.func
def cut_cross(
    win: wp.array2d(dtype=wp.float64),
    lab: wp.array2d(dtype=wp.int32),
    i: int,
    w: int,
    chosen: int,
    bg: wp.float64,
    k: int,
    cross: wp.array2d(dtype=wp.float64),
):
    """The centre cross of ``cut_dot_map``'s map into ``cross[k]``: the peak, left, right, upper and lower
    pixels (what the three-point fit reads), each as in the map (zero where not the blob or its rim)."""
    rr = chosen // w
    rc = chosen % w
    for j in range(5):
        off = cross_offset(j)
        qr = rr + off[0]
        qc = rc + off[1]
        val = wp.float64(0.0)
        if chosen >= 0 and qr >= 0 and qr < w and qc >= 0 and qc < w:
            l = lab[i, qr * w + qc]
            if l == chosen or (l < 0 and touches_blob(lab, i, w, qr, qc, chosen)):
                val = win[i, qr * w + qc] - bg
        cross[k, j] = val


# The common window, 7 x 7 pixels (3-pixel dots), is measured by ``measure_small_window`` in local
# vectors with its size known to the compiler (loops unrolled, the edge median's network inlined).
SMALL_W = wp.constant(SMALL_WINDOW)
vec_small_f = wp.types.vector(length=49, dtype=wp.float64)
vec_small_i = wp.types.vector(length=49, dtype=wp.int32)
vec_ring = wp.types.vector(length=24, dtype=wp.float64)


def _edge_network():
    """Compile-time constant: the edge-median network of the 7 x 7 window's 24 edge pixels."""
    return median_network(24).tolist()


@wp.func
def measure_small_window(
    image: wp.array2d(dtype=wp.float64),
    fill: wp.float64,
    ox: int,
    oy: int,
    lx: wp.float64,
    ly: wp.float64,
    hc: int,
    radius: wp.float64,
    frac: wp.float64,
    floor: wp.float64,
    wa: wp.float64,
    wi: wp.float64,
    wd: wp.float64,
    use_min: int,
    sat: wp.float64,
    i: int,
    full_maps: int,
    out_int: wp.array2d(dtype=wp.int32),
    out_float: wp.array2d(dtype=wp.float64),
    dotmap: wp.array3d(dtype=wp.float64),
    cross: wp.array2d(dtype=wp.float64),
):
    """``measure_windows_kernel``'s steps for a 7 x 7 window held in local vectors: the same as
    ``load_window``, ``edge_median``, ``segment_window``, ``choose_blob``, ``count_saturated`` and
    ``cut_dot_map`` / ``cut_cross``, with the same result for finite pixels (its minimum, maximum and edge
    median are plain selects, which NaN pixels would upset)."""
    w = SMALL_W
    # load_window
    win = vec_small_f()
    vmin = wp.float64(1.0e300)
    vmax = wp.float64(-1.0e300)
    if ox >= 0 and oy >= 0 and ox + w <= image.shape[1] and oy + w <= image.shape[0]:
        for r in range(SMALL_W):
            for c in range(SMALL_W):
                win[wp.static(7 * r + c)] = image[oy + r, ox + c]
    else:
        for r in range(SMALL_W):
            y = oy + r
            row_in = y >= 0 and y < image.shape[0]
            for c in range(SMALL_W):
                x = ox + c
                v = fill
                if row_in and x >= 0 and x < image.shape[1]:
                    v = image[y, x]
                win[wp.static(7 * r + c)] = v
    for r in range(SMALL_W):
        for c in range(SMALL_W):
            v = win[wp.static(7 * r + c)]
            # the minimum and maximum as plain selects (one instruction each on the CPU; finite pixels)
            vmin = wp.where(v < vmin, v, vmin)
            vmax = wp.where(v > vmax, v, vmax)
    # edge_median
    bg = vmin
    if use_min == 0:
        ring = vec_ring()
        for c in range(SMALL_W):
            ring[c] = win[c]
            ring[wp.static(17 + c)] = win[wp.static(42 + c)]
        for r in range(1, 6):
            ring[wp.static(5 + 2 * r)] = win[wp.static(7 * r)]
            ring[wp.static(6 + 2 * r)] = win[wp.static(7 * r + 6)]
        for k in range(wp.static(len(_edge_network()))):
            va = ring[wp.static(_edge_network()[k][0])]
            vb = ring[wp.static(_edge_network()[k][1])]
            # min and max as plain selects on one comparison: no branch depends on the data, and on the
            # CPU each is one instruction (finite pixels; Warp's NaN-aware wp.min / wp.max take four)
            lt = va < vb
            ring[wp.static(_edge_network()[k][0])] = wp.where(lt, va, vb)
            ring[wp.static(_edge_network()[k][1])] = wp.where(lt, vb, va)
        bg = (ring[11] + ring[12]) / wp.float64(2.0)
    thr = bg + wp.max(frac * (vmax - bg), floor)
    # segment_window: row-best of three, then steepest ascent, then the roots and areas. Both passes keep the
    # winner's value beside its index, so that no pixel is read through an index and only the (rare) root
    # test branches on the pixel values. A pixel's uphill step is the brightest of its 3 x 3 neighbourhood,
    # ties going to the higher index: the brightest of the three rows' brightest of three, where within a
    # row and between the rows (whose indices increase with the row) a tie goes to the later one.
    upv = vec_small_f()
    up = vec_small_i()
    for r in range(SMALL_W):
        for c in range(SMALL_W):
            best = wp.static(7 * r + c)
            bv = win[wp.static(7 * r + c)]
            if wp.static(c > 0):
                take = win[wp.static(7 * r + c - 1)] > bv
                best = wp.where(take, wp.static(7 * r + c - 1), best)
                bv = wp.where(take, win[wp.static(7 * r + c - 1)], bv)
            if wp.static(c < 6):
                take = win[wp.static(7 * r + c + 1)] >= bv
                best = wp.where(take, wp.static(7 * r + c + 1), best)
                bv = wp.where(take, win[wp.static(7 * r + c + 1)], bv)
            up[wp.static(7 * r + c)] = best
            upv[wp.static(7 * r + c)] = bv
    lab = vec_small_i()
    roots = vec_small_i()
    nblobs = int(0)
    for r in range(SMALL_W):
        for c in range(SMALL_W):
            best = up[wp.static(7 * max(r - 1, 0) + c)]
            bv = upv[wp.static(7 * max(r - 1, 0) + c)]
            for rr in range(wp.static(max(r - 1, 0) + 1), wp.static(min(r + 1, 6) + 1)):
                take = upv[wp.static(7 * rr + c)] >= bv
                best = wp.where(take, up[wp.static(7 * rr + c)], best)
                bv = wp.where(take, upv[wp.static(7 * rr + c)], bv)
            above = win[wp.static(7 * r + c)] > thr
            lab[wp.static(7 * r + c)] = wp.where(above, best, -1)
            if above and best == wp.static(7 * r + c):
                roots[nblobs] = wp.static(7 * r + c)
                nblobs += 1
    area = vec_small_i()
    for p in range(w * w):
        if lab[p] >= 0:
            rt = lab[p]
            while lab[rt] != rt:
                rt = lab[rt]
            lab[p] = rt
            area[rt] = area[rt] + 1
    # choose_blob
    ma = wp.float64(-1.0e300)
    mi = wp.float64(-1.0e300)
    md = wp.float64(-1.0e300)
    for k in range(nblobs):
        p = roots[k]
        dist = peak_distance(p, w, lx, ly)
        if dist <= radius:
            ma = wp.max(ma, wp.float64(area[p]))
            mi = wp.max(mi, win[p] - bg)
            md = wp.max(md, dist)
    chosen = int(-1)
    best_score = wp.float64(-1.0e300)
    for k in range(nblobs):
        p = roots[k]
        dist = peak_distance(p, w, lx, ly)
        if dist <= radius:
            score = eq1_score(wp.float64(area[p]), win[p] - bg, dist, ma, mi, md, wa, wi, wd)
            if score > best_score:
                best_score = score
                chosen = p
    out_int[i, 0] = chosen
    out_int[i, 1] = nblobs
    out_int[i, 2] = 0
    out_float[i, 0] = bg
    out_float[i, 1] = wp.float64(0.0)
    out_float[i, 2] = wp.float64(0.0)
    if chosen >= 0:
        # count_saturated
        nsat = int(0)
        if sat < wp.float64(1.0e300):
            for p in range(w * w):
                if lab[p] == chosen and win[p] >= sat:
                    nsat += 1
        out_int[i, 2] = nsat
        out_float[i, 1] = win[chosen] - bg
        out_float[i, 2] = peak_distance(chosen, w, lx, ly)
    # cut_dot_map / cut_cross: a pixel is kept where it is the blob's, or background with a blob neighbour
    rr = chosen // w
    rc = chosen % w
    cw = 2 * hc + 1
    count = 5
    if full_maps != 0:
        count = cw * cw
    for j in range(count):
        # map row a, column b: the whole map, or the cross (peak, left, right, upper, lower; no division)
        a = hc
        b = hc
        if full_maps != 0:
            a = j // cw
            b = j % cw
        else:
            off = cross_offset(j)
            a = hc + off[0]
            b = hc + off[1]
        qr = rr + a - hc
        qc = rc + b - hc
        val = wp.float64(0.0)
        if chosen >= 0 and qr >= 0 and qr < w and qc >= 0 and qc < w:
            q = qr * w + qc
            l = lab[q]
            keep = l == chosen
            if l < 0:
                for dy in range(-1, 2):
                    for dx in range(-1, 2):
                        tr = qr + dy
                        tc = qc + dx
                        if tr >= 0 and tr < w and tc >= 0 and tc < w:
                            if lab[tr * w + tc] == chosen:
                                keep = True
            if keep:
                val = win[q] - bg
        if full_maps == 0:
            cross[i, j] = val
        else:
            dotmap[i, a, b] = val


@wp.func
def measure_window(
    image: wp.array2d(dtype=wp.float64),
    fill: wp.float64,
    ox: int,
    oy: int,
    lx: wp.float64,
    ly: wp.float64,
    half: int,
    hc: int,
    radius: wp.float64,
    frac: wp.float64,
    floor: wp.float64,
    wa: wp.float64,
    wi: wp.float64,
    wd: wp.float64,
    use_min: int,
    sat: wp.float64,
    win: wp.array2d(dtype=wp.float64),
    ring: wp.array2d(dtype=wp.float64),
    network: wp.array2d(dtype=wp.int32),
    lab: wp.array2d(dtype=wp.int32),
    area: wp.array2d(dtype=wp.int32),
    roots: wp.array2d(dtype=wp.int32),
    i: int,
    full_maps: int,
    out_int: wp.array2d(dtype=wp.int32),
    out_float: wp.array2d(dtype=wp.float64),
    dotmap: wp.array3d(dtype=wp.float64),
    cross: wp.array2d(dtype=wp.float64),
):
    """Segment the window of dot ``i`` (origin ``ox, oy``, prediction ``lx, ly`` in it), choose its blob
    with Eq. 1 and cut out its dot map; without ``full_maps`` only the map's centre cross, into ``cross``
    (``cut_cross``). Results in row ``i`` of ``out_int``, ``out_float``, ``dotmap`` or ``cross``.

    ``win``, ``ring``, ``lab``, ``area`` and ``roots`` are scratch rows: thread i uses row ``i % rows`` (one row is
    enough where threads run one after another, as on the CPU).
    """
    w = 2 * half + 1
    if w == SMALL_W:
        measure_small_window(
            image, fill, ox, oy, lx, ly, hc, radius, frac, floor, wa, wi, wd, use_min, sat, i, full_maps,
            out_int, out_float, dotmap, cross,
        )  # fmt: skip
        return
    s = i % win.shape[0]
    mm = load_window(image, fill, ox, oy, w, s, win)
    bg = mm[0]
    if use_min == 0:
        bg = edge_median(win, s, w, ring, network)
    thr = bg + wp.max(frac * (mm[1] - bg), floor)
    nblobs = segment_window(win, s, w, thr, lab, area, roots)
    chosen = choose_blob(win, area, roots, nblobs, s, w, bg, lx, ly, radius, wa, wi, wd)
    out_int[i, 0] = chosen
    out_int[i, 1] = nblobs
    out_int[i, 2] = 0
    out_float[i, 0] = bg
    out_float[i, 1] = wp.float64(0.0)
    out_float[i, 2] = wp.float64(0.0)
    if chosen >= 0:
        out_int[i, 2] = count_saturated(win, lab, s, w, chosen, sat)
        out_float[i, 1] = win[s, chosen] - bg
        out_float[i, 2] = peak_distance(chosen, w, lx, ly)
    if full_maps != 0:
        cut_dot_map(win, lab, s, w, chosen, bg, hc, i, 1, dotmap)
    else:
        cut_cross(win, lab, s, w, chosen, bg, i, cross)


@wp.kernel
def measure_windows_kernel(
    image: wp.array2d(dtype=wp.float64),
    fill: wp.float64,
    origin: wp.array2d(dtype=wp.int32),
    local: wp.array2d(dtype=wp.float64),
    half: int,
    hc: int,
    radius: wp.float64,
    frac: wp.float64,
    floor: wp.float64,
    wa: wp.float64,
    wi: wp.float64,
    wd: wp.float64,
    use_min: int,
    sat: wp.float64,
    win: wp.array2d(dtype=wp.float64),
    ring: wp.array2d(dtype=wp.float64),
    network: wp.array2d(dtype=wp.int32),
    lab: wp.array2d(dtype=wp.int32),
    area: wp.array2d(dtype=wp.int32),
    roots: wp.array2d(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    full_maps: int,
    out_int: wp.array2d(dtype=wp.int32),
    out_float: wp.array2d(dtype=wp.float64),
    dotmap: wp.array3d(dtype=wp.float64),
    cross: wp.array2d(dtype=wp.float64),
):
    """``measure_window`` of dot ``i = order[tid]`` (``order``: the windows in the order of their pixels in
    memory, so that neighbouring threads read neighbouring pixels)."""
    i = order[wp.tid()]
    measure_window(
        image, fill, origin[i, 0], origin[i, 1], local[i, 0], local[i, 1], half, hc, radius, frac, floor,
        wa, wi, wd, use_min, sat, win, ring, network, lab, area, roots, i, full_maps, out_int, out_float,
        dotmap, cross,
    )  # fmt: skip


# --- the pixel-integrated dot model and its joint fit ---------------------------------------------


@wp.func
def erf_from_gauss(x: wp.float64, g: wp.float64) -> wp.float64:
    """``erf(x)`` given ``g = exp(-x^2)``: Abramowitz and Stegun 7.1.26 (absolute error below 1.5e-7)."""
    t = wp.float64(1.0) / (wp.float64(1.0) + wp.float64(0.3275911) * wp.abs(x))
    poly = wp.float64(1.061405429) * t - wp.float64(1.453152027)
    poly = poly * t + wp.float64(1.421413741)
    poly = poly * t - wp.float64(0.284496736)
    poly = poly * t + wp.float64(0.254829592)
    e = wp.float64(1.0) - poly * t * g
    if x < wp.float64(0.0):
        return -e
    return e


@wp.func
def profile_start(first: int, c: wp.float64, inv: wp.float64):
    """Standardised first edge ``z0 = (first - 1/2 - c) / s`` of a 1-D pixel profile (``inv = 1 / s``),
    ``g0 = exp(-z0^2 / 2)``, ``erf(z0 / sqrt 2)``, the ratio ``exp(-z0 h - h^2 / 2)`` of ``g`` at the
    next edge to ``g0`` (``h = 1 / s``) and whether every edge takes its own exponential instead."""
    z0 = (wp.float64(first) - wp.float64(0.5) - c) * inv
    g0 = wp.exp(wp.float64(-0.5) * z0 * z0)
    e0 = erf_from_gauss(z0 * wp.float64(0.7071067811865476), g0)
    # exp(-z^2 / 2) at the next edge is g times exp(-z h - h^2 / 2), a ratio that itself changes by
    # exp(-h^2) per edge: two exponentials per axis and one per dot, unless the first ratio would
    # overflow or g underflow (very narrow dots on a wide stamp), where every edge takes its own.
    direct = z0 < wp.float64(-20.0) or z0 * inv < wp.float64(-200.0)
    ratio = wp.exp(-z0 * inv - wp.float64(0.5) * inv * inv)
    return z0, g0, e0, ratio, direct


@wp.func
def profile_pixel(
    z0: wp.float64,
    g0: wp.float64,
    e0: wp.float64,
    ratio: wp.float64,
    direct: bool,
    inv: wp.float64,
    step: wp.float64,
    scale: wp.float64,
):
    """One pixel of a 1-D profile (``profile_start``'s recurrence): from the pixel's first edge (``z0``,
    ``g0``, ``erf``, the ratio of ``g`` to the next edge) its next edge's four values, then its
    ``p``, ``dp/dc`` and ``dp/ds`` (``inv = 1 / s``, ``step = exp(-inv^2)``, ``scale = sqrt(pi / 2) s``)."""
    z1 = z0 + inv
    g1 = g0 * ratio
    if direct:
        g1 = wp.exp(wp.float64(-0.5) * z1 * z1)
    e1 = erf_from_gauss(z1 * wp.float64(0.7071067811865476), g1)
    p = scale * (e1 - e0)
    return z1, g1, e1, ratio * step, p, g0 - g1, z0 * g0 - z1 * g1 + p * inv


@wp.func
def dot_profiles(params: wp.array2d(dtype=wp.float64), i: int, half: int, prof: wp.array3d(dtype=wp.float64)):
    """Both axes' pixel profiles of dot i on its ``2 half + 1`` stamp centred on the nearest pixel.

    Rows 0-2 of ``prof[i]``: the x profile of a unit-peak Gaussian and its c- and s-derivatives,
    ``p_k = sqrt(pi / 2) s [erf(z / sqrt 2)]``, ``dp/dc = [-exp(-z^2 / 2)]``,
    ``dp/ds = [-z exp(-z^2 / 2)] + p / s`` over the pixel's standardised edges ``z = (k -+ 1/2 - c) / s``;
    rows 3-5: the same along y. Both axes in one loop (they share ``s``).
    """
    n = 2 * half + 1
    s = params[i, 3]
    inv = wp.float64(1.0) / s
    scale = wp.float64(1.2533141373155003) * s  # sqrt(pi / 2) s
    step = wp.exp(-inv * inv)
    zx, gx, ex, rx, dx = profile_start(int(wp.rint(params[i, 0])) - half, params[i, 0], inv)
    zy, gy, ey, ry, dy = profile_start(int(wp.rint(params[i, 1])) - half, params[i, 1], inv)
    k = int(0)
    while k < n:
        zx, gx, ex, rx, p, dpdc, dpds = profile_pixel(zx, gx, ex, rx, dx, inv, step, scale)
        prof[i, 0, k] = p
        prof[i, 1, k] = dpdc
        prof[i, 2, k] = dpds
        zy, gy, ey, ry, p, dpdc, dpds = profile_pixel(zy, gy, ey, ry, dy, inv, step, scale)
        prof[i, 3, k] = p
        prof[i, 4, k] = dpdc
        prof[i, 5, k] = dpds
        k += 1


@wp.func
def common_shape(params: wp.array2d(dtype=wp.float64), partner: wp.array(dtype=wp.int32), i: int) -> wp.vec2d:
    """(I0, sigma) of dot i shared with its partner in the other image: the mean of both (own if none)."""
    j = partner[i]
    if j < 0:
        return wp.vec2d(params[i, 2], params[i, 3])
    half = wp.float64(0.5)
    return wp.vec2d(half * (params[i, 2] + params[j, 2]), half * (params[i, 3] + params[j, 3]))


@wp.func
def to_fixed(value: wp.float64, scale: wp.float64) -> wp.int64:
    """``value`` in fixed point: the nearest integer to ``value * scale``."""
    return wp.int64(wp.floor(value * scale + wp.float64(0.5)))


@wp.kernel
def render_dots_kernel(
    params: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    half: int,
    common: int,
    profiles: int,
    prof: wp.array3d(dtype=wp.float64),
    scale: wp.float64,
    height: int,
    width: int,
    models: wp.array(dtype=wp.int64),
):
    """Add dot i's model (no background) on its ``2 half + 1`` stamp into its image's model images.

    ``models``: the model images ``[2, frames, height, width]`` flat. ``models[0, f]``: ``I0 p_x p_y``;
    if ``common``, ``models[1, f]``: the same at the pair's common shape, linearised in sigma. ``prof``
    holds the dot's profiles on its stamp (``dot_profiles``); if ``profiles`` (the first render of a fit),
    they are computed here first, from ``params``.
    The images are fixed point (units of ``1 / scale``) added with integer atomics, so overlapping
    dots sum to the same bits in any thread order: CUDA fits are reproducible run to run.
    """
    i = wp.tid()
    if profiles != 0:
        dot_profiles(params, i, half, prof)
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    # the part of the stamp inside the image, rows r0 <= r < r1 and columns c0 <= c < c1
    c0 = wp.max(-ox, 0)
    c1 = wp.min(n, width - ox)
    r0 = wp.max(-oy, 0)
    r1 = wp.min(n, height - oy)
    base = (frame[i] * height + oy) * width + ox  # flat index of the stamp's pixel (0, 0)
    a = params[i, 2]
    if common == 0:
        r = int(r0)
        while r < r1:
            apy = a * prof[i, 3, r]
            at = base + r * width
            c = int(c0)
            while c < c1:
                wp.atomic_add(models, at + c, to_fixed(apy * prof[i, 0, c], scale))
                c += 1
            r += 1
    else:  # both images in one pass over the stamp; the partner's shape is a scattered read
        cs = common_shape(params, partner, i)
        ds = cs[1] - params[i, 3]
        layer = models.shape[0] // 2
        r = int(r0)
        while r < r1:
            py = prof[i, 3, r]
            spy = prof[i, 5, r]
            apy = a * py
            at = base + r * width
            c = int(c0)
            while c < c1:
                px = prof[i, 0, c]
                wp.atomic_add(models, at + c, to_fixed(apy * px, scale))
                shared = cs[0] * (py * px + ds * (spy * px + py * prof[i, 2, c]))
                wp.atomic_add(models, at + layer + c, to_fixed(shared, scale))
                c += 1
            r += 1


@wp.func
def normal_matrix(
    image: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    f: int,
    params: wp.array2d(dtype=wp.float64),
    i: int,
    half: int,
    skip: int,
    sat: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
) -> NormalEquations:
    """Dot i's normal equations: ``J^T J`` in blocks, ``J^T r`` and ``J^T r'`` (see ``NormalEquations``).

    The window is the central ``2 half + 1`` part of the stamp whose profiles ``prof`` holds (``skip``
    pixels in from its edge). ``r = image - models[0] - b``: the model image holds dot i itself, so
    this is the image less the other dots, minus dot i's model and background; ``r'`` is the same
    against the common-shape model image ``models[1]`` (both fixed point: ``inv_scale`` per unit).
    ``models`` holds the model images ``[2, frames, height, width]`` flat (``image`` is ``height x width``).
    ``J`` is the derivative of the model with
    respect to x, y, I0, sigma and the background. Pixels at or above ``sat`` (saturated: they only
    bound the intensity) take no part.
    """
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    a = params[i, 2]
    b = params[i, 4]
    zero = wp.float64(0.0)
    s00 = zero
    s01 = zero
    s02 = zero
    s03 = zero
    s04 = zero
    s11 = zero
    s12 = zero
    s13 = zero
    s14 = zero
    s22 = zero
    s23 = zero
    s24 = zero
    s33 = zero
    s34 = zero
    s44 = zero
    g0 = zero
    g1 = zero
    g2 = zero
    g3 = zero
    g4 = zero
    h0 = zero
    h1 = zero
    h4 = zero
    for rr in range(n):
        row = oy + rr
        if row >= 0 and row < image.shape[0]:
            py = prof[i, 3, rr + skip]
            dpy = a * prof[i, 4, rr + skip]
            spy = a * prof[i, 5, rr + skip]
            apy = a * py
            for cc in range(n):
                col = ox + cc
                if col >= 0 and col < image.shape[1] and image[row, col] < sat:
                    px = prof[i, 0, cc + skip]
                    v = image[row, col] - b
                    at = (f * image.shape[0] + row) * image.shape[1] + col
                    res = v - wp.float64(models[at]) * inv_scale
                    res2 = v - wp.float64(models[at + models.shape[0] // 2]) * inv_scale
                    j0 = apy * prof[i, 1, cc + skip]
                    j1 = dpy * px
                    j2 = py * px
                    j3 = spy * px + apy * prof[i, 2, cc + skip]
                    s00 += j0 * j0
                    s01 += j0 * j1
                    s02 += j0 * j2
                    s03 += j0 * j3
                    s04 += j0
                    s11 += j1 * j1
                    s12 += j1 * j2
                    s13 += j1 * j3
                    s14 += j1
                    s22 += j2 * j2
                    s23 += j2 * j3
                    s24 += j2
                    s33 += j3 * j3
                    s34 += j3
                    s44 += wp.float64(1.0)
                    g0 += j0 * res
                    g1 += j1 * res
                    g2 += j2 * res
                    g3 += j3 * res
                    g4 += res
                    h0 += j0 * res2
                    h1 += j1 * res2
                    h4 += res2
    eps = wp.float64(1.0e-12)
    ne = NormalEquations()
    ne.p = wp.mat33d(s00 + eps, s01, s04, s01, s11 + eps, s14, s04, s14, s44 + eps)
    ne.q = mat32d(s02, s03, s12, s13, s24, s34)
    ne.r = wp.mat22d(s22 + eps, s23, s23, s33 + eps)
    ne.g1 = wp.vec3d(g0, g1, g4)
    ne.g2 = wp.vec2d(g2, g3)
    ne.h1 = wp.vec3d(h0, h1, h4)
    return ne


@wp.func
def window_is_whole(
    image: wp.array2d(dtype=wp.float64), params: wp.array2d(dtype=wp.float64), i: int, half: int, sat: wp.float64
) -> bool:
    """True where dot i's ``2 half + 1`` window lies inside the image and holds no pixel at or above ``sat``."""
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    if ox < 0 or oy < 0 or ox + n > image.shape[1] or oy + n > image.shape[0]:
        return False
    if sat < wp.float64(1.0e300):
        for rr in range(n):
            for cc in range(n):
                if image[oy + rr, ox + cc] >= sat:
                    return False
    return True


@wp.func
def profile_moments(prof: wp.array3d(dtype=wp.float64), i: int, axis0: int, n: int, skip: int):
    """Sums over one axis of dot ``i``'s profile terms ``p = prof[i, axis0]``, ``d = prof[i, axis0 + 1]``,
    ``s = prof[i, axis0 + 2]`` (entries ``skip ... skip + n - 1``): pp, dd, ss, pd, ps, ds, p, d, s."""
    zero = wp.float64(0.0)
    pp = zero
    dd = zero
    ss = zero
    pd = zero
    ps = zero
    ds = zero
    sp = zero
    sd = zero
    s_ = zero
    k = int(skip)
    while k < skip + n:
        p = prof[i, axis0, k]
        d = prof[i, axis0 + 1, k]
        sg = prof[i, axis0 + 2, k]
        pp += p * p
        dd += d * d
        ss += sg * sg
        pd += p * d
        ps += p * sg
        ds += d * sg
        sp += p
        sd += d
        s_ += sg
        k += 1
    return pp, dd, ss, pd, ps, ds, sp, sd, s_


@wp.func
def normal_matrix_separable(
    image: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    f: int,
    params: wp.array2d(dtype=wp.float64),
    i: int,
    half: int,
    skip: int,
    common: int,
    prof: wp.array3d(dtype=wp.float64),
) -> NormalEquations:
    """``normal_matrix`` for a whole window (``window_is_whole``): every Jacobian column is a product of
    an x and a y profile term, so ``J^T J`` comes from 1-D sums over the rows and columns, and ``J^T r``
    from one pass that sums each row against the x terms first. ``J^T r'`` only if ``common``."""
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    a = params[i, 2]
    b = params[i, 4]
    zero = wp.float64(0.0)
    g0 = zero
    g1 = zero
    g2 = zero
    g3 = zero
    g4 = zero
    h0 = zero
    h1 = zero
    h4 = zero
    width = image.shape[1]
    layer = models.shape[0] // 2
    at = (f * image.shape[0] + oy) * width + ox  # flat index of the window's first pixel in models
    rr = int(0)
    while rr < n:
        row = oy + rr
        r0 = zero
        r1 = zero
        r2 = zero
        r3 = zero
        t0 = zero
        t1 = zero
        t3 = zero
        cc = int(0)
        while cc < n:
            col = ox + cc
            k = cc + skip
            res = image[row, col] - b - wp.float64(models[at + cc]) * inv_scale
            r0 += prof[i, 1, k] * res
            r1 += prof[i, 0, k] * res
            r2 += prof[i, 2, k] * res
            r3 += res
            cc += 1
        if common != 0:
            cc = int(0)
            while cc < n:
                col = ox + cc
                k = cc + skip
                res2 = image[row, col] - b - wp.float64(models[at + layer + cc]) * inv_scale
                t0 += prof[i, 1, k] * res2
                t1 += prof[i, 0, k] * res2
                t3 += res2
                cc += 1
        k = rr + skip
        py = prof[i, 3, k]
        dy = prof[i, 4, k]
        sy = prof[i, 5, k]
        g0 += py * r0
        g1 += dy * r1
        g2 += py * r1
        g3 += sy * r1 + py * r2
        g4 += r3
        h0 += py * t0
        h1 += dy * t1
        h4 += t3
        at += width
        rr += 1
    # 1-D sums of the x terms (p: profile, d: its c-derivative, s: its sigma-derivative) and of the y terms
    # (after the pixel loop: fewer values live across it)
    xpp, xdd, xss, xpd, xps, xds, xp, xd, xs = profile_moments(prof, i, 0, n, skip)
    ypp, ydd, yss, ypd, yps, yds, yp, yd, ys = profile_moments(prof, i, 3, n, skip)
    a2 = a * a
    eps = wp.float64(1.0e-12)
    s00 = a2 * ypp * xdd
    s01 = a2 * ypd * xpd
    s02 = a * ypp * xpd
    s03 = a2 * (yps * xpd + ypp * xds)
    s04 = a * yp * xd
    s11 = a2 * ydd * xpp
    s12 = a * ypd * xpp
    s13 = a2 * (yds * xpp + ypd * xps)
    s14 = a * yd * xp
    s22 = ypp * xpp
    s23 = a * (yps * xpp + ypp * xps)
    s24 = yp * xp
    s33 = a2 * (yss * xpp + wp.float64(2.0) * yps * xps + ypp * xss)
    s34 = a * (ys * xp + yp * xs)
    s44 = wp.float64(n * n)
    ne = NormalEquations()
    ne.p = wp.mat33d(s00 + eps, s01, s04, s01, s11 + eps, s14, s04, s14, s44 + eps)
    ne.q = mat32d(s02, s03, s12, s13, s24, s34)
    ne.r = wp.mat22d(s22 + eps, s23, s23, s33 + eps)
    ne.g1 = wp.vec3d(a * g0, a * g1, g4)
    ne.g2 = wp.vec2d(g2, a * g3)
    ne.h1 = wp.vec3d(a * h0, a * h1, h4)
    return ne


@wp.func
def limited(step: vec5d) -> vec5d:
    """The step scaled so that the position moves at most half a pixel per axis."""
    big = wp.max(wp.abs(step[0]), wp.abs(step[1]))
    if big > wp.float64(0.5):
        return step * (wp.float64(0.5) / big)
    return step


@wp.func
def all_finite(q: vec5d) -> bool:
    """Whether every entry is finite: ``|x| <= DBL_MAX`` fails for NaN and infinity alike (compares inline,
    where ``wp.isfinite`` on the CPU is a call per entry)."""
    big = wp.float64(1.7976931348623157e308)
    xy = wp.abs(q[0]) <= big and wp.abs(q[1]) <= big
    return xy and wp.abs(q[2]) <= big and wp.abs(q[3]) <= big and wp.abs(q[4]) <= big


@wp.func
def fit_dot_step(
    image: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    params: wp.array2d(dtype=wp.float64),
    start: wp.array2d(dtype=wp.float64),
    f: int,
    i: int,
    has_partner: int,
    sat: wp.float64,
    half: int,
    render_half: int,
    common: int,
    max_move: wp.float64,
    smin: wp.float64,
    smax: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
    out: wp.array2d(dtype=wp.float64),
    ok: wp.array(dtype=wp.int32),
    shared_xy: wp.array2d(dtype=wp.float64),
):
    """One Gauss-Newton step of dot i (in model frame ``f``) against its image less the other dots (see
    ``fit_dots_numpy``).

    ``models``: the fixed-point model images ``[2, frames, height, width]``, flat.

    ``prof`` holds the dot's profiles at ``params`` on its rendering stamp; they are replaced by those
    at the new parameters ``out``, except in the last step (``common``), after which none are needed.
    If ``common``, ``shared_xy`` gets the position of the step for position and background against
    the common-shape model image (NaN without a partner; all NaN without ``common``, when that image
    is not drawn).
    """
    p = vec5d(params[i, 0], params[i, 1], params[i, 2], params[i, 3], params[i, 4])
    skip = render_half - half
    ne = NormalEquations()
    if window_is_whole(image, params, i, half, sat):
        ne = normal_matrix_separable(image, models, inv_scale, f, params, i, half, skip, common, prof)
    else:
        ne = normal_matrix(image, models, inv_scale, f, params, i, half, skip, sat, prof)
    # Block elimination: the shape step from the Schur complement, then position and background.
    pinv = wp.inverse(ne.p)
    pq = pinv * ne.q
    schur = ne.r - wp.transpose(ne.q) * pq
    d2 = wp.inverse(schur) * (ne.g2 - wp.transpose(pq) * ne.g1)
    d1 = pinv * (ne.g1 - ne.q * d2)
    step = vec5d(d1[0], d1[1], d2[0], d2[1], d1[2])
    q = p + limited(step)
    good = all_finite(q)
    good = good and wp.abs(q[0] - start[i, 0]) <= max_move and wp.abs(q[1] - start[i, 1]) <= max_move
    good = good and q[2] > wp.float64(0.0) and q[3] >= smin and q[3] <= smax
    if not good:
        q = p
    hs = pinv * ne.h1
    qs = limited(vec5d(hs[0], hs[1], wp.float64(0.0), wp.float64(0.0), hs[2]))
    nan = wp.float64(wp.nan)
    shared_xy[i, 0] = nan
    shared_xy[i, 1] = nan
    if common != 0 and has_partner != 0:
        shared_xy[i, 0] = p[0] + qs[0]
        shared_xy[i, 1] = p[1] + qs[1]
    for k in range(5):
        out[i, k] = q[k]
    ok[i] = int(good)
    if common == 0:  # not the last step: the next one needs the profiles at the new parameters
        dot_profiles(out, i, render_half, prof)


@wp.kernel
def fit_dot_step_kernel(
    image0: wp.array2d(dtype=wp.float64),
    image1: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    params: wp.array2d(dtype=wp.float64),
    start: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    saturation: wp.array(dtype=wp.float64),
    half: int,
    render_half: int,
    common: int,
    max_move: wp.float64,
    smin: wp.float64,
    smax: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
    out: wp.array2d(dtype=wp.float64),
    ok: wp.array(dtype=wp.int32),
    shared_xy: wp.array2d(dtype=wp.float64),
):
    """``fit_dot_step`` of dot i; ``image0``, ``image1``: the images of frames 0 and 1 (the same array
    twice for a single image)."""
    i = wp.tid()
    f = frame[i]
    has_partner = int(partner[i] >= 0)
    if f == 0:
        fit_dot_step(
            image0, models, inv_scale, params, start, f, i, has_partner, saturation[f], half, render_half,
            common, max_move, smin, smax, prof, out, ok, shared_xy,
        )  # fmt: skip
    else:
        fit_dot_step(
            image1, models, inv_scale, params, start, f, i, has_partner, saturation[f], half, render_half,
            common, max_move, smin, smax, prof, out, ok, shared_xy,
        )  # fmt: skip


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
    of the neighbours' vectors from the fit (see ``tracking.neighbours.neighbour_fit_numpy``);
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


# --- the predictor's nearest-pixel window deformation ------------------------------------------------


@wp.func
def field_at_row(field: wp.array2d(dtype=wp.float64), iy: int, ty: wp.float64, ix: int) -> wp.float64:
    """A tile field's column ``ix`` of centres interpolated linearly to a row in cell ``iy`` at fraction
    ``ty`` (beyond [0, 1]: linear extrapolation): the first half of a separable bilinear interpolation."""
    iy1 = wp.min(iy + 1, field.shape[0] - 1)
    return (wp.float64(1.0) - ty) * field[iy, ix] + ty * field[iy1, ix]


@wp.func
def cell_ends(
    field_u: wp.array2d(dtype=wp.float64), field_v: wp.array2d(dtype=wp.float64), iy: int, ty: wp.float64, ix: int
) -> wp.vec4d:
    """(u, u, v, v) of the tile fields at centre columns ``ix`` and ``ix + 1`` (the last column at the
    edge), each interpolated to a row in cell ``iy`` at fraction ``ty`` (:func:`field_at_row`)."""
    ix1 = wp.min(ix + 1, field_u.shape[1] - 1)
    return wp.vec4d(
        field_at_row(field_u, iy, ty, ix),
        field_at_row(field_u, iy, ty, ix1),
        field_at_row(field_v, iy, ty, ix),
        field_at_row(field_v, iy, ty, ix1),
    )


@wp.func
def rounds_to(a: wp.float64, b: wp.float64, s: int) -> int:
    """1 where ``a`` and ``b`` both lie more than 1e-6 inside the rounding interval of the integer ``s``
    (so does then anything between them, give or take rounding errors far smaller), else 0."""
    lo = wp.float64(s) - wp.float64(0.5) + wp.float64(1e-6)
    hi = wp.float64(s) + wp.float64(0.5) - wp.float64(1e-6)
    if a > lo and a < hi and b > lo and b < hi:
        return 1
    return 0


@wp.kernel
def deform_nearest_kernel(
    image: wp.array(dtype=wp.float64),
    valid: wp.array(dtype=wp.float32),
    use_valid: int,
    h: int,
    w: int,
    field_u: wp.array2d(dtype=wp.float64),
    field_v: wp.array2d(dtype=wp.float64),
    row_cell: wp.array(dtype=wp.int32),
    row_frac: wp.array(dtype=wp.float64),
    col_cell: wp.array(dtype=wp.int32),
    col_frac: wp.array(dtype=wp.float64),
    y0: int,
    x0: int,
    size: int,
    tiles: int,
    tile_shift: wp.array2d(dtype=wp.int32),
    copy_whole: int,
    out: wp.array(dtype=wp.float32),
    out_valid: wp.array(dtype=wp.float32),
    tile_sums: wp.array3d(dtype=wp.int32),
):
    """One row of ``tiles`` consecutive ``size`` x ``size`` tiles (those from tile column ``t * tiles``;
    1 on a GPU, a whole row of tiles on the CPU) of the block of tiles starting at (``y0``, ``x0``):
    the ``h`` x ``w`` ``image`` (flattened, row by row) moved back by the tile field rounded to whole
    pixels. The tiles' pixel (r, c) (block coordinates) takes the pixel at (y0 + r + rint(v),
    x0 + c + rint(u)) (the edge pixel beyond the image) as float32; ``out_valid`` 1 where that lies
    inside the image (times ``valid``, flattened like ``image``, there if ``use_valid``). ``out`` and
    ``out_valid`` hold the tiles one after the other, row by row of tiles, each ``size * size`` pixels
    row by row. ``tile_sums[0|1, tile row, tile column]`` sum the rounded shifts u and v over the
    tile's pixels and ``tile_sums[2, ...]`` counts its pixels whose weight is not 1. The field is
    interpolated bilinearly, each row and column given by its cell of tile centres and fraction in it:
    first along the rows at the two centre columns around the pixel, then along the row.
    ``tile_shift[tile] = (u, v, 1)`` says that every pixel of the tile (row by row of tiles) rounds to
    the shifts (u, v) and takes its pixel from inside the image (``(0, 0, 0)``: not known): such a tile
    is copied row by row without the interpolation (the same result) if ``copy_whole``, else left to
    the caller (its pixels and weights are not written nor its weights counted; its shift sums are). A row of
    another tile whose ends lie in one cell of centres, round alike there (:func:`rounds_to`) and take
    their pixels from inside the image is copied alike."""
    r, t = wp.tid()
    nx = tile_sums.shape[2]
    row = y0 + r
    iy = row_cell[row]
    ty = row_frac[row]
    tile_row = r / size
    one = wp.float64(1.0)
    cell = int(-1)
    ends = wp.vec4d()  # u and v at the row's two centre columns of the current cell (cell_ends)
    for k in range(t * tiles, wp.min(t * tiles + tiles, nx)):
        sum_u = int(0)
        sum_v = int(0)
        n_part = int(0)
        # the tile's row r - tile_row * size in the tile-major output
        tile = tile_row * nx + k
        at = (tile * size + r - tile_row * size) * size
        col0 = x0 + k * size
        # one shift (su1, sv1) for the tile's whole row, from inside the image: known for the tile
        # (tile_shift: 1), else found from the row's ends where they lie in one cell of centres (the
        # field is linear along the row there: 2)
        one_shift = tile_shift[tile, 2]
        su1 = tile_shift[tile, 0]
        sv1 = tile_shift[tile, 1]
        if one_shift == 0:
            ix = col_cell[col0]
            if ix == col_cell[col0 + size - 1]:
                if ix != cell:
                    cell = ix
                    ends = cell_ends(field_u, field_v, iy, ty, ix)
                ta = col_frac[col0]
                tb = col_frac[col0 + size - 1]
                ua = (one - ta) * ends[0] + ta * ends[1]
                va = (one - ta) * ends[2] + ta * ends[3]
                su1 = int(wp.rint(ua))
                sv1 = int(wp.rint(va))
                ub = (one - tb) * ends[0] + tb * ends[1]
                vb = (one - tb) * ends[2] + tb * ends[3]
                same = rounds_to(ua, ub, su1) * rounds_to(va, vb, sv1)
                rv = row + sv1
                if same != 0 and rv >= 0 and rv < h and col0 + su1 >= 0 and col0 + su1 + size <= w:
                    one_shift = 2
        pixels = size  # those moved one by one below
        if one_shift != 0:
            pixels = 0
            # one shift for the whole row, all of it from inside the image: a copy (but of the tiles
            # that the caller copies)
            sum_u = su1 * size
            sum_v = sv1 * size
            src0 = (row + sv1) * w + col0 + su1
            copied = size
            if one_shift == 1 and copy_whole == 0:
                copied = 0
            for c in range(copied):
                v = wp.float32(1.0)
                if use_valid != 0:
                    v = valid[src0 + c]
                    if v != wp.float32(1.0):
                        n_part += 1
                out[at + c] = wp.float32(image[src0 + c])
                out_valid[at + c] = v
        for c in range(pixels):
            col = col0 + c
            ix = col_cell[col]
            if ix != cell:
                cell = ix
                ends = cell_ends(field_u, field_v, iy, ty, ix)
            tx = col_frac[col]
            su = int(wp.rint((one - tx) * ends[0] + tx * ends[1]))
            sv = int(wp.rint((one - tx) * ends[2] + tx * ends[3]))
            sum_u += su
            sum_v += sv
            ry = row + sv
            rx = col + su
            src = wp.clamp(ry, 0, h - 1) * w + wp.clamp(rx, 0, w - 1)
            v = wp.float32(0.0)
            if ry >= 0 and ry < h and rx >= 0 and rx < w:
                v = wp.float32(1.0)
                if use_valid != 0:
                    v = valid[src]
            if v != wp.float32(1.0):
                n_part += 1
            out[at + c] = wp.float32(image[src])
            out_valid[at + c] = v
        wp.atomic_add(tile_sums, 0, tile_row, k, sum_u)
        wp.atomic_add(tile_sums, 1, tile_row, k, sum_v)
        if n_part > 0:
            wp.atomic_add(tile_sums, 2, tile_row, k, n_part)
