"""Phase correlation on a grid of windows: an example synthbos method plugin.

Each window of the reference image and the same window of the gradient image are Fourier transformed;
the inverse transform of their cross-power spectrum, normalised to unit magnitude, peaks at the
window's displacement (Kuglin and Hines 1975). The normalised spectrum is weighted by that of a
Gaussian of ``width`` px, which makes the peak that Gaussian (as robust phase correlation does,
Eckstein and Vlachos 2009), and a three-point Gaussian fit in x and in y finds its sub-pixel
position. One pass, no window deformation: a baseline to beat. Installed, it is the method
``phase-correlation`` of every synthbos command (the entry point in ``pyproject.toml``).
"""

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from synthbos.benchmarks.method_api import GRID, Method, grid_result


@dataclass(frozen=True)
class PhaseCorrelationSettings:
    window: int = 32  # window size (px)
    step: int = 16  # distance between window centres (px)
    width: float = 1.0  # standard deviation of the correlation peak (px)

    def __post_init__(self):
        if not (isinstance(self.window, int) and self.window >= 8 and 1 <= self.step <= self.window):
            raise ValueError(f"need a window >= 8 px and 1 <= step <= window, got {self.window}, {self.step}")


def _gauss3(lo, mid, hi):
    """Sub-pixel offset of a peak from three samples (three-point Gaussian fit)."""
    lo, mid, hi = (np.log(np.maximum(v, 1e-12)) for v in (lo, mid, hi))
    return (lo - hi) / (2 * (lo - 2 * mid + hi) - 1e-12)


def run(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
    s = settings or PhaseCorrelationSettings()
    w = s.window
    a, b = (sliding_window_view(np.asarray(im, float), (w, w))[::s.step, ::s.step] for im in (reference, gradient))
    a, b = a - a.mean(axis=(-2, -1), keepdims=True), b - b.mean(axis=(-2, -1), keepdims=True)
    cross = np.conj(np.fft.rfft2(a)) * np.fft.rfft2(b)
    k2 = np.fft.fftfreq(w)[:, None] ** 2 + np.fft.rfftfreq(w)[None, :] ** 2  # (cycles / px)^2
    spectrum = cross / (np.abs(cross) + 1e-12) * np.exp(-2 * np.pi**2 * s.width**2 * k2)
    plane = np.fft.fftshift(np.fft.irfft2(spectrum, s=(w, w)), axes=(-2, -1))
    ny, nx = plane.shape[:2]
    flat = plane.reshape(ny, nx, -1).argmax(axis=-1)
    i, j = np.clip(flat // w, 1, w - 2), np.clip(flat % w, 1, w - 2)
    r, c = np.ogrid[:ny, :nx]
    dy = _gauss3(plane[r, c, i - 1, j], plane[r, c, i, j], plane[r, c, i + 1, j])
    dx = _gauss3(plane[r, c, i, j - 1], plane[r, c, i, j], plane[r, c, i, j + 1])
    y, x = np.meshgrid(np.arange(ny) * s.step + (w - 1) / 2, np.arange(nx) * s.step + (w - 1) / 2, indexing="ij")
    return grid_result("phase-correlation", x, y, j + dx - w // 2, i + dy - w // 2, settings=s)


METHOD = Method("phase-correlation", GRID, PhaseCorrelationSettings, run, label="phase correlation (32 px)",
                color="#F0E442", linestyle=(0, (6, 2, 1, 2)), marker="*")
