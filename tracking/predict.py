"""A coarse-to-fine correlation predictor for the gradient image, with a local significance measure.

The tracker pairs a dot with the blob nearest its predicted gradient-image position. Without a predictor
that position is the reference position, so displacements beyond a couple of pixels (the window margin)
are missed or, worse, paired with a neighbouring dot. Here a pyramid of window-shifted FFT correlations
(coarse tiles first, the gradient image moved back by the coarser field before each finer pass) predicts
every dot's
displacement, and the normalised correlation coefficient of the finest tiles, read at the displacement of
their neighbours, says where the prediction can be trusted: it is near 1 where the images agree and near
0 where the gradient frame is unrelated to the reference one (wrong frame, flipped frame, decorrelated
region).

The prediction only has to land within a fraction of ``TrackingSettings.max_displacement`` (2 px) of the
dot, as the identification looks for the dot in a window around it and the match must lie within
``predictor_tolerance`` (1.5 px) of it: moving the gradient image by whole pixels (no interpolation)
and a three-point Gaussian peak fit of the residual (a few hundredths of a pixel for 3 px dots) are
enough, and side-by-side tiles (no overlap) sample the field finely enough once the pyramid reaches
tiles a few times the field's scale of variation.

:func:`predict_displacement_stack` runs :func:`predict_displacement` (without a mask) for a stack of B pairs
on one Warp device: every pass is a fixed sequence of launches of :mod:`tracking.predict_kernels` over all
pairs (the tile correlation in :mod:`tracking.predict_tiles`), the images, fields and results stay on the
device, and nothing waits for the host (the host only loops over the passes). The pyramid still ends pair
by pair: a pair whose field a pass changed little is left alone by the later passes (the kernels read
which pairs run from the per-pair, per-pass ``changed`` flags), and its displacement and significance are
computed from the planes of the pass at which it stopped, as the host does for it alone. The host function
is the reference: the correlations differ by float32 rounding (Warp's tile FFTs or direct DFTs there,
SciPy's pocketfft here), which can at times flip a whole-pixel rounding of the deformation or a tie of the
peak search; otherwise the steps are the same arithmetic.
"""

from __future__ import annotations

import numpy as np
import warp as wp
from scipy import fft as sfft
from scipy import ndimage
from synthbos.correlation.median_test import median_scale, nan_median, residual_limit
from synthbos.correlation.peak import three_point_offset

from . import predict_kernels as pk
from .deform_kernels import deform_nearest_kernel
from .predict_tiles import correlate_tiles, prepare_kernels
from .settings import PREDICTOR_MIN_VALID_FRACTION, PREDICTOR_PEAK_REACH, PREDICTOR_PEAK_TIE, PREDICTOR_RESOLVED_PX
from .workspace import on_device, scratch

__all__ = [
    "PREDICTOR_WINDOWS",
    "dots_inside",
    "local_normalized_correlation",
    "pooling_block",
    "predict_displacement",
    "predict_displacement_stack",
    "predictor_passes",
]

#: Tile sizes (px) of the predictor's passes: 64 px tiles find shifts up to about 16 px (a quarter of the
#: tile) and more; the 32 and 16 px passes (the last one twice) follow fields that vary over a few tens of
#: pixels (0.2 px per px in the tests). The pyramid ends at the first pass that changes little.
PREDICTOR_WINDOWS = (64, 32, 16, 16)
prepare_kernels(PREDICTOR_WINDOWS)  # the stacked predictor's tile kernels, so a campaign compiles them up front

#: The samples of a correlation plane around its peak that the three-point fits read (row, column offsets).
_CROSS = ((-1, 0), (0, -1), (0, 0), (0, 1), (1, 0))


