"""NumPy float64 references of the renderer's kernels, for the tests.

They follow the definitions in ``raytrace.kernels`` line by line in double precision, so the tests can
check that the Warp kernels compute the same thing on every device.
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf

from .medium import MediumData

__all__ = ["deposit_gaussian", "sample_medium", "straight_ray_integrals", "trace_volume"]


def sample_medium(medium: MediumData, p_local):
    """Trilinear sample of (dn/dx, dn/dy, dn/dz, n-1) at local points (..., 3); zero outside the box."""
    f = np.asarray(medium.field, dtype=np.float64)
    nz, ny, nx = f.shape[:3]
    p = np.asarray(p_local, dtype=np.float64)
    half = np.array(medium.size) / 2.0
    frac = (p + half) / np.array(medium.spacing)
    n_max = np.array([nx - 1, ny - 1, nz - 1])
    inside = np.all((frac >= -1e-4) & (frac <= n_max + 1e-4), axis=-1)
    base = np.clip(np.floor(frac).astype(int), 0, n_max - 1)
    a = np.clip(frac - base, 0.0, 1.0)
    i, j, k = base[..., 0], base[..., 1], base[..., 2]
    ax, ay, az = (a[..., d, None] for d in range(3))
    c00 = f[k, j, i] * (1 - ax) + f[k, j, i + 1] * ax
    c10 = f[k, j + 1, i] * (1 - ax) + f[k, j + 1, i + 1] * ax
    c01 = f[k + 1, j, i] * (1 - ax) + f[k + 1, j, i + 1] * ax
    c11 = f[k + 1, j + 1, i] * (1 - ax) + f[k + 1, j + 1, i + 1] * ax
    out = (c00 * (1 - ay) + c10 * ay) * (1 - az) + (c01 * (1 - ay) + c11 * ay) * az
    return np.where(inside[..., None], out, 0.0)


def straight_ray_integrals(medium: MediumData, origins, aims, n_samples):
    """Float64 twin of ``kernels.straight_ray_integrals`` for rays (N, 3) from ``origins`` towards ``aims``.

    Returns Eq. 4's integral with each depth weighted by its geometry, ``(1 + |u|^2) / Z_D * integral
    of z (grad_xy n - u dn/dz) dz`` over the box's depth (N, 2), and the depth-mean of n - 1 (N,),
    read at the nearest point of the box's side where a ray passes beside it.
    """
    o = np.asarray(origins, dtype=np.float64)
    t = np.asarray(aims, dtype=np.float64) - o
    t = t / np.linalg.norm(t, axis=-1, keepdims=True)
    u = t[:, :2] / t[:, 2:3]
    centre, half = np.array(medium.centre), np.array(medium.size) / 2.0
    dz = 2.0 * half[2] / n_samples
    z = centre[2] - half[2] + (np.arange(n_samples) + 0.5) * dz  # (S,)
    p = o[:, None, :] + ((z[None, :] - o[:, None, 2]) / t[:, None, 2])[..., None] * t[:, None, :] - centre
    s = sample_medium(medium, p)  # (N, S, 4)
    edge = p.copy()
    edge[..., :2] = np.clip(p[..., :2], -half[:2], half[:2])
    nm1 = sample_medium(medium, edge)[..., 3].mean(axis=1)
    weighted = ((s[..., :2] - u[:, None, :] * s[..., 2:3]) * z[None, :, None]).sum(axis=1) * dz
    return weighted * ((1.0 + np.sum(u * u, axis=1)) / centre[2])[:, None], nm1


def _rate(medium, x, t):
    s = sample_medium(medium, x)
    g = s[..., :3]
    return (g - np.sum(t * g, axis=-1, keepdims=True) * t) / (1.0 + s[..., 3:4])


def trace_volume(medium: MediumData, origins, tangents, step):
    """Float64 twin of ``kernels.trace_volume`` for rays (N, 3) in the global frame."""
    x = np.asarray(origins, dtype=np.float64).copy()
    t = np.asarray(tangents, dtype=np.float64)
    t = t / np.linalg.norm(t, axis=-1, keepdims=True)
    centre, half = np.array(medium.centre), np.array(medium.size) / 2.0
    s0 = (centre[2] - half[2] - x[:, 2]) / t[:, 2]
    x = x + s0[:, None] * t - centre
    length = 2.0 * half[2] / t[:, 2]
    n = np.maximum(np.ceil(length / step - 1e-4).astype(int), 1)
    out_x, out_t = np.empty_like(x), np.empty_like(t)
    for r in range(len(x)):
        h = length[r] / n[r]
        xr, tr = x[r : r + 1], t[r : r + 1]
        for _ in range(n[r]):
            k1 = _rate(medium, xr, tr)
            t2 = tr + 0.5 * h * k1
            k2 = _rate(medium, xr + 0.5 * h * tr, t2)
            t3 = tr + 0.5 * h * k2
            k3 = _rate(medium, xr + 0.5 * h * t2, t3)
            t4 = tr + h * k3
            k4 = _rate(medium, xr + h * t3, t4)
            xr = xr + h / 6.0 * (tr + 2 * t2 + 2 * t3 + t4)
            tr = tr + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
            tr = tr / np.linalg.norm(tr)
        out_x[r], out_t[r] = xr[0] + centre, tr[0]
    return out_x, out_t


def deposit_gaussian(shape, px, energy, sigma_px, half_width):
    """Float64 twin of ``kernels.deposit_gaussian`` for spots at pixel positions (N, 2)."""
    img = np.zeros(shape)
    inv = 1.0 / (np.sqrt(2.0) * sigma_px)
    for (x, y), e in zip(np.asarray(px, float), np.broadcast_to(energy, (len(px),)), strict=True):
        c0, r0 = int(np.round(x)), int(np.round(y))
        rows = np.arange(r0 - half_width, r0 + half_width + 1)
        cols = np.arange(c0 - half_width, c0 + half_width + 1)
        fy = 0.5 * (erf((rows + 0.5 - y) * inv) - erf((rows - 0.5 - y) * inv))
        fx = 0.5 * (erf((cols + 0.5 - x) * inv) - erf((cols - 0.5 - x) * inv))
        keep_r = (rows >= 0) & (rows < shape[0])
        keep_c = (cols >= 0) & (cols < shape[1])
        img[np.ix_(rows[keep_r], cols[keep_c])] += e * np.outer(fy[keep_r], fx[keep_c])
    return img
