"""Dot patterns on the target, specified in the image plane.

The density of a pattern is given as dots per 32 x 32 px window and its dots' image diameter in
pixels, as PIV and BOS practice does; positions are chosen in pixel coordinates and carried to the
target through the camera's paraxial mapping.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from synthbos import SynthbosError

__all__ = ["grid_pattern", "random_pattern"]


def grid_pattern(width, height, dots_per_32px):
    """Regular square lattice of spacing 32 / sqrt(density) px, centred in a W x H image.

    Returns (N, 2) pixel positions (x = column, y = row).
    """
    spacing = 32.0 / np.sqrt(dots_per_32px)
    nx, ny = int(np.floor(width / spacing)), int(np.floor(height / spacing))
    if nx < 1 or ny < 1:
        raise SynthbosError(f"a grid of spacing {spacing:.2f} px does not fit a {width} x {height} px image")
    x = (width - 1) / 2.0 + (np.arange(nx) - (nx - 1) / 2.0) * spacing
    y = (height - 1) / 2.0 + (np.arange(ny) - (ny - 1) / 2.0) * spacing
    X, Y = np.meshgrid(x, y)
    return np.stack([X.ravel(), Y.ravel()], axis=1)


def random_pattern(width, height, dots_per_32px, *, min_spacing, seed):
    """Random non-overlapping dots by random sequential addition.

    Candidates are drawn uniformly over the image in batches; each is kept unless it falls within
    ``min_spacing`` px of a dot already kept. The count is ``round(density * W * H / 1024)``.

    Returns (N, 2) pixel positions (x = column, y = row).
    """
    n_target = round(dots_per_32px * width * height / 1024.0)
    if n_target < 1:
        raise SynthbosError(f"{dots_per_32px} dots per 32x32 px gives no dot in a {width} x {height} px image")
    packing = n_target * np.pi * (min_spacing / 2.0) ** 2 / (width * height)
    if packing > 0.45:
        raise SynthbosError(
            f"{n_target} non-overlapping dots {min_spacing:g} px apart cover {packing:.0%} of the image;"
            " random sequential addition stalls above ~45%: lower the density or the dot spacing"
        )
    rng = np.random.default_rng(seed)
    kept = np.empty((0, 2))
    for _ in range(200):
        need = n_target - len(kept)
        if need == 0:
            break
        cand = rng.uniform([-0.5, -0.5], [width - 0.5, height - 0.5], size=(max(2 * need, 64), 2))
        if len(kept) and min_spacing > 0:
            d, _ = cKDTree(kept).query(cand, k=1)
            cand = cand[d >= min_spacing]
        # Among the new candidates, keep each one only if no earlier candidate of the batch is too near.
        if min_spacing > 0 and len(cand) > 1:
            pairs = cKDTree(cand).query_pairs(min_spacing, output_type="ndarray")
            drop = np.zeros(len(cand), bool)
            for i, j in pairs[np.argsort(pairs[:, 1], kind="stable")]:
                if not drop[i]:
                    drop[j] = True
            cand = cand[~drop]
        kept = np.vstack([kept, cand[:need]])
    if len(kept) < n_target:
        raise SynthbosError(f"could only place {len(kept)} of {n_target} non-overlapping dots")
    return kept