def dots_inside(xy, shape):
    """Number of the (N, 2) positions ``xy`` (x = column, y = row; non-finite rows not counted) that lie
    inside an image of ``shape`` (within half a pixel beyond the outer pixel centres)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    h, w = shape
    fin = np.isfinite(xy).all(axis=1)
    return int(
        np.count_nonzero(
            fin
            & (np.abs(np.where(fin, xy[:, 0], -9) - (w - 1) / 2) <= w / 2)
            & (np.abs(np.where(fin, xy[:, 1], -9) - (h - 1) / 2) <= h / 2)
        )
    )


def predictor_passes(shape, n_inside, window_sizes=PREDICTOR_WINDOWS, min_dots_per_window=5.0):
    """The tile sizes of the predictor's passes, and the dot density, for an image of ``shape``.

    Parameters
    ----------
    shape : (int, int)
        Image shape (H, W).
    n_inside : int
        Number of dots inside the image (:func:`dots_inside`).
    window_sizes, min_dots_per_window
        As for :func:`predict_displacement`.

    Returns
    -------
    sizes : list of int
        Tile size (px) of each pass, coarse first (empty: no pass, the image is smaller than 8 px):
        ``window_sizes`` reduced to the image, and those whose tiles would hold fewer than
        ``min_dots_per_window`` dots on average replaced by one pass with the smallest tile (a multiple
        of 8 px, not necessarily a power of two) that holds that many.
    density : float
        Dots per px^2 (at least one dot counted), which also sets the pooling block
        (:func:`pooling_block`).
    """
    h, w = shape
    side = min(h, w)
    density = max(n_inside, 1) / (h * w)
    smallest = 8 * int(np.ceil(np.sqrt(min_dots_per_window / density) / 8.0))
    kept = [int(s) for s in window_sizes if s >= smallest]
    if len(kept) < len(window_sizes):
        kept.append(min(smallest, max(window_sizes)))
    sizes = []
    for s in kept:
        s = int(min(s, side))
        if s >= 8 and (not sizes or s <= sizes[-1]):
            sizes.append(s)
    return sizes, density


def pooling_block(density, size, min_dots_per_box=20.0):
    """Side k (odd, in tiles) of the block of ``size`` px tiles over which the significance is pooled:
    the smallest that holds ``min_dots_per_box`` dots at ``density`` dots per px^2."""
    return max(1 + 2 * int(np.ceil((np.sqrt(min_dots_per_box / density) / size - 1.0) / 2.0)), 1)


def local_normalized_correlation(a, b, *, size, weights=None):
    """Normalised correlation coefficient of two images in a square box around every pixel.

    Parameters
    ----------
    a, b : (H, W) arrays
        Images sampled on the same pixels.
    size : int
        Side of the box in pixels.
    weights : (H, W) array of 0 and 1, optional
        Pixels that take part (1); others are ignored.

    Returns
    -------
    (H, W) float64 array
        ``cov(a, b) / sqrt(var(a) var(b))`` over the box's pixels with weight 1, in [-1, 1]; 0 where
        either image is flat in the box or fewer than a quarter of its pixels take part.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=np.float64)

    def box(f):
        return ndimage.uniform_filter(f, size=size, mode="constant")

    n = box(w)
    enough = n > PREDICTOR_MIN_VALID_FRACTION
    n = np.where(enough, n, 1.0)
    ma, mb = box(w * a) / n, box(w * b) / n
    va = box(w * a * a) / n - ma * ma
    vb = box(w * b * b) / n - mb * mb
    cov = box(w * a * b) / n - ma * mb
    den = np.sqrt(np.maximum(va, 0.0) * np.maximum(vb, 0.0))
    ok = enough & (den > 1e-12 * (np.abs(ma) * np.abs(mb) + 1e-300))
    return np.where(ok, np.clip(cov / np.where(ok, den, 1.0), -1.0, 1.0), 0.0)


def _fill_nan(u):
    """Replace NaN nodes (masked tiles) by the nearest finite one."""
    bad = ~np.isfinite(u)
    if not bad.any():
        return u
    if bad.all():
        return np.zeros_like(u)
    idx = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
    return u[tuple(idx)]


def _tile_grid(n, size):
    """Start of each of the ``n // size`` tiles along an axis of ``n`` px, the tiles centred on the axis."""
    count = n // size
    return (n - count * size) // 2 + size * np.arange(count)


def _sparse_grid(h, w, size):
    """Whether a first pass of ``size`` px tiles may take about every other tile along both axes: where
    that still leaves at least eight tiles along each axis (on smaller images the side-by-side tiles
    are few and cheap, and the denser field keeps the finer passes' start as it was)."""
    return min(h, w) // (2 * size) >= 8


def _sparse_tile_grid(n, size):
    """Start of each tile of a first pass that takes about every other tile along an axis of ``n`` px:
    evenly spaced tiles, at most ``2 * size`` apart, the outer ones at the axis's ends (but for the
    remainder of the division, split between both ends), so that the field's outer centres lie where
    those of side-by-side tiles would."""
    count = -(-(n - size) // (2 * size)) + 1
    stride = (n - size) // (count - 1)
    return (n - size - stride * (count - 1)) // 2 + stride * np.arange(count)


def _tiles_view(image, ys, xs, size):
    """The ``size`` px tiles of ``image`` starting at rows ``ys`` and columns ``xs`` (each evenly
    spaced) as a read-only ``(len(ys), len(xs), size, size)`` view."""
    sy = int(ys[1] - ys[0]) if len(ys) > 1 else size
    sx = int(xs[1] - xs[0]) if len(xs) > 1 else size
    r0, c0 = image.strides
    return np.lib.stride_tricks.as_strided(
        image[ys[0] :, xs[0] :],
        shape=(len(ys), len(xs), size, size),
        strides=(sy * r0, sx * c0, r0, c0),
        writeable=False,
    )


def _bilinear(field, centres_y, centres_x, y, x):
    """Bilinear interpolation of a tile field (or a stack of them, ``(..., ny, nx)``) at points (x, y),
    extrapolated linearly past the outer centres."""
    iy, ty = _cell(y, centres_y)
    ix, tx = _cell(x, centres_x)
    ny, nx = field.shape[-2:]
    iy1, ix1 = np.minimum(iy + 1, ny - 1), np.minimum(ix + 1, nx - 1)
    iy, ix, iy1, ix1 = np.broadcast_arrays(iy, ix, iy1, ix1)
    flat = field.reshape(*field.shape[:-2], ny * nx)
    # the nodes by flat index (np.take: the same values as field[..., iy, ix], without fancy indexing's cost)
    f00, f01, f10, f11 = (np.take(flat, j * nx + i, axis=-1) for j, i in ((iy, ix), (iy, ix1), (iy1, ix), (iy1, ix1)))
    return (1 - ty) * ((1 - tx) * f00 + tx * f01) + ty * ((1 - tx) * f10 + tx * f11)


def _cell(t, centres):
    """Cell index and fraction of coordinates ``t`` on evenly spaced ``centres`` (fraction beyond [0, 1]
    at the ends: linear extrapolation, which follows a field's gradient to the image edge)."""
    if len(centres) == 1:
        return np.zeros(np.shape(t), dtype=np.int64), np.zeros(np.shape(t))
    f = (np.asarray(t, dtype=np.float64) - centres[0]) / (centres[1] - centres[0])
    i = np.clip(np.floor(f).astype(np.int64), 0, len(centres) - 2)
    return i, f - i


#: The offsets (rows, columns) of a tile's eight neighbours.
_NEIGHBOURS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)


