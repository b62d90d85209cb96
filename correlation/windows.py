"""Interrogation-window grids (:class:`WindowGrid`), batched window extraction, and the check of a user's pixel mask."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from synthbos import SynthbosError

__all__ = [
    "WindowGrid",
    "checked_mask",
    "extract_windows",
    "window_grid",
    "window_starts",
    "window_step",
    "window_validity",
]


def checked_mask(mask, shape):
    """A user's pixel mask as a bool array of the images' ``shape`` (True = excluded), or None.

    Raises :class:`synthbos.SynthbosError` for another shape, or values that are neither boolean nor
    finite numbers.
    """
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.shape != shape:
        raise SynthbosError(f"mask has shape {m.shape} but the images are {shape}")
    if m.dtype.kind not in "biuf" or (m.dtype.kind == "f" and not np.all(np.isfinite(m))):
        raise SynthbosError("mask must be a finite boolean or 0/1 array (True = excluded)")
    return m.astype(bool)


def window_step(size, overlap):
    """Grid spacing in pixels of windows of ``size`` pixels overlapping by the fraction ``overlap``."""
    return max(1, round(size * (1.0 - overlap)))


def window_starts(length, size, step):
    """First pixel of each window along one axis, the grid centred in the image.

    Parameters
    ----------
    length : int
        Image extent along the axis.
    size, step : int
        Window size and spacing.

    Returns
    -------
    (n,) int array
        ``margin + step * arange(n)`` with ``n = (length - size) // step + 1`` and the leftover
        pixels split evenly between both ends. Window ``k`` covers pixels ``start[k] ...
        start[k] + size - 1``; its centre is ``start[k] + (size - 1) / 2``.
    """
    n = (length - size) // step + 1
    margin = (length - size - (n - 1) * step) // 2
    return margin + step * np.arange(n)


def extract_windows(image, size, step, row0, col0, ny, nx):
    """All ``ny x nx`` windows of a regular grid, as a strided view.

    Parameters
    ----------
    image : (H, W) array
    size, step : int
        Window size and grid spacing.
    row0, col0 : int
        First pixel of the first window.
    ny, nx : int
        Number of windows along rows and columns.

    Returns
    -------
    (ny, nx, size, size) array
        A read-only view into ``image`` (no copy).
    """
    view = sliding_window_view(image, (size, size))
    return view[row0 : row0 + (ny - 1) * step + 1 : step, col0 : col0 + (nx - 1) * step + 1 : step]


@dataclass(frozen=True)
class WindowGrid:
    """Window grid of one pass: spacing, window centres and the pixel rows and columns the windows cover."""

    size: int
    step: int
    yc: np.ndarray
    xc: np.ndarray
    rows: np.ndarray
    cols: np.ndarray


def window_grid(shape, size, overlap):
    """The :class:`WindowGrid` of ``size`` px windows overlapping by ``overlap`` in an image of ``shape``."""
    step = window_step(size, overlap)
    sy, sx = window_starts(shape[0], size, step), window_starts(shape[1], size, step)
    return WindowGrid(
        size=size,
        step=step,
        yc=sy + (size - 1) / 2.0,
        xc=sx + (size - 1) / 2.0,
        rows=np.arange(sy[0], sy[-1] + size),
        cols=np.arange(sx[0], sx[-1] + size),
    )


def window_validity(valid_px, grid):
    """Pixel weights of every window of ``grid`` and the windows more than half masked.

    Parameters
    ----------
    valid_px : (H, W) float32 array of 0 and 1, or None
        1 on the pixels that take part in the correlation; None: all do.
    grid : WindowGrid

    Returns
    -------
    win_valid : (K, N, N) array or None
        The weights of the K = ny nx windows (a view of ``valid_px``); None without a mask.
    masked : (ny, nx) bool array
        Windows with less than half of their pixels valid.

    Raises
    ------
    synthbos.SynthbosError
        When every window is masked.
    """
    ny, nx, size = len(grid.yc), len(grid.xc), grid.size
    if valid_px is None:
        return None, np.zeros((ny, nx), dtype=bool)
    r0, c0 = int(grid.rows[0]), int(grid.cols[0])
    win_valid = extract_windows(valid_px, size, grid.step, r0, c0, ny, nx).reshape(-1, size, size)
    masked = (win_valid.mean(axis=(-2, -1)) < 0.5).reshape(ny, nx)
    if masked.all():
        raise SynthbosError(f"the mask covers every {size} px window: no vector can be measured")
    return win_valid, masked
