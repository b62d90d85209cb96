# ruff: noqa: UP018, RUF046
# (``int(0)`` declares a dynamic Warp variable that a loop may change; a bare ``0`` is a constant to Warp.)
"""Warp kernel of the predictor's nearest-pixel window deformation (host code:
:func:`tracking.predict.predict_displacement`): the gradient image moved back by the coarser pass's
tile field, one thread per pixel.
"""

import warp as wp

from synthbos.device import quiet_warp

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile


# --- the predictor's nearest-pixel window deformation ------------------------------------------------


@wp.func
def field_at_row(field: wp.array2d(dtype=wp.float64), iy: int, ty: wp.float64, ix: int) -> wp.float64:
    """A tile field's column ``ix`` of centres interpolated linearly to a row in cell ``iy`` at fraction
    ``ty`` (beyond [0, 1]: linear extrapolation): the first half of a separable bilinear interpolation."""
    iy1 = wp.min(iy + 1, field.shape[0] - 1)
    return (wp.float64(1.0) - ty) * field[iy, ix] + ty * field[iy1, ix]


@wp.func
def cell_ends(
    field_u: wp.array2d(dtype=wp.float64), field_v: wp.array2d(dtype=wp.float64), iy: int, ty: wp.float64, ix: int
) -> wp.vec4d:
    """(u, u, v, v) of the tile fields at centre columns ``ix`` and ``ix + 1`` (the last column at the
    edge), each interpolated to a row in cell ``iy`` at fraction ``ty`` (:func:`field_at_row`)."""
    ix1 = wp.min(ix + 1, field_u.shape[1] - 1)
    return wp.vec4d(
        field_at_row(field_u, iy, ty, ix),
        field_at_row(field_u, iy, ty, ix1),
        field_at_row(field_v, iy, ty, ix),
        field_at_row(field_v, iy, ty, ix1),
    )


@wp.func
def rounds_to(a: wp.float64, b: wp.float64, s: int) -> int:
    """1 where ``a`` and ``b`` both lie more than 1e-6 inside the rounding interval of the integer ``s``
    (so does then anything between them, give or take rounding errors far smaller), else 0."""
    lo = wp.float64(s) - wp.float64(0.5) + wp.float64(1e-6)
    hi = wp.float64(s) + wp.float64(0.5) - wp.float64(1e-6)
    if a > lo and a < hi and b > lo and b < hi:
        return 1
    return 0


@wp.func
def copy_row(
    image: wp.array(dtype=wp.float64),
    valid: wp.array(dtype=wp.float32),
    use_valid: int,
    src0: int,
    copied: int,
    at: int,
    out: wp.array(dtype=wp.float32),
    out_valid: wp.array(dtype=wp.float32),
) -> int:
    """``copied`` pixels of ``image`` from ``src0`` on copied to ``out`` from ``at`` on as float32, with
    their weights (``valid``'s if ``use_valid``, else 1) to ``out_valid``; returns how many weights are
    not 1."""
    n_part = int(0)
    for c in range(copied):
        v = wp.float32(1.0)
        if use_valid != 0:
            v = valid[src0 + c]
            if v != wp.float32(1.0):
                n_part += 1
        out[at + c] = wp.float32(image[src0 + c])
        out_valid[at + c] = v
    return n_part


