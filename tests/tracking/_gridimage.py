"""A drawn camera image of a calibration dot grid, as a real one looks: 12-bit counts, illumination that
falls off towards the image centre, shot and read noise, a small rotation, barrel distortion, a few dots
missing and a few spurious blobs (dust). Returns the image and the truth (positions, lattice indices)."""

import numpy as np
from scipy.spatial import cKDTree
from synthbos.raytrace.dots import draw_dots


def real_like_grid(shape=(1024, 1024), pitch=9.0, *, seed=0, diameter=4.0, angle_deg=1.5, barrel_px=6.0,
                   centre_level=0.25, n_missing=60, n_spurious=40, dark=False, full_scale=3000.0, tilt=0.0):
    """A grid image and its truth.

    Parameters
    ----------
    shape : (H, W)
    pitch : float
        Grid spacing in px at the image centre.
    seed : int
        Seeds the noise, the missing dots and the spurious blobs.
    diameter : float
        Dot e^-2 diameter, px.
    angle_deg : float
        Rotation of the grid.
    barrel_px : float
        Barrel distortion: a dot at the image corner is drawn this many px nearer the centre.
    centre_level : float
        Illumination at the image centre relative to the corners (dim centre).
    n_missing, n_spurious : int
        Dots left out, and blobs drawn off the lattice.
    dark : bool
        Dark dots on a bright background (a printed grid in reflected light).
    full_scale : float
        Counts of a dot (or the background when ``dark``) at full illumination.
    tilt : float
        Perspective: the grid's scale changes by this fraction from the image centre to its right edge.

    Returns
    -------
    image : (H, W) uint16 array
        12-bit counts.
    xy : (N, 2) float array
        Positions (px) of the lattice dots drawn whose centre lies inside the image.
    ij : (N, 2) int array
        Their lattice indices (i along x, j along y; (0, 0) nearest the image centre).
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    cx, cy = (w - 1) / 2 + 0.31, (h - 1) / 2 - 0.23
    n = int(0.8 * max(h, w) / pitch) + 3
    gi, gj = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    ij = np.stack([gi.ravel(), gj.ravel()], axis=1)
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    u = pitch * (c * ij[:, 0] - s * ij[:, 1])
    v = pitch * (s * ij[:, 0] + c * ij[:, 1])
    r_corner = np.hypot(w / 2, h / 2)
    k = barrel_px / r_corner**3
    shrink = 1.0 - k * (u**2 + v**2)
    persp = 1.0 / (1.0 - tilt * u / (w / 2))
    xy = np.stack([cx + u * shrink * persp, cy + v * shrink * persp], axis=1)
    near = (xy[:, 0] > -5) & (xy[:, 0] < w + 4) & (xy[:, 1] > -5) & (xy[:, 1] < h + 4)
    xy, ij = xy[near], ij[near]
    inside = (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
    interior = np.flatnonzero(inside & (xy[:, 0] > 20) & (xy[:, 0] < w - 21) & (xy[:, 1] > 20) & (xy[:, 1] < h - 21))
    drop = rng.choice(interior, n_missing, replace=False)
    drawn = np.ones(len(xy), dtype=bool)
    drawn[drop] = False
    dots = draw_dots(shape, xy[drawn], diameter, intensity=rng.uniform(0.9, 1.1, drawn.sum()))
    # spurious blobs: dust of random size and brightness, off the lattice dots
    spur = rng.uniform([10, 10], [w - 10, h - 10], (4 * n_spurious, 2))
    spur = spur[cKDTree(xy).query(spur)[0] > 0.35 * pitch][:n_spurious]
    dots = draw_dots(shape, spur, rng.uniform(2.0, 9.0, len(spur)), intensity=rng.uniform(0.4, 1.2, len(spur)),
                     out=dots)
    rows, cols = np.indices(shape)
    rr = np.hypot(cols - cx, rows - cy) / r_corner
    light = centre_level + (1.0 - centre_level) * rr**2
    dots = np.clip(dots, 0.0, 1.0)
    signal = full_scale * light * ((1.0 - 0.85 * dots) if dark else (0.06 + 0.94 * dots))
    counts = 100.0 + rng.poisson(signal) + rng.normal(0.0, 4.0, shape)
    image = np.clip(np.round(counts), 0, 4095).astype(np.uint16)
    keep = drawn & inside
    return image, xy[keep], ij[keep]
