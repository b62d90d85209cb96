# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of identification: one thread measures the window around one predicted dot.

Kernels and ``@wp.func`` steps only; one kernel, :func:`measure_stack`, measures the windows of one pair
(host code :mod:`tracking.windows`, a stack of one) and of a stack of pairs (``tracking.identify.
StackIdentification``, whose rounds of claims are :mod:`tracking.claim_kernels`). The NumPy reference
``tracking.reference.measure_windows_numpy`` defines what the kernels compute. Windows are held flat, pixel ``p`` of a
``w x w`` window at row ``p // w``, column ``p % w``. The last section takes the predictor's hand-over:
the positions to search from and the dots inside each pair's image.
"""

import warp as wp

from synthbos.device import quiet_warp

from .settings import SMALL_WINDOW
from .sorting import median_network

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile


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
def load_small_window(image: wp.array2d(dtype=wp.float64), fill: wp.float64, ox: int, oy: int) -> vec_small_f:
    """``load_window`` for the 7 x 7 window: its pixels from (``oy``, ``ox``) on, ``fill`` beyond the image."""
    w = SMALL_W
    win = vec_small_f()
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
    return win


@wp.func
def small_edge_median(win: vec_small_f) -> wp.float64:
    """``edge_median`` of the 7 x 7 window: the median of its 24 edge pixels by the unrolled network."""
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
    return (ring[11] + ring[12]) / wp.float64(2.0)


@wp.func
def choose_small_blob(
    win: vec_small_f,
    area: vec_small_i,
    roots: vec_small_i,
    nblobs: int,
    bg: wp.float64,
    lx: wp.float64,
    ly: wp.float64,
    radius: wp.float64,
    wa: wp.float64,
    wi: wp.float64,
    wd: wp.float64,
) -> int:
    """``choose_blob`` for the 7 x 7 window: the root of the blob with the best Eq. 1 score within
    ``radius`` of (``lx``, ``ly``), -1 if none."""
    w = SMALL_W
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
    return chosen


@wp.func
def cut_small_maps(
    win: vec_small_f,
    lab: vec_small_i,
    chosen: int,
    bg: wp.float64,
    hc: int,
    full_maps: int,
    i: int,
    dotmap: wp.array3d(dtype=wp.float64),
    cross: wp.array2d(dtype=wp.float64),
):
    """``cut_dot_map`` / ``cut_cross`` for the 7 x 7 window: a pixel is kept where it is the blob's, or
    background with a blob neighbour."""
    w = SMALL_W
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
    """``measure_window``'s steps for a 7 x 7 window held in local vectors: the same as
    ``load_window``, ``edge_median``, ``segment_window``, ``choose_blob``, ``count_saturated`` and
    ``cut_dot_map`` / ``cut_cross``, with the same result for finite pixels (its minimum, maximum and edge
    median are plain selects, which NaN pixels would upset)."""
    w = SMALL_W
    # load_window
    win = load_small_window(image, fill, ox, oy)
    vmin = wp.float64(1.0e300)
    vmax = wp.float64(-1.0e300)
    for r in range(SMALL_W):
        for c in range(SMALL_W):
            v = win[wp.static(7 * r + c)]
            # the minimum and maximum as plain selects (one instruction each on the CPU; finite pixels)
            vmin = wp.where(v < vmin, v, vmin)
            vmax = wp.where(v > vmax, v, vmax)
    # edge_median
    bg = vmin
    if use_min == 0:
        bg = small_edge_median(win)
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
    chosen = choose_small_blob(win, area, roots, nblobs, bg, lx, ly, radius, wa, wi, wd)
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
    # cut_dot_map / cut_cross
    cut_small_maps(win, lab, chosen, bg, hc, full_maps, i, dotmap, cross)


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
def measure_stack(
    images: wp.array3d(dtype=wp.float64),
    ids: wp.array(dtype=wp.int32),
    per_frame: int,
    fill: wp.array(dtype=wp.float64),
    floor: wp.array(dtype=wp.float64),
    sat: wp.array(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
    origin: wp.array2d(dtype=wp.int32),
    pred: wp.array(dtype=wp.vec2d),
    todo: wp.array(dtype=wp.int32),
    half: int,
    hc: int,
    radius: wp.float64,
    frac: wp.float64,
    wa: wp.float64,
    wi: wp.float64,
    wd: wp.float64,
    use_min: int,
    win: wp.array2d(dtype=wp.float64),
    ring: wp.array2d(dtype=wp.float64),
    network: wp.array2d(dtype=wp.int32),
    lab: wp.array2d(dtype=wp.int32),
    area: wp.array2d(dtype=wp.int32),
    roots: wp.array2d(dtype=wp.int32),
    dotmap: wp.array3d(dtype=wp.float64),
    out_int: wp.array2d(dtype=wp.int32),
    out_float: wp.array2d(dtype=wp.float64),
    cross: wp.array2d(dtype=wp.float64),
    full_maps: int,
):
    """``measure_window`` of dot ``ids[t]`` on its frame ``f = ids[t] // per_frame`` (``pred``: its
    prediction in image coordinates; ``fill``, ``floor``, ``sat`` per frame), results in row t (the dot
    map if ``full_maps``, else its centre cross); chosen -1 where not measured (found already, outside, or
    its frame done). One pair is a stack of one (``tracking.windows.measure_windows``); a thread order
    ``ids`` that follows the image's memory lets neighbouring threads read neighbouring pixels."""
    t = wp.tid()
    i = ids[t]
    f = i // per_frame
    out_int[t, 0] = -1
    if todo[i] == 0 or active[f] == 0:
        return
    ox = origin[i, 0]
    oy = origin[i, 1]
    p = pred[i]
    measure_window(
        images[f], fill[f], ox, oy, p[0] - wp.float64(ox), p[1] - wp.float64(oy), half, hc, radius, frac,
        floor[f], wa, wi, wd, use_min, sat[f], win, ring, network, lab, area, roots, t, full_maps, out_int, out_float,
        dotmap, cross,
    )  # fmt: skip


# --- the hand-over from the predictor: the positions to search from, the dots inside each image --------


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
