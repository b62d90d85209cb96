"""FFT cross-correlation of stacks of small windows: standard and robust phase correlation."""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

__all__ = ["cross_correlate", "robust_phase_correlate", "rpc_spectral_filter"]


def _real_stacks(a, b):
    a = np.asarray(a)
    b = np.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"window stacks differ in shape: {a.shape} and {b.shape}")
    # float32 stays float32 (half the memory traffic, twice the FFT speed); anything else -> float64
    dtype = np.float32 if (a.dtype == np.float32 and b.dtype == np.float32) else np.float64
    return a.astype(dtype, copy=False), b.astype(dtype, copy=False)


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
    (..., h, w) float array
        The correlation plane (float32 when both inputs are float32, float64 otherwise), shifted
        so that zero displacement sits at index ``(h // 2, w // 2)``; a peak at
        ``(h // 2 + dy, w // 2 + dx)`` means ``b`` is ``a`` moved by ``(dx, dy)``.
    """
    a, b = _real_stacks(a, b)
    h, w = a.shape[-2:]
    fa = sfft.rfft2(a, axes=(-2, -1), workers=workers)
    fb = sfft.rfft2(b, axes=(-2, -1), workers=workers)
    spec = np.conj(fa, out=fa)
    spec *= fb
    if subtract_mean:
        # a window's mean lives in its DC bin only: zeroing the cross spectrum's DC bin correlates the
        # mean-subtracted windows (the correlation sum of two zero-mean windows is unchanged)
        spec[..., 0, 0] = 0.0
    corr = _shifted_inverse(spec, (h, w), workers)
    if normalize:
        if subtract_mean:
            a = a - a.mean(axis=(-2, -1), keepdims=True)
            b = b - b.mean(axis=(-2, -1), keepdims=True)
        norm = np.sqrt((a * a).sum(axis=(-2, -1)) * (b * b).sum(axis=(-2, -1)))
        corr = corr / np.where(norm > 0, norm, 1.0)[..., None, None]
    return corr


def _shift_signs(shape, dtype):
    """``(-1)^(ky + kx)`` on a half spectrum: multiplying by it moves the inverse by (h/2, w/2)."""
    h, w = shape
    return np.where((np.arange(h)[:, None] + np.arange(w // 2 + 1)[None, :]) % 2 == 0, 1, -1).astype(dtype)


def _shifted_inverse(spec, shape, workers):
    """Inverse real FFT of a half spectrum, laid out with zero displacement at ``(h // 2, w // 2)``.

    For even sizes the half-size circular shift (``fftshift``) is folded into the spectrum as a sign
    pattern, which costs one multiplication instead of a copy of the planes. ``spec`` is overwritten.
    """
    h, w = shape
    if h % 2 == 0 and w % 2 == 0:
        spec *= _shift_signs(shape, spec.real.dtype)
        return sfft.irfft2(spec, s=(h, w), axes=(-2, -1), workers=workers, overwrite_x=True)
    corr = sfft.irfft2(spec, s=(h, w), axes=(-2, -1), workers=workers, overwrite_x=True)
    return np.fft.fftshift(corr, axes=(-2, -1))


def rpc_spectral_filter(shape, diameter, *, half=True):
    """Spectral energy filter of robust phase correlation for a real-FFT half spectrum.

    Parameters
    ----------
    shape : (h, w)
        Window shape.
    diameter : float
        e^-2 diameter of the particle (dot) images in pixels.
    half : bool
        The half spectrum of a real FFT (default), or with False the full (h, w) spectrum of a
        complex FFT (bins in ``numpy.fft.fft`` order).

    Returns
    -------
    (h, w // 2 + 1) or (h, w) float array
        ``exp(-pi^2 d^2 |f|^2 / 4)``, ``f`` in cycles per pixel: the energy spectrum of a Gaussian
        dot of ``sigma = d / 4`` (Eckstein and Vlachos, Meas. Sci. Technol. 20 (2009) 075402, eq. 9),
        which turns the phase-only correlation into a Gaussian peak of a dot's autocorrelation width.
    """
    h, w = shape
    fy = sfft.fftfreq(h)[:, None]
    fx = (sfft.rfftfreq(w) if half else sfft.fftfreq(w))[None, :]
    return np.exp(-(np.pi**2) * diameter**2 * (fx * fx + fy * fy) / 4.0)


def robust_phase_correlate(a, b, *, diameter=2.8, subtract_mean=True, workers=1):
    """Robust phase correlation (RPC) of window pairs, batched over the leading axes.

    Parameters
    ----------
    a, b : (..., h, w) arrays
        First- and second-frame windows.
    diameter : float
        Dot diameter setting the spectral filter (:func:`rpc_spectral_filter`).
    subtract_mean : bool
        Remove each window's mean first.
    workers : int
        Threads for ``scipy.fft``.

    Returns
    -------
    (..., h, w) float array
        Correlation plane laid out as in :func:`cross_correlate`.

    Notes
    -----
    The cross spectrum is normalised to unit magnitude (only phase is kept, which whitens the dot
    pattern) and weighted by the dot's energy spectrum, which suppresses the noisy high
    frequencies (Eckstein and Vlachos 2009, eqs. 7-9).
    """
    a, b = _real_stacks(a, b)
    if subtract_mean:
        a = a - a.mean(axis=(-2, -1), keepdims=True)
        b = b - b.mean(axis=(-2, -1), keepdims=True)
    h, w = a.shape[-2:]
    fa = sfft.rfft2(a, axes=(-2, -1), workers=workers)
    fb = sfft.rfft2(b, axes=(-2, -1), workers=workers)
    spec = np.conj(fa) * fb
    mag = np.abs(spec)
    tiny = np.finfo(mag.dtype).tiny
    spec = spec / np.maximum(mag, tiny) * rpc_spectral_filter((h, w), diameter).astype(mag.dtype)
    return _shifted_inverse(spec, (h, w), workers)
