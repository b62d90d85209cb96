"""Synthetic dot patterns for the tracking tests (imported by the test modules)."""

import numpy as np
from scipy.spatial import cKDTree
from synthbos.tracking.dotfit import fit_dots, fit_window_half


def dot_pattern(rng, shape, *, per_32x32=20.0, min_distance=3.0, margin=3.0):
    """Random dot centres with a minimum centre distance, ``per_32x32`` dots per 32x32 px."""
    h, w = shape
    n = round(per_32x32 * h * w / 1024.0)
    xy = rng.uniform([margin, margin], [w - 1 - margin, h - 1 - margin], size=(int(n * 1.6) + 16, 2))
    pairs = cKDTree(xy).query_pairs(min_distance, output_type="ndarray")
    drop = np.zeros(len(xy), dtype=bool)
    drop[pairs.max(axis=1)] = True
    xy = xy[~drop]
    assert len(xy) >= n
    return xy[:n]


def jittered_grid(rng, shape, *, spacing=10.0, margin=6.0):
    """Isolated dots: a square grid with uniform sub-pixel jitter."""
    h, w = shape
    gx, gy = np.meshgrid(np.arange(margin, w - margin, spacing), np.arange(margin, h - margin, spacing))
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
    return xy + rng.uniform(-0.5, 0.5, xy.shape)


def smooth_displacement(xy, shape, amplitude=1.5):
    """One-period vortex-like displacement field of peak ``amplitude`` px."""
    h, w = shape
    x, y = xy[:, 0], xy[:, 1]
    u = amplitude * np.sin(2 * np.pi * y / h) * np.cos(2 * np.pi * x / w)
    v = amplitude * np.cos(2 * np.pi * x / w) * np.sin(2 * np.pi * y / h)
    return np.stack([u, v], axis=1)


def distorted_dots(rng, shape, xy, *, diameter=3.0, strength=0.4, rays=48):
    """Dots seen through a sharp interface inside the light cone: each dot is ``rays`` spots of equal weight
    (its rays through the aperture), each displaced by ``strength * tanh((a . n - c) / 0.15)`` along ``n``
    for aperture points ``a`` in the unit disk, with a random direction ``n`` and interface offset ``c``
    per dot. The image is skewed, not just spread; the truth is the mean landing position of the rays.

    Returns
    -------
    image : (H, W) float64 array
    mean_xy : (N, 2) array
        Each dot's mean ray landing position.
    """
    from synthbos.raytrace.dots import draw_dots

    n = len(xy)
    r = np.sqrt(rng.uniform(0, 1, (n, rays)))
    t = rng.uniform(0, 2 * np.pi, (n, rays))
    a = np.stack([r * np.cos(t), r * np.sin(t)], axis=-1)
    phi = rng.uniform(0, 2 * np.pi, n)
    normal = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    c = rng.uniform(-0.6, 0.6, n)
    along = strength * np.tanh((np.einsum("nkd,nd->nk", a, normal) - c[:, None]) / 0.15)
    landing = xy[:, None, :] + along[..., None] * normal[:, None, :]
    image = draw_dots(shape, landing.reshape(-1, 2), diameter, intensity=1.0 / rays)
    return image, landing.mean(axis=1)


def fitted_pair(reference, gradient, xy, truth, device):
    """The model fit of both images, started at the truth, and the step's keywords."""
    n = len(xy)
    half, render_half = fit_window_half(0.75)
    start = np.column_stack([np.r_[xy, xy + truth], np.ones(2 * n), np.full(2 * n, 0.75), np.zeros(2 * n)])
    frame = np.r_[np.zeros(n, int), np.ones(n, int)]
    partner = np.r_[np.arange(n) + n, np.arange(n)]
    params, _, _ = fit_dots([reference, gradient], start, half=half, render_half=render_half, frame=frame,
                            partner=partner, iterations=3, device=device)  # fmt: skip
    return params, {"half": render_half, "frame": frame, "partner": partner, "noise": (0.0, 0.0)}
