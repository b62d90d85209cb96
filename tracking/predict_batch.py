"""The correlation predictor of :mod:`tracking.predict` for a batch of image pairs, on one Warp device.

:func:`predict_displacement_batch` runs :func:`tracking.predict.predict_displacement` (without a mask)
for B pairs at once: every pass is a fixed sequence of launches of :mod:`tracking.predict_kernels`
over all pairs, the images, fields and results stay on the device, and nothing waits for the host
(the host only loops over the passes). The pyramid still ends pair by pair: a pair whose field a pass
changed little is left alone by the later passes (the kernels read which pairs run from the per-pair,
per-pass ``changed`` flags), and its displacement and significance are computed from the planes of the
pass at which it stopped, as the host does for it alone.

The host function is the reference: the correlations differ by float32 rounding (Warp's tile FFTs or
direct DFTs here, SciPy's pocketfft there), which can at times flip a whole-pixel rounding of the
deformation or a tie of the peak search; otherwise the steps are the same arithmetic.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import predict_fft_kernels as fk
from . import predict_kernels as pk
from .predict import _sparse_grid, _sparse_tile_grid, _tile_grid, pooling_block
from .workspace import on_device

__all__ = ["correlate_tiles", "predict_displacement_batch", "uses_tile_fft"]

#: Rows (or columns) of a tile that one block of the tile-FFT kernels transforms (at most the tile size).
FFT_ROWS = 8

#: The smallest tile size correlated by Warp's tile FFT (powers of two only); smaller tiles, and sizes
#: that are not powers of two, by direct DFTs, one thread per sample (a tile FFT's block would be a few
#: threads there).
FFT_FROM = 32

_kernels: dict = {}  # (what, size) -> kernel(s)
_twiddles: dict = {}
_spectral: dict = {}  # (size, device) -> spectral factors


def uses_tile_fft(size):
    """Whether passes of ``size`` px tiles correlate by Warp's tile FFT (a power of two from
    ``FFT_FROM``), else by direct DFTs (any size, such as 24 px from sparse patterns)."""
    return size >= FFT_FROM and size & (size - 1) == 0


def _kernel(what, size):
    """The pass's ``"centre"`` kernel, or its three ``"fft"`` kernels, built once per size."""
    key = (what, size)
    if key not in _kernels:
        if what == "centre":
            _kernels[key] = fk.make_centre_tiles(size)
        else:
            _kernels[key] = fk.make_tile_fft_steps(size, _fft_rows(size))
    return _kernels[key]


def _twiddle(size, device):
    """exp(-2 pi i m / size), m = 0 ... size - 1, as float32 pairs on ``device`` (uploaded once)."""
    key = (size, str(device))
    if key not in _twiddles:
        m = np.arange(size)
        w = np.exp(-2j * np.pi * m / size)
        _twiddles[key] = wp.array(np.stack([w.real, w.imag], axis=1).astype(np.float32), dtype=wp.vec2f, device=device)
    return _twiddles[key]


def _fft_rows(size):
    return min(size, FFT_ROWS)


