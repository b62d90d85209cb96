# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernels of the correlation predictor's tile correlation for a stack of pairs.

Host code: :mod:`tracking.predict_tiles`. The centred tiles, their spectra (FFT blocks or a direct DFT), the
cross-spectrum's inverse and the search of each plane's peak. Tiles and passes as in
:mod:`tracking.predict_kernels`.
"""

import warp as wp
from synthbos.correlation.pass_kernels import centred_complex, cross_spectrum, real_part, real_square, same, weighted

from synthbos.device import quiet_warp

from .predict_kernels import TileGrid, row_runs, runs
from .settings import PREDICTOR_PEAK_REACH, PREDICTOR_PEAK_TIE

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile

#: ``predict.PEAK_KEEP``: the share of a plane's largest sample that another peak must reach to compete.
PEAK_KEEP = wp.constant(wp.float32(1.0 - PREDICTOR_PEAK_TIE))
#: ``settings.PREDICTOR_PEAK_REACH``: a peak is the largest sample within this many samples along each axis.
PEAK_REACH = wp.constant(PREDICTOR_PEAK_REACH)


@wp.func
def is_peak(planes: wp.array2d(dtype=wp.float32), row0: int, r: int, c: int, lo: int, m: int) -> bool:
    """Whether sample (r, c) of the plane from row ``row0`` is no smaller than any other within ``PEAK_REACH``
    samples along each axis inside the searched block (``lo`` ... ``lo + m - 1``)."""
    v = planes[row0 + r, c]
    for rr in range(wp.max(r - PEAK_REACH, lo), wp.min(r + PEAK_REACH + 1, lo + m)):
        for cc in range(wp.max(c - PEAK_REACH, lo), wp.min(c + PEAK_REACH + 1, lo + m)):
            if planes[row0 + rr, cc] > v:
                return False
    return True


# --- the correlation of each tile pair ---------------------------------------------------------------------


@wp.func
def to_float32(x: wp.float64) -> wp.float32:
    return wp.float32(x)


def make_centre_tiles(n: int):
    """Kernel centring the ``n`` x ``n`` tile pairs of a pass, one tile pair per block (any threads per
    block: ``wp.launch_tiled(kernel, dim=[pairs * ny * nx], block_dim=...)``)."""

    @wp.kernel(module="unique", enable_backward=False)
    def centre_tiles(
        references: wp.array3d(dtype=wp.float64),
        moved: wp.array3d(dtype=wp.float32),
        weight: wp.array3d(dtype=wp.float32),
        shift: wp.array3d(dtype=wp.vec2f),
        changed: wp.array2d(dtype=wp.int32),
        p: int,
        grid: TileGrid,
        centred: wp.array3d(dtype=wp.float32),
        norm: wp.array3d(dtype=wp.float64),
        count: wp.array3d(dtype=wp.float32),
        energy: wp.array3d(dtype=wp.vec2d),
        base: wp.array3d(dtype=wp.vec2d),
    ):
        """Tile pair k (pair, i, j): the reference tile as float32 less its mean, and the moved tile less
        its mean over the pixels of weight 1 times the weights (``predict._centre_tiles``), into
        ``centred[0]`` and ``centred[1]`` (rows ``k n ... k n + n - 1``); their sums of squares
        (``energy``), ``norm`` = sqrt of their product, the moved tile's weight sum (``count``) and its
        mean rounded shift (``base``)."""
        k = wp.tid()
        tiles = grid.ny * grid.nx
        b = k // tiles
        i = (k % tiles) // grid.nx
        j = k % grid.nx
        if not runs(changed, b, p):
            return
        ta = wp.tile_map(
            to_float32,
            wp.tile_load(
                references[b], shape=(n, n), offset=(grid.top + i * grid.row_step, grid.left + j * grid.col_step)
            ),
        )
        tb = wp.tile_load(moved[b], shape=(n, n), offset=(i * n, j * n))
        tw = wp.tile_load(weight[b], shape=(n, n), offset=(i * n, j * n))
        ts = wp.tile_load(shift[b], shape=(n, n), offset=(i * n, j * n))
        shifts = wp.tile_extract(wp.tile_sum(ts), 0)
        nb = wp.tile_extract(wp.tile_sum(tw), 0)
        ma = wp.tile_extract(wp.tile_sum(ta), 0) / wp.float32(n * n)
        mb = wp.tile_extract(wp.tile_sum(wp.tile_map(weighted, tb, tw)), 0) / wp.max(nb, wp.float32(1.0))
        za = wp.tile_map(
            centred_complex,
            ta,
            wp.tile_ones(shape=(n, n), dtype=wp.float32),
            wp.tile_full(shape=(n, n), value=ma, dtype=wp.float32),
        )
        zb = wp.tile_map(centred_complex, tb, tw, wp.tile_full(shape=(n, n), value=mb, dtype=wp.float32))
        ea = wp.tile_extract(wp.tile_sum(wp.tile_map(real_square, za)), 0)
        eb = wp.tile_extract(wp.tile_sum(wp.tile_map(real_square, zb)), 0)
        norm[b, i, j] = wp.sqrt(ea * eb)
        count[b, i, j] = nb
        energy[b, i, j] = wp.vec2d(ea, eb)
        area = wp.float64(n * n)
        base[b, i, j] = wp.vec2d(wp.float64(shifts[0]) / area, wp.float64(shifts[1]) / area)
        wp.tile_store(centred[0], wp.tile_map(real_part, za), offset=(k * n, 0))
        wp.tile_store(centred[1], wp.tile_map(real_part, zb), offset=(k * n, 0))

    return centre_tiles


@wp.func
def as_complex(x: wp.float32) -> wp.vec2f:
    return wp.vec2f(x, wp.float32(0.0))


def make_tile_fft_steps(n: int, rows: int):
    """The three kernels of the circular cross-correlation of a pass's centred tile pairs by 1-D tile FFTs
    of ``rows`` rows (or columns) of ``n`` samples per block (``rows`` divides ``n``, a power of two).

    Each takes the same launch: ``wp.launch_tiled(kernel, dim=[tiles * (n // rows)], block_dim=...)``
    (``n // 2`` threads on a GPU, where Warp's tile FFT wants at least two samples per thread; 1 on the
    CPU), and skips the pairs that do not run the pass. A block holds ``rows`` x ``n`` samples, not the
    whole tile, so that a 64 px tile's transforms neither spill registers nor fill an SM's shared
    memory. The steps are the 2-D transforms as rows, transpose, rows, through global memory:

    1. ``rows_forward``: the FFT along each row of both centred tiles, stored transposed:
       ``spectra[t, c, k n + r]`` is tile ``k``'s row ``r`` at frequency ``c``.
    2. ``columns``: for ``rows`` frequencies ``c`` of a tile, the FFT along the tile's column axis of
       both (the 2-D spectra), the cross-spectrum ``conj(A) B (-1)^(r + c) / n^2`` (the inverse's scale
       and the shift of zero displacement to the plane's centre), its inverse FFT back along the column
       axis, stored transposed again: ``cross[k n + r, c]``.
    3. ``rows_inverse``: the inverse FFT along each row of ``cross``; the real part is the plane.
    """

    @wp.kernel(module="unique", enable_backward=False)
    def rows_forward(
        centred: wp.array3d(dtype=wp.float32),
        changed: wp.array2d(dtype=wp.int32),
        p: int,
        grid: TileGrid,
        spectra: wp.array3d(dtype=wp.vec2f),
    ):
        q = wp.tid()
        g0 = q * rows
        if not row_runs(changed, grid, g0, p):
            return
        za = wp.tile_map(as_complex, wp.tile_load(centred[0], shape=(rows, n), offset=(g0, 0)))
        zb = wp.tile_map(as_complex, wp.tile_load(centred[1], shape=(rows, n), offset=(g0, 0)))
        wp.tile_fft(za)
        wp.tile_fft(zb)
        # a transposed tile lives in shared memory: copy the FFT's register tile there
        wp.tile_store(spectra[0], wp.tile_transpose(wp.tile_map(same, za)), offset=(0, g0))
        wp.tile_store(spectra[1], wp.tile_transpose(wp.tile_map(same, zb)), offset=(0, g0))

    @wp.kernel(module="unique", enable_backward=False)
    def columns(
        spectra: wp.array3d(dtype=wp.vec2f),
        spectral: wp.array2d(dtype=wp.float32),
        changed: wp.array2d(dtype=wp.int32),
        p: int,
        grid: TileGrid,
        cross: wp.array2d(dtype=wp.vec2f),
    ):
        q = wp.tid()
        chunks = n // rows
        k = q // chunks
        c0 = (q % chunks) * rows
        if not runs(changed, k // (grid.ny * grid.nx), p):
            return
        fa = wp.tile_load(spectra[0], shape=(rows, n), offset=(c0, k * n))
        fb = wp.tile_load(spectra[1], shape=(rows, n), offset=(c0, k * n))
        wp.tile_fft(fa)
        wp.tile_fft(fb)
        # the spectral factors are symmetric in (r, c): rows c0 ... of the table serve the transposed layout
        s = wp.tile_map(cross_spectrum, fa, fb, wp.tile_load(spectral, shape=(rows, n), offset=(c0, 0)))
        wp.tile_ifft(s)
        wp.tile_store(cross, wp.tile_transpose(wp.tile_map(same, s)), offset=(k * n, c0))

    @wp.kernel(module="unique", enable_backward=False)
    def rows_inverse(
        cross: wp.array2d(dtype=wp.vec2f),
        changed: wp.array2d(dtype=wp.int32),
        p: int,
        grid: TileGrid,
        planes: wp.array2d(dtype=wp.float32),
    ):
        q = wp.tid()
        g0 = q * rows
        if not row_runs(changed, grid, g0, p):
            return
        s = wp.tile_load(cross, shape=(rows, n), offset=(g0, 0))
        wp.tile_ifft(s)
        wp.tile_store(planes, wp.tile_map(real_part, s), offset=(g0, 0))

    return rows_forward, columns, rows_inverse


@wp.func
def times(z: wp.vec2f, w: wp.vec2f) -> wp.vec2f:
    """The complex product ``z w``."""
    return wp.vec2f(z[0] * w[0] - z[1] * w[1], z[0] * w[1] + z[1] * w[0])


# The direct-DFT route (tiles of any size; the faster one for small tiles, whose FFT blocks would be a few
# threads each). Both tiles are real, so every spectrum along the rows is Hermitian: only the frequencies
# c = 0 ... size // 2 (``half = size // 2 + 1`` of them) are computed and stored, ``(tiles * size, half)``
# arrays, and the planes' real inverse along the rows weighs each stored frequency by how many it stands
# for. ``twiddle[m]`` = exp(-2 pi i m / size); the index ``(j c) mod size`` is stepped, not divided.


@wp.func
def step_index(m: int, step: int, n: int) -> int:
    """``(m + step) mod n`` for ``m`` and ``step`` in ``[0, n)``: the next twiddle of a DFT's sum."""
    m += step
    if m >= n:
        m -= n
    return m


@wp.kernel
def dft_rows(
    centred: wp.array3d(dtype=wp.float32),
    twiddle: wp.array1d(dtype=wp.vec2f),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    grid: TileGrid,
    spectra: wp.array3d(dtype=wp.vec2f),
):
    """Sample (t, g, c): the DFT along row ``g`` (tile ``g // size``'s row ``g % size``) of centred tile
    ``t`` at frequency ``c``, ``sum_j x_j w^(j c)``."""
    t, g, c = wp.tid()
    n = grid.size
    if not row_runs(changed, grid, g, p):
        return
    acc = wp.vec2f()
    m = int(0)
    for j in range(n):
        acc += centred[t, g, j] * twiddle[m]
        m = step_index(m, c, n)
    spectra[t, g, c] = acc


@wp.kernel
def dft_columns_cross(
    spectra: wp.array3d(dtype=wp.vec2f),
    twiddle: wp.array1d(dtype=wp.vec2f),
    spectral: wp.array2d(dtype=wp.float32),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    grid: TileGrid,
    cross: wp.array2d(dtype=wp.vec2f),
):
    """Sample (k size + f, c): the DFT of both row spectra along tile ``k``'s column axis at frequency
    ``f`` (the 2-D spectra A and B at (f, c)), and their cross-spectrum ``conj(A) B (-1)^(f + c) / size^2``
    (the inverse's scale and the shift of zero displacement to the plane's centre)."""
    g, c = wp.tid()
    n = grid.size
    k = g // n
    if not runs(changed, k // (grid.ny * grid.nx), p):
        return
    f = g - k * n
    fa = wp.vec2f()
    fb = wp.vec2f()
    m = int(0)
    for r in range(n):
        w = twiddle[m]
        fa += times(spectra[0, k * n + r, c], w)
        fb += times(spectra[1, k * n + r, c], w)
        m = step_index(m, f, n)
    cross[g, c] = cross_spectrum(fa, fb, spectral[f, c])


@wp.kernel
def dft_columns_inverse(
    cross: wp.array2d(dtype=wp.vec2f),
    twiddle: wp.array1d(dtype=wp.vec2f),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    grid: TileGrid,
    out: wp.array2d(dtype=wp.vec2f),
):
    """Sample (k size + r, c): the inverse DFT (unscaled) of the cross-spectrum along tile ``k``'s column
    axis at row ``r``."""
    g, c = wp.tid()
    n = grid.size
    k = g // n
    if not runs(changed, k // (grid.ny * grid.nx), p):
        return
    r = g - k * n
    acc = wp.vec2f()
    m = int(0)
    for f in range(n):
        w = twiddle[m]
        acc += times(cross[k * n + f, c], wp.vec2f(w[0], -w[1]))
        m = step_index(m, r, n)
    out[g, c] = acc


@wp.kernel
def dft_rows_inverse_real(
    half: wp.array2d(dtype=wp.vec2f),
    twiddle: wp.array1d(dtype=wp.vec2f),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    grid: TileGrid,
    planes: wp.array2d(dtype=wp.float32),
):
    """Sample (g, c) of the planes: the real inverse DFT (unscaled) along row ``g`` from its stored
    frequencies, each but 0 and size / 2 counted twice (for itself and its conjugate)."""
    g, c = wp.tid()
    n = grid.size
    if not row_runs(changed, grid, g, p):
        return
    acc = wp.float32(0.0)
    m = int(0)
    for f in range(half.shape[1]):
        z = half[g, f]
        w = twiddle[m]
        term = z[0] * w[0] + z[1] * w[1]
        if f == 0 or 2 * f == n:
            acc += term
        else:
            acc += wp.float32(2.0) * term
        m = step_index(m, c, n)
    planes[g, c] = acc


@wp.kernel
def search_peaks(
    planes: wp.array2d(dtype=wp.float32),
    changed: wp.array2d(dtype=wp.int32),
    p: int,
    grid: TileGrid,
    lo: int,
    m: int,
    peak: wp.array3d(dtype=wp.int32),
):
    """Index (row * size + column) of tile (pair, i, j)'s peak in its plane's ``m`` x ``m`` samples from
    (``lo``, ``lo``): ``predict.peak_index`` of the searched block (its largest sample, or of the peaks
    within ``PEAK_KEEP`` of it the one nearest the plane's centre; the first, row by row, of equals)."""
    b, i, j = wp.tid()
    if not runs(changed, b, p):
        return
    n = grid.size
    row0 = ((b * grid.ny + i) * grid.nx + j) * n
    best = planes[row0 + lo, lo]
    for r in range(lo, lo + m):
        for c in range(lo, lo + m):
            best = wp.max(best, planes[row0 + r, c])
    keep = best * PEAK_KEEP
    half = n // 2
    at = int(-1)
    near = int(0)
    for r in range(lo, lo + m):
        for c in range(lo, lo + m):
            v = planes[row0 + r, c]
            if v >= keep:
                d2 = (r - half) * (r - half) + (c - half) * (c - half)
                if (at < 0 or d2 < near) and is_peak(planes, row0, r, c, lo, m):
                    at = r * n + c
                    near = d2
    if at < 0:  # no sample compares (a plane of NaN): the block's first, as before any rule
        at = lo * n + lo
    peak[b, i, j] = at
