"""FFT cross-correlation of stacks of small windows."""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

__all__ = ["cross_correlate"]


def cross_correlate(a, b, *, subtract_mean=True, normalize=False, workers=1):
    """Circular cross-correlation of window pairs, batched over the leading axes.

    Parameters
    ----------
    a, b : (..., h, w) arrays
        First- and second-frame windows.
    subtract_mean : bool
        Remove each window's mean first.
    normalize : bool
        Divide by ``sqrt(sum a^2 sum b^2)`` so a perfect match peaks at 1.
    workers : int
        Threads for ``scipy.fft``.

    Returns
    -------
    (..., h, w) float64 array
        The correlation plane, shifted so that zero displacement sits at index ``(h // 2, w // 2)``;
        a peak at ``(h // 2 + dy, w // 2 + dx)`` means ``b`` is ``a`` moved by ``(dx, dy)``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"window stacks differ in shape: {a.shape} and {b.shape}")
    if subtract_mean:
        a = a - a.mean(axis=(-2, -1), keepdims=True)
        b = b - b.mean(axis=(-2, -1), keepdims=True)
    h, w = a.shape[-2:]
    fa = sfft.rfft2(a, axes=(-2, -1), workers=workers)
    fb = sfft.rfft2(b, axes=(-2, -1), workers=workers)
    corr = sfft.irfft2(np.conj(fa) * fb, s=(h, w), axes=(-2, -1), workers=workers)
    corr = np.fft.fftshift(corr, axes=(-2, -1))
    if normalize:
        norm = np.sqrt((a * a).sum(axis=(-2, -1)) * (b * b).sum(axis=(-2, -1)))
        corr = corr / np.where(norm > 0, norm, 1.0)[..., None, None]
    return corr
