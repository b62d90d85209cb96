"""Warp kernels of the image deformation: symmetric resampling of an image pair.

Only ``@wp.func`` helpers and ``@wp.kernel``\\ s live here; the host code that allocates, launches
and copies is in :mod:`correlation.deform`. Images are float32, indexed ``[row, col]``; pixel
centres sit at integer coordinates. Outside the image every sampler mirrors about the edge pixel
centres (whole-sample symmetric, ``d c b | a b c d | c b a``: scipy.ndimage's ``mode="mirror"``).
"""

from __future__ import annotations

import warp as wp

from synthbos.device import quiet_warp

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile


@wp.func
def mirror_index(k: int, n: int) -> int:
    """Index ``k`` folded into ``[0, n)`` by whole-sample symmetric extension."""
    if n == 1:
        return 0
    period = 2 * n - 2
    m = wp.abs(k) % period
    if m >= n:
        m = period - m
    return m


vec6 = wp.types.vector(length=6, dtype=wp.float32)


@wp.func
def lanczos3_weights(t: float) -> vec6:
    """Normalised Lanczos-3 weights of the six taps floor(u) - 2 ... floor(u) + 3, fraction ``t``.

    ``L(s) = 3 sin(pi s) sin(pi s / 3) / (pi s)^2`` at ``s = t - k``; the sines of all six taps follow
    from ``sin(pi t)``, ``sin(pi t / 3)`` and ``cos(pi t / 3)`` by the angle-sum identities.
    """
    if t < 1.0e-6:
        return vec6(0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    sp = wp.sin(wp.pi * t)
    s3 = wp.sin(wp.pi * t / 3.0)
    c3 = wp.cos(wp.pi * t / 3.0)
    h = 0.8660254037844386  # sin(pi / 3)
    # (-1)^k sin(pi t) * sin(pi (t - k) / 3) for k = -2 ... 3
    n = vec6(
        sp * (-0.5 * s3 + h * c3),
        -sp * (0.5 * s3 + h * c3),
        sp * s3,
        -sp * (0.5 * s3 - h * c3),
        sp * (-0.5 * s3 - h * c3),
        sp * s3,
    )
    w = vec6()
    total = 0.0
    for k in range(6):
        d = t - float(k - 2)
        w[k] = 3.0 * n[k] / (wp.pi * wp.pi * d * d)
        total += w[k]
    return w / total


@wp.func
def bspline3_weights(t: float) -> wp.vec4:
    """Cubic B-spline weights of the four taps floor(u) - 1 ... floor(u) + 2, fraction ``t``."""
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return wp.vec4(
        s * s * s / 6.0,
        (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
    )


@wp.func
def sample_lanczos3(image: wp.array2d(dtype=wp.float32), y: float, x: float) -> float:
    """Lanczos-3 interpolation of ``image`` at (y, x), weights normalised to sum 1 per axis."""
    h = image.shape[0]
    w = image.shape[1]
    fy = wp.floor(y)
    fx = wp.floor(x)
    iy = int(fy)
    ix = int(fx)
    wy = lanczos3_weights(y - fy)
    wx = lanczos3_weights(x - fx)
    total = 0.0
    if iy >= 2 and iy + 3 < h and ix >= 2 and ix + 3 < w:
        for a in range(6):
            r = iy - 2 + a
            row = 0.0
            for b in range(6):
                row += wx[b] * image[r, ix - 2 + b]
            total += wy[a] * row
        return total
    for a in range(6):
        r = mirror_index(iy - 2 + a, h)
        row = 0.0
        for b in range(6):
            row += wx[b] * image[r, mirror_index(ix - 2 + b, w)]
        total += wy[a] * row
    return total


@wp.kernel
def deform_pair_lanczos3(
    first: wp.array2d(dtype=wp.float32),
    second: wp.array2d(dtype=wp.float32),
    du: wp.array2d(dtype=wp.float32),
    dv: wp.array2d(dtype=wp.float32),
    row0: float,
    col0: float,
    out_first: wp.array2d(dtype=wp.float32),
    out_second: wp.array2d(dtype=wp.float32),
):
    """Symmetric deformation: first image sampled at x - d/2, second at x + d/2 (Lanczos-3)."""
    i, j = wp.tid()
    y = row0 + float(i)
    x = col0 + float(j)
    hu = 0.5 * du[i, j]
    hv = 0.5 * dv[i, j]
    out_first[i, j] = sample_lanczos3(first, y - hv, x - hu)
    out_second[i, j] = sample_lanczos3(second, y + hv, x + hu)


@wp.func
def keys_weights(t: float) -> wp.vec4:
    """Cubic convolution (Keys 1981, a = -1/2) weights of the taps floor(u) - 1 ... floor(u) + 2."""
    t2 = t * t
    t3 = t2 * t
    return wp.vec4(
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    )


@wp.func
def sample_taps4(image: wp.array2d(dtype=wp.float32), iy: int, ix: int, wy: wp.vec4, wx: wp.vec4) -> float:
    """``sum_ab wy[a] wx[b] image[iy - 1 + a, ix - 1 + b]``, mirrored outside the image."""
    h = image.shape[0]
    w = image.shape[1]
    total = 0.0
    if iy >= 1 and iy + 2 < h and ix >= 1 and ix + 2 < w:
        for a in range(4):
            r = iy - 1 + a
            row = (
                wx[0] * image[r, ix - 1]
                + wx[1] * image[r, ix]
                + wx[2] * image[r, ix + 1]
                + wx[3] * image[r, ix + 2]
            )
            total += wy[a] * row
        return total
    for a in range(4):
        r = mirror_index(iy - 1 + a, h)
        row = 0.0
        for b in range(4):
            row += wx[b] * image[r, mirror_index(ix - 1 + b, w)]
        total += wy[a] * row
    return total


@wp.func
def sample_image(image: wp.array2d(dtype=wp.float32), y: float, x: float, interpolator: int) -> float:
    """``image`` at (y, x): 0 cubic B-spline (image = coefficients), 1 Keys cubic, 2 Lanczos-3."""
    if interpolator == 2:
        return sample_lanczos3(image, y, x)
    fy = wp.floor(y)
    fx = wp.floor(x)
    if interpolator == 0:
        return sample_taps4(image, int(fy), int(fx), bspline3_weights(y - fy), bspline3_weights(x - fx))
    return sample_taps4(image, int(fy), int(fx), keys_weights(y - fy), keys_weights(x - fx))


@wp.kernel
def deform_rows_cubic(
    first: wp.array2d(dtype=wp.float32),
    second: wp.array2d(dtype=wp.float32),
    du: wp.array2d(dtype=wp.float32),
    dv: wp.array2d(dtype=wp.float32),
    row0: float,
    col0: float,
    keys: int,
    out_first: wp.array2d(dtype=wp.float32),
    out_second: wp.array2d(dtype=wp.float32),
):
    """Symmetric 4x4-tap deformation, one thread per output row: B-spline (keys = 0) or Keys taps."""
    i = wp.tid()
    y = row0 + float(i)
    for j in range(du.shape[1]):
        x = col0 + float(j)
        hu = 0.5 * du[i, j]
        hv = 0.5 * dv[i, j]
        out_first[i, j] = sample_image(first, y - hv, x - hu, keys)
        out_second[i, j] = sample_image(second, y + hv, x + hu, keys)
