# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of dot tracking: one thread measures the window around one predicted dot position.

Kernels only; the host code that allocates and launches is :mod:`tracking.windows`, whose NumPy
reference (``measure_windows_numpy``) defines what the kernel computes.
"""

import warp as wp

wp.config.quiet = True  # no banner or module-load lines from library code
wp.config.log_level = wp.LOG_WARNING

wp.config.quiet = True


@wp.func
def ring_pixel(k: int, w: int) -> int:
    """Flat index of the k-th pixel on the edge of a w x w window (top row, bottom row, then the sides)."""
    if k < w:
        return k
    if k < 2 * w:
        return (w - 1) * w + (k - w)
    k2 = k - 2 * w
    row = 1 + k2 // 2
    if k2 % 2 == 0:
        return row * w
    return row * w + (w - 1)


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
    lab: wp.array2d(dtype=wp.int32),
    area: wp.array2d(dtype=wp.int32),
    out_int: wp.array2d(dtype=wp.int32),
    out_float: wp.array2d(dtype=wp.float64),
    dotmap: wp.array3d(dtype=wp.float64),
):
    i = wp.tid()
    w = 2 * half + 1
    ww = w * w
    nrow = image.shape[0]
    ncol = image.shape[1]
    ox = origin[i, 0]
    oy = origin[i, 1]
    vmax = wp.float64(-1.0e300)
    vmin = wp.float64(1.0e300)
    for p in range(ww):
        y = oy + p // w
        x = ox + p % w
        v = fill
        if y >= 0 and y < nrow and x >= 0 and x < ncol:
            v = image[y, x]
        win[i, p] = v
        vmax = wp.max(vmax, v)
        vmin = wp.min(vmin, v)
        area[i, p] = 0
    # Background: the median of the window's edge pixels (or the window minimum).
    bg = vmin
    if use_min == 0:
        n = 4 * (w - 1)
        for j in range(n):
            ring[i, j] = win[i, ring_pixel(j, w)]
        # Insertion sort of the edge pixels (n <= 4 (w - 1) is small), then the two middle values.
        for j in range(1, n):
            v = ring[i, j]
            k = j - 1
            while k >= 0 and ring[i, k] > v:
                ring[i, k + 1] = ring[i, k]
                k -= 1
            ring[i, k + 1] = v
        m1 = ring[i, n / 2 - 1]
        m2 = ring[i, n / 2]
        bg = (m1 + m2) / wp.float64(2.0)
    thr = bg + wp.max(frac * (vmax - bg), floor)
    # Steepest ascent: each foreground pixel points to its brightest 8-neighbour (ties: higher index).
    for p in range(ww):
        vp = win[i, p]
        if vp > thr:
            pr = p // w
            pc = p % w
            best = p
            bv = vp
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    r = pr + dy
                    c = pc + dx
                    if r >= 0 and r < w and c >= 0 and c < w:
                        q = r * w + c
                        vq = win[i, q]
                        if vq > bv or (vq == bv and q > best):
                            best = q
                            bv = vq
            lab[i, p] = best
        else:
            lab[i, p] = -1
    for p in range(ww):
        if lab[i, p] >= 0:
            r = lab[i, p]
            while lab[i, r] != r:
                r = lab[i, r]
            lab[i, p] = r
            area[i, r] = area[i, r] + 1
    lx = local[i, 0]
    ly = local[i, 1]
    ma = wp.float64(-1.0e300)
    mi = wp.float64(-1.0e300)
    md = wp.float64(-1.0e300)
    nblobs = int(0)  # a dynamic Warp variable
    for p in range(ww):
        if lab[i, p] == p:
            nblobs += 1
            ddx = wp.float64(p % w) - lx
            ddy = wp.float64(p // w) - ly
            dist = wp.sqrt(ddx * ddx + ddy * ddy)
            if dist <= radius:
                ma = wp.max(ma, wp.float64(area[i, p]))
                mi = wp.max(mi, win[i, p] - bg)
                md = wp.max(md, dist)
    # Eq. 1 of Rajendran, Bane and Vlachos (2019) over the candidate blobs; the first best wins.
    chosen = int(-1)  # a dynamic Warp variable
    best_score = wp.float64(-1.0e300)
    best_dist = wp.float64(0.0)
    for p in range(ww):
        if lab[i, p] == p:
            ddx = wp.float64(p % w) - lx
            ddy = wp.float64(p // w) - ly
            dist = wp.sqrt(ddx * ddx + ddy * ddy)
            if dist <= radius:
                ta = wp.float64(1.0)
                ti = wp.float64(1.0)
                td = wp.float64(1.0)
                if ma > wp.float64(0.0):
                    ta = wp.float64(area[i, p]) / ma
                if mi > wp.float64(0.0):
                    ti = (win[i, p] - bg) / mi
                if md > wp.float64(0.0):
                    td = wp.float64(1.0) - dist / md
                score = (wa * ta + wi * ti + wd * td) / (wa + wi + wd)
                if score > best_score:
                    best_score = score
                    chosen = p
                    best_dist = dist
    out_int[i, 0] = chosen
    out_int[i, 1] = nblobs
    out_float[i, 0] = bg
    c = 2 * hc + 1
    if chosen < 0:
        out_int[i, 2] = 0
        out_float[i, 1] = wp.float64(0.0)
        out_float[i, 2] = wp.float64(0.0)
        for a in range(c):
            for b in range(c):
                dotmap[i, a, b] = wp.float64(0.0)
        return
    out_float[i, 1] = win[i, chosen] - bg
    out_float[i, 2] = best_dist
    nsat = int(0)  # a dynamic Warp variable
    for p in range(ww):
        if lab[i, p] == chosen and win[i, p] >= sat:
            nsat += 1
    out_int[i, 2] = nsat
    # Dot map around the peak: the chosen blob and its rim, minus background; other blobs zeroed.
    rr = chosen // w
    rc = chosen % w
    for a in range(c):
        for b in range(c):
            qr = rr + a - hc
            qc = rc + b - hc
            val = wp.float64(0.0)
            if qr >= 0 and qr < w and qc >= 0 and qc < w:
                l = lab[i, qr * w + qc]
                keep = l == chosen
                if l < 0:
                    for dy in range(-1, 2):
                        for dx in range(-1, 2):
                            r = qr + dy
                            cc = qc + dx
                            if r >= 0 and r < w and cc >= 0 and cc < w:
                                if lab[i, r * w + cc] == chosen:
                                    keep = True
                if keep:
                    val = win[i, qr * w + qc] - bg
            dotmap[i, a, b] = val