def _centre_threads(size, device):
    """Threads per block of the centring kernel: a few samples each on a GPU; one on the CPU."""
    return 1 if device.is_cpu else min(256, max(size * size // 4, 1))


def _fft_threads(size, device):
    """Threads per block of the tile-FFT kernels: two samples of a row each on a GPU (Warp's tile FFT
    wants at least two); one on the CPU, whose sequential FFT is the fastest there."""
    return 1 if device.is_cpu else size // 2


def _search_block(size, first):
    """The peak search of a pass: the whole plane in the first pass, else the samples within a quarter
    tile of zero displacement (``predict_displacement``'s ``lo`` and ``m``)."""
    if first:
        return 0, size
    return size // 2 - size // 4, 2 * (size // 4) + 1


def _spectral_factors(size, device):
    """The spectral factors ``(-1)^(r + c) / size^2`` of a pass (the inverse FFT's scale and the shift
    of zero displacement to the plane's centre), on ``device`` (uploaded once per process)."""
    key = (size, str(device))
    if key not in _spectral:
        r, c = np.indices((size, size))
        spectral = (np.where((r + c) % 2 == 0, 1.0, -1.0) / (size * size)).astype(np.float32)
        _spectral[key] = wp.array(spectral, dtype=wp.float32, device=device)
    return _spectral[key]


def _grid(shape, size, sparse):
    """The :class:`predict_kernels.TileGrid` of a pass (``predict_displacement``'s tile grids)."""
    h, w = shape
    ys = _sparse_tile_grid(h, size) if sparse else _tile_grid(h, size)
    xs = _sparse_tile_grid(w, size) if sparse else _tile_grid(w, size)
    g = pk.TileGrid()
    g.top, g.left = int(ys[0]), int(xs[0])
    g.row_step = int(ys[1] - ys[0]) if len(ys) > 1 else size
    g.col_step = int(xs[1] - xs[0]) if len(xs) > 1 else size
    g.size, g.ny, g.nx = int(size), len(ys), len(xs)
    return g


def correlate_tiles(references, moved, weight, shift, changed, p, grid, device):
    """The correlation planes of pass ``p``'s tile pairs and their peaks, for the pairs that run the pass.

    Parameters
    ----------
    references : (B, H, W) float64 Warp array
        The reference images.
    moved, weight : (B, ny * size, nx * size) float32 Warp arrays
        The gradient image's tiles moved back by the coarser field, side by side, and their pixels'
        weights (1 inside the image), as :func:`predict_kernels.deform_tiles` writes them.
    shift : (B, ny * size, nx * size) ``wp.vec2f`` Warp array
        The whole-pixel shift of each moved pixel.
    changed : (B, passes) int32 Warp array
        Which pairs run the pass (:func:`predict_kernels.runs`).
    p : int
        The pass.
    grid : :class:`predict_kernels.TileGrid`
        The pass's tiles.
    device : warp.context.Device

    Returns
    -------
    planes : (B ny nx size, size) float32 Warp array
        Each tile pair's circular cross-correlation, zero displacement at ``(size // 2, size // 2)``.
    peak : (B, ny, nx) int32 Warp array
        The index (row * size + column) of each plane's first maximum over the pass's search block.
    norm, count, energy, base : (B, ny, nx) Warp arrays
        As :func:`predict_fft_kernels.make_centre_tiles` writes them.

    Notes
    -----
    Tile sizes that are powers of two from ``FFT_FROM`` go through Warp's tile FFT in three kernels of
    ``FFT_ROWS`` rows per block (:func:`predict_fft_kernels.make_tile_fft_steps`); other sizes through four
    kernels of direct DFTs over half the spectrum (the tiles are real), one thread per sample.
    """
    size = grid.size
    count_tiles = references.shape[0] * grid.ny * grid.nx
    per_tile = (references.shape[0], grid.ny, grid.nx)

    def empty(dtype, shape=per_tile):
        return wp.empty(shape, dtype=dtype, device=device)

    planes = empty(wp.float32, (count_tiles * size, size))
    centred = empty(wp.float32, (2, count_tiles * size, size))
    peak, norm, count, energy, base = (empty(t) for t in (wp.int32, wp.float64, wp.float32, wp.vec2d, wp.vec2d))
    inputs = [references, moved, weight, shift, changed, p, grid, centred, norm, count, energy, base]
    wp.launch_tiled(_kernel("centre", size), dim=[count_tiles], inputs=inputs, block_dim=_centre_threads(size, device),
                    device=device)  # fmt: skip
    if uses_tile_fft(size):
        rows_forward, columns, rows_inverse = _kernel("fft", size)
        spectra = empty(wp.vec2f, (2, size, count_tiles * size))
        cross = empty(wp.vec2f, (count_tiles * size, size))
        for kernel, inputs in (
            (rows_forward, [centred, changed, p, grid, spectra]),
            (columns, [spectra, _spectral_factors(size, device), changed, p, grid, cross]),
            (rows_inverse, [cross, changed, p, grid, planes]),
        ):
            wp.launch_tiled(kernel, dim=[count_tiles * (size // _fft_rows(size))], inputs=inputs,
                            block_dim=_fft_threads(size, device), device=device)  # fmt: skip
    else:
        tw = _twiddle(size, device)
        half = (count_tiles * size, size // 2 + 1)
        spectra = empty(wp.vec2f, (2, *half))
        cross = empty(wp.vec2f, half)
        for kernel, dim, inputs in (
            (fk.dft_rows, (2, *half), [centred, tw, changed, p, grid, spectra]),
            (fk.dft_columns_cross, half, [spectra, tw, _spectral_factors(size, device), changed, p, grid, cross]),
            (fk.dft_columns_inverse, half, [cross, tw, changed, p, grid, spectra[0]]),
            (fk.dft_rows_inverse_real, (count_tiles * size, size), [spectra[0], tw, changed, p, grid, planes]),
        ):
            wp.launch(kernel, dim=dim, inputs=inputs, device=device)
    lo, m = _search_block(size, p == 0)
    wp.launch(fk.search_peaks, dim=per_tile, inputs=[planes, changed, p, grid, lo, m, peak], device=device)
    return planes, peak, norm, count, energy, base


def predict_displacement_batch(references, gradients, xy, *, sizes, min_dots_per_box=20.0, density, device=None):
    """Predict each dot's displacement in each of B image pairs, and say how far to trust it.

    :func:`tracking.predict.predict_displacement` (``mask=None``) for every pair, all pairs in each
    launch.

    Parameters
    ----------
    references, gradients : (B, H, W) float64 Warp arrays (or NumPy arrays, uploaded)
        The image pairs.
    xy : (B, N) ``wp.vec2d`` Warp array (or (B, N, 2) NumPy array)
        Reference-image positions (x = column, y = row) at which to predict; non-finite rows give NaN.
    sizes : sequence of int, keyword-only
        Tile size of each pass, as :func:`tracking.predict.predictor_passes` gives it for the pairs'
        shape and number of dots inside the image (shared by all pairs of the batch).
    min_dots_per_box : float, keyword-only
        As for ``predict_displacement``.
    density : float, keyword-only
        Dots per px^2, as ``predictor_passes`` gives it: sets the block over which the significance is
        pooled (:func:`tracking.predict.pooling_block`).
    device : str, optional
        Warp device (Warp's default when None).

    Returns
    -------
    uv : (B, N) ``wp.vec2d`` Warp array
        Predicted displacement (u, v) in pixels, as ``predict_displacement``.
    quality : (B, N) float64 Warp array
        Its significance, as ``predict_displacement``.

    Notes
    -----
    Every pass is launched for the whole batch (17 launches, 18 where the correlation is by direct DFTs:
    :func:`correlate_tiles`); a pair that stopped at an earlier pass is skipped by every kernel. Nothing
    is copied back to the host.
    """
    device = wp.get_device(device)
    refs = on_device(references, wp.float64, 3, device, "references")
    grads = on_device(gradients, wp.float64, 3, device, "gradients")
    pts = on_device(xy, wp.vec2d, 2, device, "xy")
    if refs.shape != grads.shape:
        raise ValueError(f"references {refs.shape} and gradients {grads.shape} differ in shape")
    nb, h, w = refs.shape
    if pts.shape[0] != nb:
        raise ValueError(f"xy holds {pts.shape[0]} pairs, the images {nb}")
    n_dots = pts.shape[1]
    sizes = [int(s) for s in sizes]
    if not sizes or n_dots == 0 or nb == 0:
        return (
            wp.zeros((nb, n_dots), dtype=wp.vec2d, device=device),
            wp.zeros((nb, n_dots), dtype=wp.float64, device=device),
        )
    grids = [_grid((h, w), s, p == 0 and len(sizes) > 1 and _sparse_grid(h, w, s)) for p, s in enumerate(sizes)]

    def launch(kernel, dim, inputs):
        wp.launch(kernel, dim=dim, inputs=inputs, device=device)

    changed = wp.zeros((nb, len(sizes)), dtype=wp.int32, device=device)
    uv = wp.empty((nb, n_dots), dtype=wp.vec2d, device=device)
    quality = wp.empty((nb, n_dots), dtype=wp.float64, device=device)
    none = wp.empty((1, 1, 1), dtype=wp.float64, device=device)  # the first pass's coarser field: not read
    coarse = None  # (grid, u, v) of the previous pass
    for p, (size, g) in enumerate(zip(sizes, grids, strict=True)):
        last = int(p == len(sizes) - 1)
        rows, cols = g.ny * size, g.nx * size
        run = size if device.is_cpu else 1  # pixels per thread of the deformation: fewer, longer threads on the CPU
        per_tile = (nb, g.ny, g.nx)

        def tiles(dtype=wp.float64, shape=per_tile):
            return wp.empty(shape, dtype=dtype, device=device)

        # the gradient image moved back by the coarser field, tile by tile
        moved, weight, shift = (tiles(t, (nb, rows, cols)) for t in (wp.float32, wp.float32, wp.vec2f))
        cg, cu, cv = coarse if coarse is not None else (g, none, none)
        launch(pk.deform_tiles, (nb, rows, -(-cols // run)), [grads, changed, p, g, int(coarse is not None), cg, cu,
                                                             cv, run, moved, weight, shift])  # fmt: skip

        # correlation planes and their peaks
        planes, peak, norm, count, energy, base = correlate_tiles(refs, moved, weight, shift, changed, p, g, device)

        # the field: peak fits, the normalised median test, holes filled from the nearest tile
        res_u, res_v, raw_u, raw_v, rep_u, rep_v, field_u, field_v = (tiles() for _ in range(8))
        scaled, usable, feature, stack = (tiles(t) for t in (wp.float32, wp.int32, wp.int32, wp.int32))
        launch(pk.fit_tiles, per_tile, [planes, peak, norm, count, base, changed, p, g, res_u, res_v, raw_u, raw_v,
                                        scaled, usable])  # fmt: skip
        launch(pk.replace_outliers, per_tile, [raw_u, raw_v, changed, p, rep_u, rep_v])
        launch(pk.nearest_in_columns, (nb, g.nx), [rep_u, changed, p, last, 0, feature])
        launch(pk.nearest_in_rows, (nb, g.ny), [rep_u, rep_v, feature, stack, changed, p, last, 0, field_u, field_v])
        launch(pk.field_change, per_tile, [field_u, field_v, g, int(coarse is not None), cg, cu, cv, p, changed])

        # pairs that stop here: the significance from this pass's planes, the values at the dots
        med_u, med_v, fill_u, fill_v, coefficient = (tiles() for _ in range(5))
        terms = tiles(wp.vec4d)
        launch(pk.neighbour_medians, per_tile, [res_u, res_v, changed, p, last, med_u, med_v])
        launch(pk.nearest_in_columns, (nb, g.nx), [med_u, changed, p, last, 1, feature])
        launch(pk.nearest_in_rows, (nb, g.ny), [med_u, med_v, feature, stack, changed, p, last, 1, fill_u, fill_v])
        launch(pk.tile_coefficients, per_tile, [planes, fill_u, fill_v, scaled, usable, energy, changed, p, last, g,
                                                terms])  # fmt: skip
        k = pooling_block(density, size, min_dots_per_box)
        launch(pk.pool_coefficients, per_tile, [terms, k, changed, p, last, coefficient])
        launch(pk.values_at_dots, (nb, n_dots), [pts, field_u, field_v, coefficient, g, changed, p, last, uv, quality])
        coarse = (g, field_u, field_v)
    return uv, quality
