"""Warp kernels of the device-resident correlation pass (host code: :mod:`correlation.device_pass`).

Only ``@wp.func`` helpers, ``@wp.kernel``\\ s and one kernel factory (the window correlation, whose
tile shape is a compile-time constant) live here. Each kernel does one step of an iteration of
:func:`correlation.correlate_pair` on device arrays, over all pixels, windows or vectors at once:
predictor interpolation (separable spline weights), symmetric deformation with
edge weights, windowed FFT correlation (one tile per window), peak fit and significance, normalised
median test and confirmation, isolated vectors, replacement by the neighbours' median (the kernels that
loop over image lines, the B-spline prefilter and the image statistics, are in
:mod:`correlation.line_kernels`). The NumPy
functions they mirror (:mod:`correlation.peak`, :mod:`correlation.validation`, ...) are the reference.

Correlation planes are stored unshifted (zero displacement at index 0); the peak kernel reads them
through :func:`shifted`, the layout of :func:`correlation.xcorr.cross_correlate`. Vector fields are
float64 on a (ny, nx) grid; flags are :class:`correlation.VectorFlag` bits.
"""

from __future__ import annotations

import warp as wp

from synthbos.device import quiet_warp

from .flags import VectorFlag
from .kernels import sample_image
from .median_test import median_scale_wp, median_wp, normalised_residual_wp, vec8d
from .rules import WINDOW_SIZES

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})

#: The :class:`correlation.flags.VectorFlag` bits, as the kernels read them.
FLAG_MEDIAN = wp.constant(int(VectorFlag.MEDIAN))
FLAG_PEAK = wp.constant(int(VectorFlag.PEAK))
FLAG_BORDER = wp.constant(int(VectorFlag.BORDER))
FLAG_MASKED = wp.constant(int(VectorFlag.MASKED))
FLAG_DISAGREE = wp.constant(int(VectorFlag.DISAGREE))
FLAG_ISOLATED = wp.constant(int(VectorFlag.ISOLATED))

#: Relative size below which a three-point denominator counts as zero (``correlation.peak._TINY``).
PEAK_TINY = wp.constant(wp.float64(1.0e-12))
#: The largest float64, the peak ratio of a plane whose only positive value is its peak.
FLOAT64_MAX = wp.constant(wp.float64(1.7976931348623157e308))


# ---------------------------------------------------------------- predictor: separable spline weights


@wp.kernel
def spline_rows(
    wy: wp.array2d(dtype=wp.float32),
    u: wp.array2d(dtype=wp.float64),
    v: wp.array2d(dtype=wp.float64),
    su: wp.array2d(dtype=wp.float32),
    sv: wp.array2d(dtype=wp.float32),
):
    """``su = wy @ float32(u)`` and ``sv = wy @ float32(v)``: the first factor of ``Wy @ F @ Wx.T``."""
    i, b = wp.tid()
    acc_u = wp.float32(0.0)
    acc_v = wp.float32(0.0)
    for a in range(u.shape[0]):
        acc_u += wy[i, a] * wp.float32(u[a, b])
        acc_v += wy[i, a] * wp.float32(v[a, b])
    su[i, b] = acc_u
    sv[i, b] = acc_v


@wp.kernel
def spline_cols(
    su: wp.array2d(dtype=wp.float32),
    sv: wp.array2d(dtype=wp.float32),
    wx: wp.array2d(dtype=wp.float32),
    du: wp.array2d(dtype=wp.float32),
    dv: wp.array2d(dtype=wp.float32),
):
    """``du = su @ wx.T``, ``dv = sv @ wx.T``: the predictor at every target point."""
    i, j = wp.tid()
    acc_u = wp.float32(0.0)
    acc_v = wp.float32(0.0)
    for b in range(su.shape[1]):
        acc_u += su[i, b] * wx[j, b]
        acc_v += sv[i, b] * wx[j, b]
    du[i, j] = acc_u
    dv[i, j] = acc_v


# ---------------------------------------------------------------- symmetric deformation and edge weights