def _neighbours(u):
    """The eight neighbours of each tile of a field (or a stack of fields, ``(..., ny, nx)``), NaN beyond
    the edges, stacked along a new first axis."""
    ny, nx = u.shape[-2:]
    pad = np.pad(u, [(0, 0)] * (u.ndim - 2) + [(1, 1), (1, 1)], constant_values=np.nan)
    return np.stack([pad[..., 1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx] for dy, dx in _NEIGHBOURS])


def _neighbour_median(u):
    """Median of each tile's (up to) eight neighbours, the tile itself left out (NaN where it has none),
    of a field or a stack of fields (``(..., ny, nx)``)."""
    return nan_median(_neighbours(u), axis=0)[0]


def _replace_outliers(u, *, threshold=3.0, epsilon=0.5):
    """Tiles failing the normalised median test against their neighbours take the neighbours' median
    (of a field or of each of a stack of fields, ``(..., ny, nx)``).

    Westerweel and Scarano (2005): a tile further from its neighbours' median than ``threshold`` times
    (their median distance from it + ``epsilon`` px) is an outlier (:mod:`correlation.median_test`).
    """
    med, scale, _ = median_scale(_neighbours(u), axis=0)
    scale[np.isnan(scale)] = np.inf
    bad = np.isfinite(med) & ~(np.abs(u - med) <= residual_limit(scale, epsilon=epsilon, threshold=threshold))
    return np.where(bad, med, u)


