"""The user's pixel mask: its check, the fill of the excluded pixels and the reach of the excluded area.

A mask (True = excluded) changes four steps, in their rooms: the images' excluded pixels are filled with
the median of the others (:func:`masked_fill`, so no dot is found there), the noise is estimated from the
differences of pixels both kept (``identify.estimate_noise``), the predictor leaves the excluded pixels
out of its correlation (``predict.predict_displacement``), and the table marks MASKED every dot whose
prior, reference or gradient position lies within a dot radius of the excluded area (:func:`mask_reach`,
:func:`touches`; on a stack of pairs ``table_kernels.masked_rows``).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from synthbos.correlation.windows import checked_mask

from synthbos import SynthbosError

__all__ = ["check_mask", "mask_reach", "masked_fill", "touches"]


def check_mask(mask, shape):
    """The mask as a bool array of ``shape`` (True = excluded), or None; refused where it excludes every
    pixel (or has another shape, or values neither boolean nor finite numbers)."""
    m = checked_mask(mask, shape)
    if m is not None and m.all():
        raise SynthbosError("the mask excludes every pixel: nothing can be tracked")
    return m


def masked_fill(image, mask):
    """The image with its excluded pixels set to the median of the others (no dot is found there)."""
    out = image.copy()
    out[mask] = np.median(image[~mask])
    return out


def _disk(radius):
    r = int(np.ceil(radius))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return xx * xx + yy * yy <= radius * radius + 1e-9


def mask_reach(excluded, diameter):
    """The pixels within half a dot ``diameter`` of an excluded one (the excluded area dilated by that
    disk): a dot whose rounded position lies there is MASKED."""
    return ndimage.binary_dilation(excluded, structure=_disk(diameter / 2.0))


def touches(mask_near, xy):
    """True where the rounded position lies on ``mask_near`` (outside the image: False)."""
    h, w = mask_near.shape
    fin = np.isfinite(xy).all(axis=1)
    c = np.rint(np.where(fin, xy[:, 0], -1.0)).astype(np.int64)
    r = np.rint(np.where(fin, xy[:, 1], -1.0)).astype(np.int64)
    inside = fin & (c >= 0) & (c < w) & (r >= 0) & (r < h)
    out = np.zeros(len(xy), dtype=bool)
    out[inside] = mask_near[r[inside], c[inside]]
    return out
