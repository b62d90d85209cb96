"""The correlation predictor's tile correlation on one Warp device, for a stack of pairs.

:func:`correlate_tiles` gives the correlation planes of one pass's tile pairs and their peaks for every
pair of a stack that runs the pass (:func:`tracking.predict.predict_displacement_stack` walks the passes):
Warp's tile FFT for tiles of a power of two from ``FFT_FROM`` px, direct DFTs for other sizes; the
kernels are in :mod:`tracking.predict_fft_kernels`. The host predictor
(:func:`tracking.predict.predict_displacement`) correlates by SciPy's pocketfft: the planes agree to
float32 rounding.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import predict_fft_kernels as fk

__all__ = ["correlate_tiles", "uses_tile_fft"]

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
    """The pass's ``"centre"`` kernel, or its three ``"fft"`` kernels, built once per size.

    Each is a Warp module of its own, whose default block size is set to its GPU launch's, so that
    compiling it ahead of the launch (``synthbos.device.load_kernels``, Warp's ``force_load``) builds the
    variant the launch uses (Warp's default of 256 threads is no block size for a tile FFT of 32 samples).
    """
    key = (what, size)
    if key not in _kernels:
        if what == "centre":
            made, threads = fk.make_centre_tiles(size), _cuda_threads("centre", size)
        else:
            made, threads = fk.make_tile_fft_steps(size, _fft_rows(size)), _cuda_threads("fft", size)
        for kernel in made if isinstance(made, tuple) else (made,):
            kernel.module.options["block_dim"] = threads
        _kernels[key] = made
    return _kernels[key]


def prepare_kernels(sizes) -> None:
    """Create the tile kernels of the passes of ``sizes`` now, uncompiled. Each is a Warp module of its
    own, made on first use; made at import for the default passes, a campaign's
    ``synthbos.device.load_kernels`` finds them among ``predict_fft_kernels``' modules and compiles them
    with the others, in parallel, instead of one after another inside the first stack's predictor.

    Examples
    --------
    >>> prepare_kernels([64, 16])
    >>> ("fft", 64) in _kernels and ("centre", 16) in _kernels and ("fft", 16) not in _kernels
    True
    """
    for size in sorted({int(s) for s in sizes}):
        _kernel("centre", size)
        if uses_tile_fft(size):
            _kernel("fft", size)


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


def _cuda_threads(what, size):
    """Threads per block of a pass's kernels on a GPU: the centring kernel's a few samples each, the
    tile-FFT kernels' two samples of a row each (Warp's tile FFT wants at least two).

    Examples
    --------
    >>> _cuda_threads("centre", 64), _cuda_threads("fft", 64), _cuda_threads("fft", 32)
    (256, 32, 16)
    """
    return min(256, max(size * size // 4, 1)) if what == "centre" else size // 2


def _centre_threads(size, device):
    """Threads per block of the centring kernel: :func:`_cuda_threads` on a GPU; one on the CPU."""
    return 1 if device.is_cpu else _cuda_threads("centre", size)


def _fft_threads(size, device):
    """Threads per block of the tile-FFT kernels: :func:`_cuda_threads` on a GPU; one on the CPU, whose
    sequential FFT is the fastest there."""
    return 1 if device.is_cpu else _cuda_threads("fft", size)


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