def _gaussian_sample(planes, row, col, scale, *, top=0, height=None):
    """Value of each correlation plane, divided by its ``scale``, at a sub-pixel position, from a
    separable three-point Gaussian (``planes`` may hold only the rows from ``top`` of planes ``height``
    rows high: the rows read must be among them).

    Around the sample nearest the position the plane is modelled as ``C exp(b t + c t^2)`` along each
    axis (fitted to that sample and its two neighbours), which a correlation peak of Gaussian dots
    follows closely; where a sample is not positive the nearest sample itself is taken. Positions
    off the plane give 0.
    """
    k, h, w = planes.shape
    h = h if height is None else height
    r, c = np.rint(row).astype(np.int64), np.rint(col).astype(np.int64)
    on = (r >= 1) & (r <= h - 2) & (c >= 1) & (c <= w - 2)
    r, c = np.clip(r, 1, h - 2), np.clip(c, 1, w - 2)
    i = np.arange(k)
    tr, tc = row - r, col - c
    r = r - top
    centre = (planes[i, r, c] / scale).astype(np.float64)
    trip = (
        (planes[i, r - 1, c] / scale, planes[i, r + 1, c] / scale, tr),
        (planes[i, r, c - 1] / scale, planes[i, r, c + 1] / scale, tc),
    )
    ok = centre > 0
    for lo, hi, _ in trip:
        ok &= (lo > 0) & (hi > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lc = np.log(np.where(ok, centre, 1.0))
        factor = np.zeros(k)
        for lo, hi, t in trip:
            ll, lh = np.log(np.where(ok, lo, 1.0)), np.log(np.where(ok, hi, 1.0))
            b, cc = 0.5 * (lh - ll), 0.5 * (lh + ll) - lc
            factor += b * t + np.minimum(cc, 0.0) * t * t
    value = np.where(ok, centre * np.exp(factor), centre)
    return np.where(on, value, 0.0)


def _tile_stack(tiles, *, roll=False, which=None):
    """The tiles of a ``(ny, nx, size, size)`` view (:func:`_tiles_view`; or those where the ``(ny, nx)``
    bool array ``which`` is True) as a contiguous ``(tiles, size * size)`` float32 array, tiles row by
    row; with ``roll`` each tile is rolled circularly by ``-(size // 2)`` along both axes (its pixel
    (0, 0) taken from (size // 2, size // 2))."""
    size = tiles.shape[-1]
    if which is not None:
        tiles = tiles[which]
    out = np.empty((*tiles.shape[:-2], size, size), dtype=np.float32)
    if roll:
        k = size // 2
        for dst_r, src_r in ((np.s_[: size - k], np.s_[k:]), (np.s_[size - k :], np.s_[:k])):
            for dst_c, src_c in ((np.s_[: size - k], np.s_[k:]), (np.s_[size - k :], np.s_[:k])):
                out[..., dst_r, dst_c] = tiles[..., src_r, src_c]
    else:
        out[...] = tiles
    return out.reshape(-1, size * size)


def _partial_tiles(weights):
    """Which tiles of a ``(ny, nx, size, size)`` view of the weights have pixels of weight other than 1
    (None: no weights, no such tile)."""
    if weights is None:
        return None
    return (weights != 1).any(axis=(2, 3))


def _any(partial):
    """Whether any tile is partial (``partial`` None: none)."""
    return partial is not None and bool(partial.any())


def _centre_tiles(t, partial, wt, size):
    """Subtract in place each tile's mean over its pixels that take part and zero the others.

    ``t`` holds the tiles of :func:`_tile_stack`; ``partial`` which tiles have weights other than 1
    (None: every pixel of every tile takes part) and ``wt`` the stacked weights of those tiles' pixels
    (1 take part, 0 not, or fractions; tiles in the order of ``t``; None where no tile is partial).
    Returns the tiles' weight sums and sums of squares (after the subtraction).
    """
    t -= t.mean(axis=1, keepdims=True)
    count = np.full(len(t), float(size * size))
    if _any(partial):
        rows = np.flatnonzero(partial.ravel())
        sub = t[rows]
        n = wt.sum(axis=1, dtype=np.float64)
        sub -= (np.einsum("ij,ij->i", sub, wt) / np.maximum(n, 1.0)).astype(np.float32)[:, None]
        sub *= wt
        t[rows] = sub
        count[rows] = n
    return count, np.einsum("ij,ij->i", t, t).astype(np.float64)


def _reference_spectra(a, valid, ys, xs, size):
    """Conjugate spectra of the mean-subtracted reference tiles (rolled by half a tile, so that the
    inverse transform of a cross spectrum puts zero displacement at ``size // 2``), with the tiles'
    weight sums and sums of squares: what :func:`_correlate_tiles` needs of the reference."""
    ta = _tile_stack(_tiles_view(a, ys, xs, size), roll=True)
    va = None if valid is None else _tiles_view(valid, ys, xs, size)
    partial = _partial_tiles(va)
    wt = _tile_stack(va, roll=True, which=partial) if _any(partial) else None
    count, energy = _centre_tiles(ta, partial, wt, size)
    spec = sfft.rfft2(ta.reshape(-1, size, size), axes=(-2, -1), overwrite_x=True)
    return np.conjugate(spec, out=spec), count, energy


def _correlate_tiles(reference, tb, partial, wt, shape, size, *, rows=None):
    """Circular correlation of each reference tile with the same tile of the gradient image, not
    normalised.

    ``reference`` is :func:`_reference_spectra`'s result; ``tb`` the gradient image's tiles as
    :func:`_tile_stack` gives them (overwritten), ``partial`` the ``shape`` (tile rows, tile columns)
    array of tiles with weights other than 1 (None: none) and ``wt`` the stacked weights of those
    tiles' pixels (1 take part, 0 masked; None where no tile is partial); ``rows`` (start, stop), where
    given, the only rows of the planes wanted.
    Tiles are mean-subtracted over their unmasked pixels. Returns the ``(k, size, size)`` float32
    planes (zero displacement at ``size // 2``; with ``rows`` only those rows, ``(k, stop - start,
    size)``), the norms ``sqrt(sum a^2 sum b^2)`` that make a perfect match peak at 1, which tiles have
    enough unmasked pixels and the tiles' sums of squares (reference, b).

    Notes
    -----
    With ``rows`` the inverse transform is SciPy's ``irfft2`` in the two steps that pocketfft takes
    (the complex transform along the rows' axis, then the real one along each row, scaled by
    ``1 / size**2`` at the end), the second on the rows wanted only: the same float32 values as
    ``irfft2``'s, bit for bit, with fewer of the real transforms.
    """
    spec_a, na, ea = reference
    nb, eb = _centre_tiles(tb, partial, wt, size)
    spec = sfft.rfft2(tb.reshape(-1, size, size), axes=(-2, -1), overwrite_x=True)
    spec *= spec_a
    if rows is None:
        planes = sfft.irfft2(spec, s=(size, size), axes=(-2, -1), overwrite_x=True)
    else:
        spec = sfft.ifft(spec, axis=-2, norm="forward", overwrite_x=True)
        planes = sfft.irfft(spec[:, rows[0] : rows[1]], n=size, axis=-1, norm="forward", overwrite_x=True)
        # irfft2's factor: float32(1 / size**2) from a long double quotient, as pocketfft computes it
        planes *= np.float32(np.longdouble(1.0) / (size * size))
    norm = np.sqrt(ea * eb)
    enough = PREDICTOR_MIN_VALID_FRACTION * size * size
    usable = ((na >= enough) & (nb >= enough) & (norm > 0)).reshape(shape)
    return planes, norm, usable, (ea.reshape(shape), eb.reshape(shape))


def _uniform_tile_shifts(field, row_cell, col_cell, ys, xs, size, shape):
    """Which tiles (rows ``ys``, columns ``xs``, side ``size``) the tile ``field`` moves by one whole-pixel
    shift from inside the image (of ``shape``): ``(tiles, 3)`` int32 rows (rounded u, rounded v, 1) for
    those, (0, 0, 0) for the others, tiles row by row. ``row_cell`` and ``col_cell`` are the field's
    cells of the image's rows and columns (:func:`_cell`).

    Within a cell of tile centres the field is bilinear, so over a rectangle of pixels it is largest and
    smallest at the rectangle's corners: the field is read at each tile's first and last rows and
    columns and at those on both sides of a change of cell. A tile whose values there all lie more than
    1e-6 px inside one rounding interval has every pixel rounded alike (the interpolation's rounding
    errors are many orders smaller).
    """
    u, v, cy, cx = field
    ny, nx = len(ys), len(xs)

    def corners(cells, start, count):
        """The block's rows (or columns) at the ends of its tiles and of its runs of one cell."""
        at = np.arange(count * size)
        change = np.flatnonzero(np.diff(cells[start : start + count * size]) != 0)
        ends = np.concatenate([at[::size], at[size - 1 :: size], change, change + 1])
        return np.unique(ends)

    rows, cols = corners(row_cell, ys[0], ny), corners(col_cell, xs[0], nx)
    f = _bilinear(np.stack([u, v]), cy, cx, (ys[0] + rows)[:, None], (xs[0] + cols)[None, :])
    # the extremes over each tile's rows, then over its columns (every tile has rows and columns there)
    row_start, col_start = np.searchsorted(rows, size * np.arange(ny)), np.searchsorted(cols, size * np.arange(nx))
    lo = np.minimum.reduceat(np.minimum.reduceat(f, row_start, axis=1), col_start, axis=2)
    hi = np.maximum.reduceat(np.maximum.reduceat(f, row_start, axis=1), col_start, axis=2)
    shift = np.rint(lo)
    one = ((lo > shift - 0.5 + 1e-6) & (hi < shift + 0.5 - 1e-6)).all(axis=0)
    top, left = ys[:, None] + shift[1], xs[None, :] + shift[0]
    one &= (top >= 0) & (top + size <= shape[0]) & (left >= 0) & (left + size <= shape[1])
    out = np.zeros((ny * nx, 3), dtype=np.int32)
    out[:, 0], out[:, 1] = (np.where(one, shift[i], 0).ravel() for i in (0, 1))
    out[:, 2] = one.ravel()
    return out


def _deform_nearest(image, valid, field, ys, xs, size, device, *, whole_on_host=None):
    """``image`` moved back by the tile ``field`` (u, v, centres_y, centres_x), bilinearly interpolated
    and rounded to whole pixels at every pixel, over the block of the finer pass's tiles (rows ``ys``,
    columns ``xs``, side ``size``) only (Warp kernel ``deform_nearest_kernel``).

    Returns the moved tiles as a ``(tiles, size * size)`` float32 stack (as :func:`_tile_stack` of the
    moved block; a view of the thread's workspace, valid until the next call), the weights of the pixels
    of the tiles that have weights other than 1 (1 where the source pixel lies inside the image, times
    ``valid`` there; stacked alike, those tiles in order; None where there are none), the mean rounded
    shifts u and v of each tile and which tiles have pixels of weight other than 1.

    Tiles that the field moves by one whole-pixel shift from inside the image
    (:func:`_uniform_tile_shifts`) are copied as a whole: by NumPy where ``whole_on_host`` (default:
    on the CPU, where a gather of whole tiles costs far less than the kernel's pixel by pixel), else by
    the kernel.
    """
    h, w = image.shape
    u, v, cy, cx = field
    ny, nx = len(ys), len(xs)

    def on_device(a, dtype):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device, copy=not wp.get_device(device).is_cpu)

    row_cell, row_frac = _cell(np.arange(h), cy)
    col_cell, col_frac = _cell(np.arange(w), cx)
    # from the thread's workspace: the views returned are used within the pass only
    out = scratch("predict_moved", (ny * nx * size * size,), wp.float32, device)
    out_valid = scratch("predict_weights", (ny * nx * size * size,), wp.float32, device)
    tile_sums = wp.zeros((3, ny, nx), dtype=wp.int32, device=device)
    # float64 pixels (those of the tracker's images, no copy), rounded to float32 as they are moved
    img = on_device(np.asarray(image, dtype=np.float64).reshape(-1), wp.float64)
    # a row of all tiles per thread on the CPU (fewer, longer threads), of one tile on a GPU
    is_cpu = wp.get_device(device).is_cpu
    tiles = nx if is_cpu else 1
    whole_on_host = is_cpu if whole_on_host is None else whole_on_host
    shifts = _uniform_tile_shifts(field, row_cell, col_cell, ys, xs, size, (h, w))
    # without ``valid`` the kernel reads none: ``out_valid`` stands in for it
    wp.launch(
        deform_nearest_kernel,
        dim=(ny * size, -(-nx // tiles)),
        inputs=[
            img,
            out_valid if valid is None else on_device(np.asarray(valid, dtype=np.float32).reshape(-1), wp.float32),
            int(valid is not None),
            h,
            w,
            on_device(np.asarray(u, dtype=np.float64), wp.float64),
            on_device(np.asarray(v, dtype=np.float64), wp.float64),
            on_device(row_cell.astype(np.int32), wp.int32),
            on_device(row_frac, wp.float64),
            on_device(col_cell.astype(np.int32), wp.int32),
            on_device(col_frac, wp.float64),
            int(ys[0]),
            int(xs[0]),
            size,
            tiles,
            wp.array(shifts, dtype=wp.int32, device=device),
            int(not whole_on_host),
            out,
            out_valid,
            tile_sums,
        ],
        device=device,
    )
    sums = tile_sums.numpy()
    stack = (ny * nx, size * size)
    moved, weights, partial = out.numpy().reshape(stack), out_valid.numpy().reshape(stack), sums[2] > 0
    whole = np.flatnonzero(shifts[:, 2]) if whole_on_host else ()
    if len(whole):
        # the source tiles' corners, tiles row by row
        top = ys[whole // nx] + shifts[whole, 1]
        left = xs[whole % nx] + shifts[whole, 0]
        windows = np.lib.stride_tricks.sliding_window_view
        moved.reshape(-1, size, size)[whole] = windows(np.asarray(image), (size, size))[top, left]
        if valid is not None:  # (without, the whole tiles' weights are all 1: not partial, not read)
            weights.reshape(-1, size, size)[whole] = windows(valid, (size, size))[top, left]
            partial.ravel()[whole] = (weights[whole] != 1).any(axis=1)
    return (
        moved,
        weights[partial.ravel()] if partial.any() else None,
        sums[0] / float(size * size),
        sums[1] / float(size * size),
        partial,
    )



def predict_displacement(
    reference,
    gradient,
    xy,
    *,
    window_sizes=PREDICTOR_WINDOWS,
    min_dots_per_window=5.0,
    min_dots_per_box=20.0,
    mask=None,
    device=None,
):
    """Predict each dot's displacement by coarse-to-fine correlation, and say how far to trust it.

    Parameters
    ----------
    reference, gradient : (H, W) arrays
        The image pair.
    xy : (N, 2) array
        Reference-image positions (x = column, y = row) at which to predict; non-finite rows give NaN.
    window_sizes : tuple of int, keyword-only
        Tile size of each correlation pass, coarse first (tiles side by side, no overlap; a size may
        repeat: another pass at that size). The first should be at least four times the largest
        displacement; sizes larger than the image are reduced to it. The passes end early at the first
        one that changes no tile's displacement by more than 0.25 px from the coarser field. Where it
        leaves at least eight tiles along each axis, the first of several passes takes about every other
        tile along each axis (evenly spaced, the outer ones at the image edges).
    min_dots_per_window : float, keyword-only
        Passes whose tiles would hold fewer dots than this on average (from the number of ``xy`` inside
        the image) are replaced by one pass with the smallest tile (a multiple of 8 px) that holds that
        many: sparse patterns, calibration grids.
    min_dots_per_box : float, keyword-only
        The significance is pooled over a square block of finest tiles (1x1, 3x3, 5x5 ...) holding at
        least this many dots: the chance correlation of unrelated images falls as one over the square
        root of the number of dots.
    mask : (H, W) bool array, optional
        True on pixels to exclude: they take no part in the correlation.
    device : str, optional
        Warp device of the window deformation ("cpu", "cuda:0"; Warp's default when None); the
        correlations run on the CPU with SciPy's FFTs.

    Returns
    -------
    uv : (N, 2) float array
        Predicted displacement (u, v) in pixels: the last pass's tile field (the mean shift by which
        the gradient image was moved back, the coarser field rounded at every pixel, plus the tile's
        correlation peak (:func:`peak_index`: on a regular dot grid, of the lattice's equal peaks the one
        nearest the searched displacement) by a three-point Gaussian fit; a tile failing the normalised median test
        against its eight neighbours takes their median), bilinearly interpolated from the tile
        centres to ``xy`` (linearly extrapolated beyond the outer centres).
    quality : (N,) float array
        Normalised correlation coefficient of the last pass's tiles (mean-subtracted, masked pixels left
        out) at the median residual displacement of each tile's neighbours, read off the plane by a
        separable three-point Gaussian (not its own peak, so that an unrelated
        gradient image does not gain the bias of the maximum over the plane), pooled over the block of
        ``min_dots_per_box`` dots and interpolated to ``xy`` like ``uv``: about 1 where the prediction
        is right, about 0 for an unrelated gradient image.

    Notes
    -----
    Not part of Rajendran, Bane and Vlachos (2019), where the reference position itself is the
    prediction for the gradient image (which limits the displacement to the window margin). The passes
    are a multigrid correlation (Scarano and Riethmuller 1999; Scarano 2002) whose deformation moves
    pixels by whole pixels only, which the tracker can afford (the prediction is only required to
    within a fraction of ``max_displacement``; the peak fit measures the residual); the significance
    is the normalised correlation at the predicted displacement (Raffel et al. 2018, section 5.5: a
    correct displacement leaves two nearly identical images).
    """
    # the pixels are taken as float32 as the tiles are cut (float64 images are not copied first)
    a, b = (np.asarray(f) for f in (reference, gradient))
    a, b = (f if f.dtype == np.float32 else np.asarray(f, dtype=np.float64) for f in (a, b))
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    h, w = a.shape
    n = len(xy)
    fin = np.isfinite(xy).all(axis=1)
    sizes, density = predictor_passes(a.shape, dots_inside(xy, a.shape), window_sizes, min_dots_per_window)
    if not sizes or n == 0:
        return np.zeros((n, 2)), np.zeros(n)
    valid = None if mask is None else (~np.asarray(mask, dtype=bool)).astype(np.float32)

    spectra = {}  # the reference tiles' spectra of each tile grid, computed once
    field = None  # (u, v, centres_y, centres_x) of the previous pass
    for size in sizes:
        sparse = field is None and len(sizes) > 1 and _sparse_grid(h, w, size)
        ys, xs = _pass_grid(h, w, size, sparse=sparse)
        ny, nx = len(ys), len(xs)
        if (size, sparse) not in spectra:
            spectra[size, sparse] = _reference_spectra(a, valid, ys, xs, size)
        cy, cx = ys + (size - 1) / 2.0, xs + (size - 1) / 2.0
        tb, wt, base_u, base_v, prev_u, prev_v, partial = _gradient_tiles(b, valid, field, ys, xs, size, device)
        half = size // 2
        pl, norm, usable, energy, r, c, top = _searched_planes(
            spectra[size, sparse], tb, partial, wt, (ny, nx), size, whole=field is None
        )
        r, c = np.clip(r, 1, size - 2), np.clip(c, 1, size - 2)
        i = np.arange(len(pl))
        scaled = np.where(norm > 0, norm, 1.0).astype(np.float32)  # the planes normalised where read
        up, left, centre, right, down = (pl[i, r + dr - top, c + dc] / scaled for dr, dc in _CROSS)
        # the fits along the columns and along the rows in one call
        off = three_point_offset(np.stack([up, left]), np.stack([centre, centre]), np.stack([down, right]))
        rv = (r + off[0] - half).reshape(usable.shape)
        ru = (c + off[1] - half).reshape(usable.shape)
        ru, rv = np.where(usable, ru, np.nan), np.where(usable, rv, np.nan)
        u, v = _replace_outliers(np.stack([base_u + ru, base_v + rv]))
        field = (_fill_nan(u), _fill_nan(v), cy, cx)
        change = np.maximum(np.abs(field[0] - prev_u), np.abs(field[1] - prev_v))
        if np.all(change <= PREDICTOR_RESOLVED_PX):
            break  # the coarser field already gave this one to within the finer pass's noise
    u, v = field[0], field[1]

    # Significance of the finest pass: each tile's coefficient at its neighbours' residual displacement.
    mu, mv = (_fill_nan(f) for f in _neighbour_median(np.stack([ru, rv])))
    coef = _gaussian_sample(pl, mv.ravel() + half, mu.ravel() + half, scaled, top=top, height=size).reshape(u.shape)
    coef = _pooled_coefficient(coef, usable, energy, pooling_block(density, size, min_dots_per_box))

    pts = np.where(fin[:, None], xy, 0.0)
    u, v, quality = _bilinear(np.stack([u, v, coef]), cy, cx, pts[:, 1], pts[:, 0])
    uv = np.stack([u, v], axis=1)
    uv[~fin] = np.nan
    quality = np.where(fin, quality, np.nan)
    return uv, quality


def _gradient_tiles(b, valid, field, ys, xs, size, device):
    """A pass's gradient tiles stacked, their weights (None: all whole) and which are partial, with the
    coarser field's rounded shifts ``base`` and its value ``prev`` at the tile centres (0 at the first pass)."""
    if field is None:
        tb = _tile_stack(_tiles_view(b, ys, xs, size))
        vb = None if valid is None else _tiles_view(valid, ys, xs, size)
        partial = _partial_tiles(vb)
        wt = _tile_stack(vb, which=partial) if _any(partial) else None
        return tb, wt, 0.0, 0.0, 0.0, 0.0, partial
    # the gradient image moved back by the coarser field rounded to whole pixels at every pixel
    # (a nearest-pixel window deformation: no interpolation, the residual is measured below),
    # its tiles stacked
    cy, cx = ys + (size - 1) / 2.0, xs + (size - 1) / 2.0
    tb, wt, base_u, base_v, partial = _deform_nearest(b, valid, field, ys, xs, size, device)
    prev_u, prev_v = _bilinear(np.stack(field[:2]), field[2], field[3], cy[:, None], cx[None, :])
    return tb, wt, base_u, base_v, prev_u, prev_v, partial


def _searched_planes(spectra, tb, partial, wt, shape, size, *, whole):
    """A pass's correlation planes (their rows from ``top`` on), norms, usable tiles and energies, and each
    plane's highest pixel (row, column): over the ``whole`` plane at the first pass, else within a
    quarter of the tile around the coarser pass's displacement."""
    half = size // 2
    if whole:
        top = 0  # the whole plane is searched
        pl, norm, usable, energy = _correlate_tiles(spectra, tb, partial, wt, shape, size)
        r, c = np.divmod(peak_index(pl, centre=half), size)
        return pl, norm, usable, energy, r, c, top
    # the coarser pass placed the window: look for the residual within a quarter
    lo, m = half - size // 4, 2 * (size // 4) + 1
    # the planes' rows read (from ``top``): those searched and their neighbours, and those of the
    # significance sample below (the neighbours' median residual lies within the search, so its
    # nearest row within rint(lo - 0.5) ... rint(lo + m - 0.5)) and their neighbours
    top = max(min(lo, int(np.rint(lo - 0.5))) - 1, 0)
    stop = min(max(lo + m - 1, int(np.rint(lo + m - 0.5))) + 2, size)
    pl, norm, usable, energy = _correlate_tiles(spectra, tb, partial, wt, shape, size, rows=(top, stop))
    search = pl[:, lo - top : lo - top + m, lo : lo + m]
    r, c = np.divmod(peak_index(search, centre=half - lo), m)
    return pl, norm, usable, energy, r + lo, c + lo, top


#: :data:`PREDICTOR_PEAK_TIE`'s share of the largest sample a peak must reach, as float32 (the planes' type).
PEAK_KEEP = np.float32(1.0 - PREDICTOR_PEAK_TIE)


def peak_index(blocks, *, centre):
    """Each searched block's correlation peak, as a flat index (row * m + column) into its ``(m, m)`` block.

    The largest sample (the first, row by row), unless other peaks (samples no smaller than any other of
    the :data:`PREDICTOR_PEAK_REACH` samples around them inside the block, so not the shoulder of a broad peak) reach
    :data:`PEAK_KEEP` times it: then, of those and it, the one nearest the sample ``(centre, centre)`` (the
    first, row by row, of equals). A regular dot grid whose pitch divides the tile has a peak at every
    lattice shift; the nearest is the smallest displacement (:data:`PREDICTOR_PEAK_TIE`).

    Examples
    --------
    >>> b = np.zeros((1, 5, 5), np.float32)
    >>> b[0, 0, 0], b[0, 2, 3], b[0, 4, 4] = 1.0, 0.95, 0.5
    >>> divmod(int(peak_index(b, centre=2)[0]), 5)  # 0.95 ties 1.0 and lies nearer the centre
    (2, 3)
    >>> b[0, 2, 3] = 0.8
    >>> divmod(int(peak_index(b, centre=2)[0]), 5)
    (0, 0)
    """
    k, m = blocks.shape[0], blocks.shape[-1]
    flat = blocks.reshape(k, -1)
    at = np.argmax(flat, axis=1)
    keep = flat[np.arange(k), at] * PEAK_KEEP
    several = np.count_nonzero(flat >= keep[:, None], axis=1) > 1
    if not several.any():
        return at
    sub = blocks[several]
    reach = 2 * PREDICTOR_PEAK_REACH + 1
    around = ndimage.maximum_filter(sub, size=(1, reach, reach), mode="constant", cval=-np.inf)
    local = (sub >= keep[several, None, None]) & (sub >= around)
    d2 = (np.arange(m) - centre) ** 2
    dist = np.where(local, d2[:, None] + d2[None, :], np.iinfo(np.int64).max)
    at[several] = np.argmin(dist.reshape(len(sub), -1), axis=1)
    return at


def _pooled_coefficient(coef, usable, energy, k):
    """The tiles' coefficients pooled over k x k tiles as one coefficient: sum of covariances over the root
    of the sums of variances, so tiles without dots (variance of the noise only) hardly count."""
    ea, eb = (np.where(usable, e, 0.0) for e in energy)
    cov = np.where(usable, coef, 0.0) * np.sqrt(ea * eb)
    pooled = usable
    if k > 1:
        cov, ea, eb, share = (
            ndimage.uniform_filter(f, size=k, mode="constant") for f in (cov, ea, eb, usable.astype(np.float64))
        )
        # a block without usable tiles pools to rounding residues of the filter's running sums (which
        # can even end a hair below zero): no coefficient there
        pooled = share > 0.5 / (k * k)
    den = np.sqrt(np.maximum(ea * eb, 0.0))
    ok = pooled & (den > 0)
    return np.where(ok, cov / np.where(ok, den, 1.0), 0.0)


def _pass_grid(h, w, size, *, sparse):
    """The first row and column of a pass's tiles in an ``h`` x ``w`` image."""
    if sparse:
        # the first pass only places the next one's search (a quarter of its tile): tiles at most twice
        # their side apart (about a quarter of them)
        return _sparse_tile_grid(h, size), _sparse_tile_grid(w, size)
    return _tile_grid(h, size), _tile_grid(w, size)


# --- a stack of pairs on one Warp device ------------------------------------------------------------


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


def predict_displacement_stack(references, gradients, xy, *, sizes, min_dots_per_box=20.0, density, device=None):
    """Predict each dot's displacement in each of B image pairs, and say how far to trust it.

    :func:`predict_displacement` (``mask=None``) for every pair, all pairs in each
    launch.

    Parameters
    ----------
    references, gradients : (B, H, W) float64 Warp arrays (or NumPy arrays, uploaded)
        The image pairs.
    xy : (B, N) ``wp.vec2d`` Warp array (or (B, N, 2) NumPy array)
        Reference-image positions (x = column, y = row) at which to predict; non-finite rows give NaN.
    sizes : sequence of int, keyword-only
        Tile size of each pass, as :func:`tracking.predict.predictor_passes` gives it for the pairs'
        shape and number of dots inside the image (shared by all pairs of the stack).
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
    Every pass is launched for the whole stack (17 launches, 18 where the correlation is by direct DFTs:
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
