"""Is a background pattern periodic? The lattice test that chooses the peak handling of the correlation.

A regular dot grid (or any periodic pattern) correlates with itself at every lattice vector: each
correlation plane has secondary peaks as high as the true one (the FFT correlation is circular), so
the peak ratio tells nothing and the highest peak may lie a lattice vector away from the truth.
:func:`lattice_peak` measures that property on the reference image; :func:`correlate_pair` then judges
its peaks differently (``CorrelationSettings.pattern``).
"""

from __future__ import annotations

import numpy as np
from scipy import fft

from .windows import extract_windows, window_starts

__all__ = ["PERIODIC_PEAK", "SAMPLE_WINDOWS", "is_periodic", "lattice_peak"]

#: A pattern is periodic when its mean window autocorrelation (1 at zero lag) has a local maximum
#: at least this high away from zero lag. Regular dot grids of 3 px dots with pitches of 6-12 px in
#: 32 px windows give 0.9 and more with noise of 2 % of the dots' peak, 0.5-0.85 with 10 %; random
#: dots (20 per 32 x 32 px) and the particle images of the PIV pairs of ``benchmarks/bench_openpiv.py``
#: 0.01-0.035. Jittered grids lie between: with 3 px dots at pitches of 6-10 px, a jitter of +-1.5 px
#: gives 0.26-0.44 and +-1 px 0.43-0.66 (0 and 10 % noise). Such a pattern is judged random up to
#: +-1.5 px, so that a displacement beyond half its pitch is still found by larger windows.
PERIODIC_PEAK = 0.45

#: At most this many windows (evenly spread over the image) enter the mean autocorrelation.
SAMPLE_WINDOWS = 256


def lattice_peak(image, size):
    """Highest secondary maximum of the mean autocorrelation of ``size`` px windows of an image.

    Parameters
    ----------
    image : (H, W) array
        The reference image.
    size : int
        Window size (px), at most the image's smaller side.

    Returns
    -------
    height : float
        The highest local maximum (over its 8 neighbours) of the normalised autocorrelation at lags
        up to ``size // 2`` px other than zero lag, 0 if there is none; 1 for a perfectly periodic
        pattern.
    lag : (2,) int array
        Its lag (rows, columns) in px.

    Notes
    -----
    Each window is brought to zero mean and zero-padded to twice its size, so that the
    autocorrelation is linear; the mean power spectrum over the windows gives the mean
    autocorrelation, which is divided by the number of pixel pairs at each lag and by its value at
    zero lag. The central lobe of a dot decreases away from zero lag and has no other maximum.

    Examples
    --------
    >>> import numpy as np
    >>> y, x = np.mgrid[0:128, 0:128]
    >>> grid = np.cos(2 * np.pi * x / 8) * np.cos(2 * np.pi * y / 8)
    >>> height, lag = lattice_peak(grid, 32)
    >>> bool(height > 0.9), bool(np.all(lag % 4 == 0))  # a vector of its lattice (4, 4), (8, 0), ...
    (True, True)
    """
    img = np.asarray(image, dtype=np.float64)
    h, w = img.shape
    sy, sx = window_starts(h, size, size), window_starts(w, size, size)
    step_y = max(1, int(np.ceil(len(sy) / np.sqrt(SAMPLE_WINDOWS))))
    step_x = max(1, int(np.ceil(len(sx) / np.sqrt(SAMPLE_WINDOWS))))
    ny, nx = len(sy[::step_y]), len(sx[::step_x])
    win = extract_windows(img, size, size, int(sy[0]), int(sx[0]), len(sy), len(sx))
    win = win[::step_y, ::step_x].reshape(ny * nx, size, size)
    win = win - win.mean(axis=(-2, -1), keepdims=True)
    spec = fft.rfft2(win, s=(2 * size, 2 * size))
    power = np.mean(spec.real**2 + spec.imag**2, axis=0)
    auto = fft.fftshift(fft.irfft2(power, s=(2 * size, 2 * size)))
    lags = np.arange(-size, size)
    pairs = (size - np.abs(lags))[:, None] * (size - np.abs(lags))[None, :]
    auto = np.divide(auto, pairs, out=np.zeros_like(auto), where=pairs > 0)
    if auto[size, size] <= 0:
        return 0.0, np.zeros(2, dtype=int)
    half = size // 2
    core = auto[size - half - 1 : size + half + 2, size - half - 1 : size + half + 2] / auto[size, size]
    inner = core[1:-1, 1:-1]
    peak = np.ones(inner.shape, dtype=bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                peak &= inner >= core[1 + dy : core.shape[0] - 1 + dy, 1 + dx : core.shape[1] - 1 + dx]
    peak[half, half] = False
    if not peak.any():
        return 0.0, np.zeros(2, dtype=int)
    values = np.where(peak, inner, -np.inf)
    r, c = np.unravel_index(np.argmax(values), values.shape)
    return float(values[r, c]), np.array([r - half, c - half])


def is_periodic(image, size):
    """Whether the pattern of ``image`` repeats within ``size`` px windows (:func:`lattice_peak` >= ``PERIODIC_PEAK``).

    Examples
    --------
    >>> import numpy as np
    >>> is_periodic(np.random.default_rng(0).random((128, 128)), 32)
    False
    """
    return lattice_peak(image, size)[0] >= PERIODIC_PEAK