@wp.kernel
def deform_pair_weighted(
    first: wp.array2d(dtype=wp.float32),
    second: wp.array2d(dtype=wp.float32),
    du: wp.array2d(dtype=wp.float32),
    dv: wp.array2d(dtype=wp.float32),
    row0: float,
    col0: float,
    interpolator: int,
    valid_px: wp.array2d(dtype=wp.float32),
    pixel_row0: int,
    pixel_col0: int,
    margin: wp.float64,
    out_first: wp.array2d(dtype=wp.float32),
    out_second: wp.array2d(dtype=wp.float32),
    weight: wp.array2d(dtype=wp.float32),
):
    """Both images resampled at x -/+ d(x)/2 (one thread per pixel), and each pixel's weight.

    The weight is 0 where either deformed image is sampled closer than ``margin`` px to the image
    edge (``multigrid._edge_weights``) or where the pixel of the undeformed window is masked
    (``valid_px[pixel_row0 + i, pixel_col0 + j]`` is 0), else 1.
    """
    i, j = wp.tid()
    y = row0 + float(i)
    x = col0 + float(j)
    hu = 0.5 * du[i, j]
    hv = 0.5 * dv[i, j]
    out_first[i, j] = sample_image(first, y - hv, x - hu, interpolator)
    out_second[i, j] = sample_image(second, y + hv, x + hu, interpolator)
    h = wp.float64(first.shape[0])
    w = wp.float64(first.shape[1])
    yd = wp.float64(row0) + wp.float64(i)
    xd = wp.float64(col0) + wp.float64(j)
    ahu = wp.float64(wp.abs(hu))
    ahv = wp.float64(wp.abs(hv))
    one = wp.float64(1.0)
    inside = (
        yd - ahv >= margin and yd + ahv <= h - one - margin and xd - ahu >= margin and xd + ahu <= w - one - margin
    )
    wgt = valid_px[pixel_row0 + i, pixel_col0 + j]
    if not inside:
        wgt = wp.float32(0.0)
    weight[i, j] = wgt


# ---------------------------------------------------------------- window correlation (one tile per window)


@wp.func
def centred_complex(x: wp.float32, w: wp.float32, m: wp.float32) -> wp.vec2f:
    return wp.vec2f((x - m) * w, wp.float32(0.0))


@wp.func
def weighted(x: wp.float32, w: wp.float32) -> wp.float32:
    return x * w


@wp.func
def real_square(z: wp.vec2f) -> wp.float64:
    return wp.float64(z[0]) * wp.float64(z[0])


@wp.func
def same(z: wp.vec2f) -> wp.vec2f:
    return z


@wp.func
def real_part(z: wp.vec2f) -> wp.float32:
    return z[0]


@wp.func
def cross_spectrum(fa: wp.vec2f, fb: wp.vec2f, f: wp.float32) -> wp.vec2f:
    """``conj(fa) fb f``."""
    re = fa[0] * fb[0] + fa[1] * fb[1]
    im = fa[0] * fb[1] - fa[1] * fb[0]
    return wp.vec2f(re * f, im * f)


@wp.func
def phase_spectrum(fa: wp.vec2f, fb: wp.vec2f, f: wp.float32) -> wp.vec2f:
    """``conj(fa) fb / |conj(fa) fb| f``: robust phase correlation (``xcorr.robust_phase_correlate``)."""
    re = fa[0] * fb[0] + fa[1] * fb[1]
    im = fa[0] * fb[1] - fa[1] * fb[0]
    mag = wp.max(wp.sqrt(re * re + im * im), wp.float32(1.17549435e-38))
    return wp.vec2f(re / mag * f, im / mag * f)


#: Shifted plane positions (row, column) are coded as row * PLANE_CODE + column.
PLANE_CODE = wp.constant(4096)


