"""Sensor noise and digitisation, applied to noise-free renders after the fact.

A render is stored noise-free in float32 so that one render serves every noise level: ``add_noise``
adds zero-mean Gaussian noise whose standard deviation is a percentage of the peak intensity,
reproducibly from a seed, and optionally quantises to a bit depth with saturation.

A campaign adds the noise of one seed to one image once per method; the standard normal draws of the
last few (integer) seeds are remembered, so the later methods only scale and add them. The noise is
bit for bit ``numpy.random.default_rng(seed).normal(0, sigma, shape)``, which draws
``0 + sigma * z`` from the same standard normal stream.
"""

from __future__ import annotations

import numbers

import numpy as np

from synthbos import SynthbosError
from synthbos.memo import RecentResults

__all__ = ["add_noise"]


def add_noise(image, *, percent, seed, peak=None, bit_depth=0, full_scale=None):
    """Add seeded Gaussian sensor noise (and optionally quantise) to a noise-free image.

    Parameters
    ----------
    image : (H, W) array
        Noise-free intensities.
    percent : float
        Noise standard deviation in percent of ``peak``.
    seed : int
        Seed of the noise; the same seed gives the same noise.
    peak : float, optional
        Reference intensity of the percentage; the image maximum if None.
    bit_depth : int
        0 keeps float values; otherwise values are scaled so that ``full_scale`` maps to
        ``2**bit_depth - 1`` counts, rounded and clipped to [0, 2**bit_depth - 1] (saturation).
    full_scale : float, optional
        Intensity that saturates the sensor; ``peak`` if None.

    Returns
    -------
    (H, W) float32 array
        In intensity units when ``bit_depth == 0``, else in counts.
    """
    img = np.asarray(image, dtype=np.float64)
    if not np.isfinite(img).all():
        raise SynthbosError("image has non-finite pixels")
    if not np.isfinite(percent) or percent < 0:
        raise SynthbosError(f"noise percent must be a finite number >= 0, got {percent}")
    ref = float(img.max()) if peak is None else float(peak)
    if percent > 0 and ref < 0:
        raise SynthbosError(f"the noise's reference intensity must be >= 0, got {ref}")
    noisy = img + (0.0 + (percent / 100.0 * ref) * _standard_normal(seed, img.shape)) if percent > 0 else img.copy()
    if bit_depth:
        if not 1 <= int(bit_depth) <= 32:
            raise SynthbosError(f"bit depth must be between 1 and 32, got {bit_depth}")
        top = 2.0 ** int(bit_depth) - 1.0
        scale = top / (ref if full_scale is None else float(full_scale))
        noisy = np.clip(np.round(noisy * scale), 0.0, top)
    return noisy.astype(np.float32)


def _standard_normal(seed, shape):
    """``default_rng(seed).standard_normal(shape)``, remembered for the last few integer seeds (read-only)."""
    if isinstance(seed, numbers.Integral) and not isinstance(seed, bool):
        return _draws.get([], lambda: _draw(int(seed), shape), extra=(int(seed), tuple(int(n) for n in shape)))
    return np.random.default_rng(seed).standard_normal(size=shape)


def _draw(seed, shape):
    z = np.random.default_rng(seed).standard_normal(size=shape)
    z.flags.writeable = False
    return z


_draws = RecentResults(8)  # a campaign's noise level: two images, three methods