@wp.kernel
def deform_nearest_kernel(
    image: wp.array(dtype=wp.float64),
    valid: wp.array(dtype=wp.float32),
    use_valid: int,
    h: int,
    w: int,
    field_u: wp.array2d(dtype=wp.float64),
    field_v: wp.array2d(dtype=wp.float64),
    row_cell: wp.array(dtype=wp.int32),
    row_frac: wp.array(dtype=wp.float64),
    col_cell: wp.array(dtype=wp.int32),
    col_frac: wp.array(dtype=wp.float64),
    y0: int,
    x0: int,
    size: int,
    tiles: int,
    tile_shift: wp.array2d(dtype=wp.int32),
    copy_whole: int,
    out: wp.array(dtype=wp.float32),
    out_valid: wp.array(dtype=wp.float32),
    tile_sums: wp.array3d(dtype=wp.int32),
):
    """One row of ``tiles`` consecutive ``size`` x ``size`` tiles (those from tile column ``t * tiles``;
    1 on a GPU, a whole row of tiles on the CPU) of the block of tiles starting at (``y0``, ``x0``):
    the ``h`` x ``w`` ``image`` (flattened, row by row) moved back by the tile field rounded to whole
    pixels. The tiles' pixel (r, c) (block coordinates) takes the pixel at (y0 + r + rint(v),
    x0 + c + rint(u)) (the edge pixel beyond the image) as float32; ``out_valid`` 1 where that lies
    inside the image (times ``valid``, flattened like ``image``, there if ``use_valid``). ``out`` and
    ``out_valid`` hold the tiles one after the other, row by row of tiles, each ``size * size`` pixels
    row by row. ``tile_sums[0|1, tile row, tile column]`` sum the rounded shifts u and v over the
    tile's pixels and ``tile_sums[2, ...]`` counts its pixels whose weight is not 1. The field is
    interpolated bilinearly, each row and column given by its cell of tile centres and fraction in it:
    first along the rows at the two centre columns around the pixel, then along the row.
    ``tile_shift[tile] = (u, v, 1)`` says that every pixel of the tile (row by row of tiles) rounds to
    the shifts (u, v) and takes its pixel from inside the image (``(0, 0, 0)``: not known): such a tile
    is copied row by row without the interpolation (the same result) if ``copy_whole``, else left to
    the caller (its pixels and weights are not written nor its weights counted; its shift sums are). A row of
    another tile whose ends lie in one cell of centres, round alike there (:func:`rounds_to`) and take
    their pixels from inside the image is copied alike."""
    r, t = wp.tid()
    nx = tile_sums.shape[2]
    row = y0 + r
    iy = row_cell[row]
    ty = row_frac[row]
    tile_row = r / size
    one = wp.float64(1.0)
    cell = int(-1)
    ends = wp.vec4d()  # u and v at the row's two centre columns of the current cell (cell_ends)
    for k in range(t * tiles, wp.min(t * tiles + tiles, nx)):
        sum_u = int(0)
        sum_v = int(0)
        n_part = int(0)
        # the tile's row r - tile_row * size in the tile-major output
        tile = tile_row * nx + k
        at = (tile * size + r - tile_row * size) * size
        col0 = x0 + k * size
        # one shift (su1, sv1) for the tile's whole row, from inside the image: known for the tile
        # (tile_shift: 1), else found from the row's ends where they lie in one cell of centres (the
        # field is linear along the row there: 2)
        one_shift = tile_shift[tile, 2]
        su1 = tile_shift[tile, 0]
        sv1 = tile_shift[tile, 1]
        if one_shift == 0:
            ix = col_cell[col0]
            if ix == col_cell[col0 + size - 1]:
                if ix != cell:
                    cell = ix
                    ends = cell_ends(field_u, field_v, iy, ty, ix)
                ta = col_frac[col0]
                tb = col_frac[col0 + size - 1]
                ua = (one - ta) * ends[0] + ta * ends[1]
                va = (one - ta) * ends[2] + ta * ends[3]
                su1 = int(wp.rint(ua))
                sv1 = int(wp.rint(va))
                ub = (one - tb) * ends[0] + tb * ends[1]
                vb = (one - tb) * ends[2] + tb * ends[3]
                same = rounds_to(ua, ub, su1) * rounds_to(va, vb, sv1)
                rv = row + sv1
                if same != 0 and rv >= 0 and rv < h and col0 + su1 >= 0 and col0 + su1 + size <= w:
                    one_shift = 2
        pixels = size  # those moved one by one below
        if one_shift != 0:
            pixels = 0
            # one shift for the whole row, all of it from inside the image: a copy (but of the tiles
            # that the caller copies)
            sum_u = su1 * size
            sum_v = sv1 * size
            src0 = (row + sv1) * w + col0 + su1
            copied = size
            if one_shift == 1 and copy_whole == 0:
                copied = 0
            n_part = copy_row(image, valid, use_valid, src0, copied, at, out, out_valid)
        for c in range(pixels):
            col = col0 + c
            ix = col_cell[col]
            if ix != cell:
                cell = ix
                ends = cell_ends(field_u, field_v, iy, ty, ix)
            tx = col_frac[col]
            su = int(wp.rint((one - tx) * ends[0] + tx * ends[1]))
            sv = int(wp.rint((one - tx) * ends[2] + tx * ends[3]))
            sum_u += su
            sum_v += sv
            ry = row + sv
            rx = col + su
            src = wp.clamp(ry, 0, h - 1) * w + wp.clamp(rx, 0, w - 1)
            v = wp.float32(0.0)
            if ry >= 0 and ry < h and rx >= 0 and rx < w:
                v = wp.float32(1.0)
                if use_valid != 0:
                    v = valid[src]
            if v != wp.float32(1.0):
                n_part += 1
            out[at + c] = wp.float32(image[src])
            out_valid[at + c] = v
        wp.atomic_add(tile_sums, 0, tile_row, k, sum_u)
        wp.atomic_add(tile_sums, 1, tile_row, k, sum_v)
        if n_part > 0:
            wp.atomic_add(tile_sums, 2, tile_row, k, n_part)