@wp.func
def outside_peak(x: wp.float32, at: wp.int32, peak: wp.int32) -> wp.float32:
    """``x`` where its shifted position ``at`` lies outside the 5 x 5 square around ``peak``, else -FLT_MAX."""
    if wp.abs(at // PLANE_CODE - peak // PLANE_CODE) > 2 or wp.abs(at % PLANE_CODE - peak % PLANE_CODE) > 2:
        return x
    return wp.float32(-3.4028235e38)


def make_correlate_windows(n: int, rpc: bool):
    """Kernel correlating all ``n`` x ``n`` window pairs of a grid, one tile (block) per window.

    Launch with ``wp.launch_tiled(kernel, dim=[windows], block_dim=window_threads(n))``: the FFT's constraints
    (a power-of-two ``n`` divisible by ``block_dim`` without libmathdx, at least two elements per
    thread with it).
    """

    @wp.kernel(module="unique", enable_backward=False)
    def correlate_windows(
        img_a: wp.array2d(dtype=wp.float32),
        img_b: wp.array2d(dtype=wp.float32),
        weight: wp.array2d(dtype=wp.float32),
        row0: int,
        col0: int,
        step: int,
        nx: int,
        spectral: wp.array2d(dtype=wp.float32),
        positions: wp.array2d(dtype=wp.int32),
        select: wp.array2d(dtype=wp.float32),
        planes: wp.array2d(dtype=wp.float32),
        norm: wp.array(dtype=wp.float64),
        peak_at: wp.array(dtype=wp.int32),
        peak_values: wp.array2d(dtype=wp.float32),
    ):
        """Window k: weighted means subtracted, 2-D FFTs (rows, transpose, rows), cross spectrum times
        ``spectral`` (1/n^2, and the RPC filter), inverse; plane k (unshifted) in rows k n ... k n + n - 1.

        ``norm[k]`` = sqrt(sum a'^2 sum b'^2) of the mean-subtracted windows; ``peak_at[k]`` the shifted
        position of the maximum of the plane times ``select`` (all 1, or the overlap weights for
        periodic patterns: ``correlation.peak.subpixel_peak``) (``PLANE_CODE``; (0, 0) for a constant
        plane, as np.argmax);
        ``peak_values[k]`` its maximum, minimum and the maximum outside the 5 x 5 square around the
        peak (``correlation.peak.peak_ratio``; the minimum if there is nothing outside).
        ``positions`` holds the shifted position of every unshifted sample."""
        k = wp.tid()
        r = row0 + (k // nx) * step
        c = col0 + (k % nx) * step
        ta = wp.tile_load(img_a, shape=(n, n), offset=(r, c))
        tb = wp.tile_load(img_b, shape=(n, n), offset=(r, c))
        tw = wp.tile_load(weight, shape=(n, n), offset=(r, c))
        count = wp.max(wp.tile_extract(wp.tile_sum(tw), 0), wp.float32(1.0))
        ma = wp.tile_extract(wp.tile_sum(wp.tile_map(weighted, ta, tw)), 0) / count
        mb = wp.tile_extract(wp.tile_sum(wp.tile_map(weighted, tb, tw)), 0) / count
        za = wp.tile_map(centred_complex, ta, tw, wp.tile_full(shape=(n, n), value=ma, dtype=wp.float32))
        zb = wp.tile_map(centred_complex, tb, tw, wp.tile_full(shape=(n, n), value=mb, dtype=wp.float32))
        ea = wp.tile_extract(wp.tile_sum(wp.tile_map(real_square, za)), 0)
        eb = wp.tile_extract(wp.tile_sum(wp.tile_map(real_square, zb)), 0)
        norm[k] = wp.sqrt(ea * eb)
        wp.tile_fft(za)
        wp.tile_fft(zb)
        # a transposed tile lives in shared memory; the FFT wants registers: copy before and after
        fa = wp.tile_map(same, wp.tile_transpose(wp.tile_map(same, za)))
        fb = wp.tile_map(same, wp.tile_transpose(wp.tile_map(same, zb)))
        wp.tile_fft(fa)
        wp.tile_fft(fb)
        filt = wp.tile_load(spectral, shape=(n, n))
        if wp.static(rpc):
            s = wp.tile_map(phase_spectrum, fa, fb, filt)
        else:
            s = wp.tile_map(cross_spectrum, fa, fb, filt)
        wp.tile_ifft(s)
        st = wp.tile_map(same, wp.tile_transpose(wp.tile_map(same, s)))
        wp.tile_ifft(st)
        plane = wp.tile_map(real_part, st)
        wp.tile_store(planes, plane, offset=(k * n, 0))
        # the peak and the second peak
        at = wp.tile_load(positions, shape=(n, n))
        top = wp.tile_extract(wp.tile_max(plane), 0)
        low = wp.tile_extract(wp.tile_min(plane), 0)
        sel = wp.tile_load(select, shape=(n, n))
        i = wp.tile_extract(wp.tile_argmax(wp.tile_map(weighted, plane, sel)), 0)  # cooperative: every thread
        peak = positions[i // n, i % n]
        if top <= low:
            peak = wp.int32(0)
        second = wp.tile_extract(
            wp.tile_max(wp.tile_map(outside_peak, plane, at, wp.tile_full(shape=(n, n), value=peak, dtype=wp.int32))),
            0,
        )
        if second == wp.float32(-3.4028235e38):
            second = low
        peak_at[k] = peak
        peak_values[k, 0] = top
        peak_values[k, 1] = low
        peak_values[k, 2] = second

    return correlate_windows


_window_kernels: dict = {}  # (n, rpc) -> kernel


def window_threads(n: int) -> int:
    """Threads per block of :func:`make_correlate_windows`'s kernel for ``n`` px windows: two samples of a
    row each (Warp's tile FFT wants at least two)."""
    return max(int(n) // 2, 1)


def correlate_windows_kernel(n: int, rpc: bool):
    """:func:`make_correlate_windows`'s kernel for ``n`` px windows, made once per process. It is a Warp
    module of its own, whose default block size is its launch's (:func:`window_threads`), so that
    compiling it ahead of the launch (``synthbos.device.load_kernels``) builds the variant the launch uses."""
    key = (int(n), bool(rpc))
    if key not in _window_kernels:
        kernel = make_correlate_windows(*key)
        kernel.module.options["block_dim"] = window_threads(key[0])
        _window_kernels[key] = kernel
    return _window_kernels[key]


# The default passes' kernels, made at import so that a campaign's load_kernels compiles them with the
# others, in parallel, instead of each inside its first pair (12-14 s each on a first GPU run).
for _n in WINDOW_SIZES:
    correlate_windows_kernel(_n, False)


# ---------------------------------------------------------------- peak fit and significance


@wp.func
def clip_half(x: wp.float64) -> wp.float64:
    return wp.clamp(x, wp.float64(-0.5), wp.float64(0.5))


@wp.func
def three_point_offset(left: wp.float64, centre: wp.float64, right: wp.float64, method: int) -> wp.float64:
    """``correlation.peak.three_point_offset``: 0 Gaussian, 1 parabolic, 2 centroid."""
    zero = wp.float64(0.0)
    if method == 2:
        den = left + centre + right
        if wp.abs(den) > PEAK_TINY:
            return clip_half((right - left) / den)
        return zero
    den = left - wp.float64(2.0) * centre + right
    parabolic = zero
    if den < -PEAK_TINY:
        parabolic = (left - right) / (wp.float64(2.0) * den)
    if method == 1:
        return clip_half(parabolic)
    if left > zero and centre > zero and right > zero:
        ll = wp.log(left)
        lc = wp.log(centre)
        lr = wp.log(right)
        gden = ll - wp.float64(2.0) * lc + lr
        if gden < -PEAK_TINY:
            return clip_half((ll - lr) / (wp.float64(2.0) * gden))
    return clip_half(parabolic)


@wp.func
def shifted(planes: wp.array2d(dtype=wp.float32), k: int, n: int, r: int, c: int) -> wp.float64:
    """Sample (r, c) of plane k with zero displacement at (n // 2, n // 2) (``np.fft.fftshift``)."""
    h = n // 2
    return wp.float64(planes[k * n + (r + n - h) % n, (c + n - h) % n])


@wp.func
def overlap_weight(r: int, c: int, n: int) -> wp.float64:
    """``correlation.peak.overlap_weights`` at (r, c)."""
    fn = wp.float64(n)
    wy = wp.float64(1.0) - wp.float64(wp.abs(r - n // 2)) / fn
    wx = wp.float64(1.0) - wp.float64(wp.abs(c - n // 2)) / fn
    return wy * wx


@wp.kernel
def fit_peaks(
    planes: wp.array2d(dtype=wp.float32),
    n: int,
    norm: wp.array(dtype=wp.float64),
    peak_at: wp.array(dtype=wp.int32),
    peak_values: wp.array2d(dtype=wp.float32),
    pu: wp.array2d(dtype=wp.float32),
    pv: wp.array2d(dtype=wp.float32),
    method: int,
    has_norm: int,
    peak_ratio_min: wp.float64,
    min_correlation: wp.float64,
    coarse_u: wp.array2d(dtype=wp.float32),
    coarse_v: wp.array2d(dtype=wp.float32),
    use_coarse: int,
    max_distance: wp.float64,
    masked: wp.array2d(dtype=wp.int32),
    u: wp.array2d(dtype=wp.float64),
    v: wp.array2d(dtype=wp.float64),
    ratio: wp.array2d(dtype=wp.float64),
    coef: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
):
    """One thread per window, from the peak found by the correlation kernel (its value read from the
    plane, the plane's maximum unless the search was weighted): three-point fit on
    overlap-weighted samples, peak ratio (exclusion 2), correlation coefficient, vector = predictor +
    peak offset, and the flags ``BORDER``, ``PEAK``, ``DISAGREE``, ``MASKED`` (``subpixel_peak``,
    ``peak_ratio``, ``correlate_pair``)."""
    i, j = wp.tid()
    k = i * u.shape[1] + j
    r0 = peak_at[k] // PLANE_CODE
    c0 = peak_at[k] % PLANE_CODE
    c1 = shifted(planes, k, n, r0, c0)
    cmin = wp.float64(peak_values[k, 1])
    c2 = wp.float64(peak_values[k, 2])
    num = c1 - cmin
    den = c2 - cmin
    pr = wp.float64(1.0)
    if den > wp.float64(0.0):
        pr = num / den
    elif num > wp.float64(0.0):
        pr = FLOAT64_MAX
    # three-point fits; on the border the missing neighbour mirrors the other one
    last = n - 1
    border = r0 == 0 or r0 == last or c0 == 0 or c0 == last
    rm = wp.max(r0 - 1, 0)
    rp = wp.min(r0 + 1, last)
    cm = wp.max(c0 - 1, 0)
    cp = wp.min(c0 + 1, last)
    ru = rm
    rd = rp
    if r0 == 0:
        ru = rp
    if r0 == last:
        rd = rm
    cl = cm
    cr = cp
    if c0 == 0:
        cl = cp
    if c0 == last:
        cr = cm
    centre = c1 / overlap_weight(r0, c0, n)
    up = shifted(planes, k, n, ru, c0) / overlap_weight(ru, c0, n)
    down = shifted(planes, k, n, rd, c0) / overlap_weight(rd, c0, n)
    left = shifted(planes, k, n, r0, cl) / overlap_weight(r0, cl, n)
    right = shifted(planes, k, n, r0, cr) / overlap_weight(r0, cr, n)
    row = wp.float64(r0) + three_point_offset(up, centre, down, method)
    col = wp.float64(c0) + three_point_offset(left, centre, right, method)
    uu = wp.float64(pu[i, j]) + (col - wp.float64(n // 2))
    vv = wp.float64(pv[i, j]) + (row - wp.float64(n // 2))
    cc = wp.float64(0.0)
    if norm[k] > wp.float64(0.0):
        cc = c1 / norm[k]
    f = wp.int32(0)
    if border:
        f = f | FLAG_BORDER
    if pr < peak_ratio_min or (has_norm != 0 and cc < min_correlation):
        f = f | FLAG_PEAK
    if use_coarse != 0:
        eu = uu - wp.float64(coarse_u[i, j])
        ev = vv - wp.float64(coarse_v[i, j])
        if wp.sqrt(eu * eu + ev * ev) > max_distance:
            f = f | FLAG_DISAGREE
    if masked[i, j] != 0:
        f = f | FLAG_MASKED
    u[i, j] = uu
    v[i, j] = vv
    ratio[i, j] = pr
    coef[i, j] = cc
    flags[i, j] = f


# ---------------------------------------------------------------- validation


@wp.func
def row_extended(field: wp.array2d(dtype=wp.float64), ok: wp.array2d(dtype=wp.int32), i: int, j: int) -> wp.vec2d:
    """(value, 1) of node (i, j) for -1 <= i <= ny, the rows continued linearly; (0, 0) where not valid."""
    ny = field.shape[0]
    if i >= 0 and i < ny:
        return wp.vec2d(field[i, j], wp.float64(ok[i, j]))
    e = 0
    nb = 1
    if i >= ny:
        e = ny - 1
        nb = ny - 2
    if ny < 2:
        return wp.vec2d(field[e, j], wp.float64(ok[e, j]))
    both = ok[e, j] * ok[nb, j]
    return wp.vec2d(wp.float64(2.0) * field[e, j] - field[nb, j], wp.float64(both))


@wp.func
def extended(field: wp.array2d(dtype=wp.float64), ok: wp.array2d(dtype=wp.int32), i: int, j: int) -> wp.vec2d:
    """(value, 1) of node (i, j) of the grid padded by one node, continued linearly
    (``validation._extrapolated_pad``: rows first, then columns); (0, 0) where not valid."""
    nx = field.shape[1]
    if j >= 0 and j < nx:
        return row_extended(field, ok, i, j)
    e = 0
    nb = 1
    if j >= nx:
        e = nx - 1
        nb = nx - 2
    if nx < 2:
        return row_extended(field, ok, i, e)
    a = row_extended(field, ok, i, e)
    b = row_extended(field, ok, i, nb)
    return wp.vec2d(wp.float64(2.0) * a[0] - b[0], a[1] * b[1])


@wp.func
def median_residual(
    field: wp.array2d(dtype=wp.float64), ok: wp.array2d(dtype=wp.int32), i: int, j: int, epsilon: wp.float64
) -> wp.vec2d:
    """(r0^2, neighbour count) of the normalised median test of one component at node (i, j)."""
    nb = vec8d()
    count = wp.int32(0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            if dy != 0 or dx != 0:
                e = extended(field, ok, i + dy, j + dx)
                if e[1] > wp.float64(0.0):
                    nb[count] = e[0]
                    count += 1
    if count == 0:
        return wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    ms = median_scale_wp(nb, count)
    r0 = normalised_residual_wp(wp.abs(field[i, j] - ms[0]), ms[1], epsilon)
    r2 = wp.float64(0.0)
    if wp.isfinite(r0):  # a zero denominator gives inf or NaN there: not counted, as on the host
        r2 = r0 * r0
    return wp.vec2d(r2, wp.float64(count))


@wp.kernel
def measured_mask(flags: wp.array2d(dtype=wp.int32), ok: wp.array2d(dtype=wp.int32)):
    """``ok = flags == 0``."""
    i, j = wp.tid()
    m = wp.int32(0)
    if flags[i, j] == 0:
        m = 1
    ok[i, j] = m


@wp.kernel
def median_test(
    u: wp.array2d(dtype=wp.float64),
    v: wp.array2d(dtype=wp.float64),
    ok: wp.array2d(dtype=wp.int32),
    epsilon: wp.float64,
    threshold: wp.float64,
    confirm: int,
    tolerance: wp.float64,
    raw_u: wp.array2d(dtype=wp.float64),
    raw_v: wp.array2d(dtype=wp.float64),
    has_coef: int,
    coef: wp.array2d(dtype=wp.float64),
    confirm_fraction: wp.float64,
    flags_in: wp.array2d(dtype=wp.int32),
    flags_out: wp.array2d(dtype=wp.int32),
):
    """Normalised median test on the valid (``ok``) vectors, unless the previous iteration confirms
    them (``multigrid._confirmed``; ``confirm_fraction`` is ``CONFIRM_CORRELATION``):
    ``flags_out = flags_in | MEDIAN`` for the rejected ones."""
    i, j = wp.tid()
    f = flags_in[i, j]
    if ok[i, j] != 0:
        ru = median_residual(u, ok, i, j, epsilon)
        rv = median_residual(v, ok, i, j, epsilon)
        outlier = ru[1] >= wp.float64(2.0) and wp.sqrt(ru[0] + rv[0]) > threshold
        if outlier and confirm != 0:
            du = u[i, j] - raw_u[i, j]
            dv = v[i, j] - raw_v[i, j]
            confirmed = wp.sqrt(du * du + dv * dv) <= tolerance
            if confirmed and has_coef != 0:
                nb = vec8d()
                count = wp.int32(0)
                for dy in range(-1, 2):
                    for dx in range(-1, 2):
                        y = i + dy
                        x = j + dx
                        if (dy != 0 or dx != 0) and y >= 0 and y < u.shape[0] and x >= 0 and x < u.shape[1]:
                            if ok[y, x] != 0:
                                nb[count] = coef[y, x]
                                count += 1
                if count > 0:
                    confirmed = coef[i, j] >= confirm_fraction * median_wp(nb, count)
            outlier = not confirmed
        if outlier:
            f = f | FLAG_MEDIAN
    flags_out[i, j] = f


@wp.kernel
def isolated_test(flags_in: wp.array2d(dtype=wp.int32), flags_out: wp.array2d(dtype=wp.int32)):
    """``ISOLATED`` for measured vectors with fewer than two measured of at least three unmasked neighbours."""
    i, j = wp.tid()
    f = flags_in[i, j]
    if f == 0:
        n_meas = wp.int32(0)
        n_open = wp.int32(0)
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                y = i + dy
                x = j + dx
                if (dy != 0 or dx != 0) and y >= 0 and y < flags_in.shape[0] and x >= 0 and x < flags_in.shape[1]:
                    g = flags_in[y, x]
                    if g == 0:
                        n_meas += 1
                    if (g & FLAG_MASKED) == 0:
                        n_open += 1
        if n_open >= 3 and n_meas < 2:
            f = f | FLAG_ISOLATED
    flags_out[i, j] = f


# ---------------------------------------------------------------- replacement (validation.replace_outliers)


@wp.func
def neighbour_median_at(
    field: wp.array2d(dtype=wp.float64), todo: wp.array2d(dtype=wp.int32), i: int, j: int
) -> wp.vec2d:
    """(median, count) of the neighbours of (i, j) with ``todo == 0``; (0, 0) if there are none."""
    nb = vec8d()
    count = wp.int32(0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            y = i + dy
            x = j + dx
            if (dy != 0 or dx != 0) and y >= 0 and y < field.shape[0] and x >= 0 and x < field.shape[1]:
                if todo[y, x] == 0:
                    nb[count] = field[y, x]
                    count += 1
    if count == 0:
        return wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    return wp.vec2d(median_wp(nb, count), wp.float64(count))


@wp.kernel
def start_replacement(
    u: wp.array2d(dtype=wp.float64),
    v: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    u_out: wp.array2d(dtype=wp.float64),
    v_out: wp.array2d(dtype=wp.float64),
    todo: wp.array2d(dtype=wp.int32),
    left: wp.array(dtype=wp.int32),
):
    """Copy the field; every flagged vector is to be replaced; the first thread clears the sweeps' counts
    ``left`` (a launch on the caller's stream, where a memset would take the device's current one)."""
    i, j = wp.tid()
    if i == 0 and j == 0:
        for sweep in range(left.shape[0]):
            left[sweep] = 0
    u_out[i, j] = u[i, j]
    v_out[i, j] = v[i, j]
    t = wp.int32(0)
    if flags[i, j] != 0:
        t = 1
    todo[i, j] = t


@wp.kernel
def replacement_sweep(
    u: wp.array2d(dtype=wp.float64),
    v: wp.array2d(dtype=wp.float64),
    todo: wp.array2d(dtype=wp.int32),
    u_out: wp.array2d(dtype=wp.float64),
    v_out: wp.array2d(dtype=wp.float64),
    todo_out: wp.array2d(dtype=wp.int32),
    left: wp.array(dtype=wp.int32),
    sweep: int,
):
    """One sweep: vectors to replace that have valid neighbours get their median; ``left[sweep]`` counts the rest."""
    i, j = wp.tid()
    uu = u[i, j]
    vv = v[i, j]
    t = todo[i, j]
    if t != 0:
        mu = neighbour_median_at(u, todo, i, j)
        if mu[1] > wp.float64(0.0):
            uu = mu[0]
            vv = neighbour_median_at(v, todo, i, j)[0]
            t = 0
        else:
            wp.atomic_add(left, sweep, 1)
    u_out[i, j] = uu
    v_out[i, j] = vv
    todo_out[i, j] = t


@wp.kernel
def finish_replacement(
    u: wp.array2d(dtype=wp.float64),
    v: wp.array2d(dtype=wp.float64),
    todo: wp.array2d(dtype=wp.int32),
    left: wp.array(dtype=wp.int32),
    sweeps_done: int,
    max_sweeps: int,
    scratch: wp.array(dtype=wp.float64),
):
    """One thread: if vectors are left after the parallel sweeps, more sweeps in place (stamped so
    that each sees only the vectors valid at its start) up to ``max_sweeps``, then the median of all
    valid vectors (0 if none) for what is still left. Usually returns at once."""
    if left[sweeps_done - 1] == 0:
        return
    ny = u.shape[0]
    nx = u.shape[1]
    for _ in range(sweeps_done, max_sweeps):
        filled = wp.int32(0)
        for i in range(ny):
            for j in range(nx):
                if todo[i, j] == 1:
                    mu = neighbour_median_at(u, todo, i, j)
                    if mu[1] > wp.float64(0.0):
                        mv = neighbour_median_at(v, todo, i, j)
                        u[i, j] = mu[0]
                        v[i, j] = mv[0]
                        todo[i, j] = 2  # filled in this sweep: a neighbour from the next one on
                        filled += 1
        for i in range(ny):
            for j in range(nx):
                if todo[i, j] == 2:
                    todo[i, j] = 0
        if filled == 0:
            break
    for comp in range(2):
        count = wp.int32(0)
        for i in range(ny):
            for j in range(nx):
                if todo[i, j] == 0:
                    x = u[i, j]
                    if comp == 1:
                        x = v[i, j]
                    b = count - 1
                    while b >= 0 and scratch[b] > x:
                        scratch[b + 1] = scratch[b]
                        b -= 1
                    scratch[b + 1] = x
                    count += 1
        med = wp.float64(0.0)
        if count > 0:
            med = wp.float64(0.5) * (scratch[(count - 1) // 2] + scratch[count // 2])
        for i in range(ny):
            for j in range(nx):
                if todo[i, j] != 0:
                    if comp == 0:
                        u[i, j] = med
                    else:
                        v[i, j] = med


# ---------------------------------------------------------------- interpolation (validation.fill_by_interpolation)


@wp.kernel
def laplace_sweep(
    u: wp.array2d(dtype=wp.float64),
    v: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    u_out: wp.array2d(dtype=wp.float64),
    v_out: wp.array2d(dtype=wp.float64),
):
    """One Jacobi sweep of the Laplace equation on the flagged vectors: each becomes the mean of its
    four neighbours (the edge node standing in beyond the grid); the others are copied."""
    i, j = wp.tid()
    uu = u[i, j]
    vv = v[i, j]
    if flags[i, j] != 0:
        ny = u.shape[0]
        nx = u.shape[1]
        up = wp.max(i - 1, 0)
        down = wp.min(i + 1, ny - 1)
        left = wp.max(j - 1, 0)
        right = wp.min(j + 1, nx - 1)
        q = wp.float64(0.25)
        uu = q * (u[up, j] + u[down, j] + u[i, left] + u[i, right])
        vv = q * (v[up, j] + v[down, j] + v[i, left] + v[i, right])
    u_out[i, j] = uu
    v_out[i, j] = vv
