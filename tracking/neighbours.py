"""Local linear fit of scattered vectors from each point's nearest neighbours.

The reference of the tracker's outlier tests (a normalised median test on scattered data, Westerweel and
Scarano 2005, with a local linear reference as in Duncan et al. 2010): for every query point, the least
squares plane ``f = c + G d`` through the vectors of its ``k`` nearest points and the median distance of
those vectors from it. :func:`neighbour_fit` is a Warp kernel (one thread per query, the points sorted
into square cells, growing blocks of cells around the query searched until one holds k points within its
inner edge); :func:`tracking.reference.neighbour_fit_numpy` is the array-program reference (a k-d tree) that defines the
result.
"""

from __future__ import annotations

import functools

import numpy as np
import warp as wp

from .neighbour_kernels import neighbour_fit_kernel
from .windows import median_network
from .workspace import scratch

__all__ = ["neighbour_fit"]

#: Points per cell, on average, of the kernel's cell grid.
_POINTS_PER_CELL = 4.5



@functools.lru_cache(maxsize=8)
def _network(k):
    """``median_network(k)`` made once per k (read only)."""
    net = median_network(k)
    net.flags.writeable = False
    return net


def _cell_grid(xy, query, count):
    """Square cells holding ``count`` points on average over the box of ``xy`` and ``query``: the origin,
    side and shape, the start of each cell's run in the sorted order (``nx * ny + 1``) and the order."""
    # each coordinate reduced as one (strided) column: a reduction along an axis of an (n, 2) array or of
    # its transpose runs a short loop per point and costs some hundred times more
    boxes = (xy,) if query is xy else (xy, query)
    lo = np.array([min(float(a[:, c].min()) for a in boxes) for c in range(2)])
    hi = np.array([max(float(a[:, c].max()) for a in boxes) for c in range(2)])
    extent = np.maximum(hi - lo, 1e-9)
    side = float(np.sqrt(extent[0] * extent[1] * count / len(xy)))
    side = max(side, float(extent.max()) / 4096.0, 1e-9)
    nx, ny = (int(np.floor(e / side)) + 1 for e in extent)
    cx = np.clip(np.floor((xy[:, 0] - lo[0]) / side).astype(np.int64), 0, nx - 1)
    cy = np.clip(np.floor((xy[:, 1] - lo[1]) / side).astype(np.int64), 0, ny - 1)
    cell = cy * nx + cx
    # the order within a cell does not matter (ties go to the lower index); 16-bit keys sort by radix
    key = cell.astype(np.uint16) if nx * ny <= 65536 else cell
    order = np.argsort(key, kind="stable").astype(np.int32)
    start = np.zeros(nx * ny + 1, dtype=np.int32)
    np.cumsum(np.bincount(cell, minlength=nx * ny), out=start[1:])
    return float(lo[0]), float(lo[1]), side, nx, ny, start, order


def neighbour_fit(xy, uv, query, self_index, *, k, return_neighbours=False, device=None):
    """Local linear fit of ``uv`` at each query point from its ``k`` nearest points of ``xy``.

    Parameters
    ----------
    xy : (M, 2) array
        Points (finite), ``M > k``.
    uv : (M, 2) array
        Their vectors.
    query : (N, 2) array
        Points at which to fit (finite).
    self_index : (N,) int array
        The query's own row in ``xy`` (left out of its neighbours), or -1.
    k : int, keyword-only
        Neighbours per fit.
    return_neighbours : bool, keyword-only
        Also return the neighbours' rows.

    device : str or None, keyword-only
        Warp device ("cpu", "cuda:0"); Warp's default when None.

    Returns
    -------
    value : (N, 2) array
        The fit's value at the query point.
    spread : (N,) array
        Median distance of the neighbours' vectors from the fit.
    neighbours : (N, k) int array
        Only with ``return_neighbours``: the rows of ``xy`` of each query's neighbours (the set; the
        order within a row is not part of the result).

    Notes
    -----
    ``G`` and ``c`` solve the 2x2 normal equations of the offsets and vectors centred on their means,
    ``c = mean f - G mean d``; a ridge of ``1e-6 (k + trace)`` keeps collinear neighbourhoods finite.
    """
    same = query is xy  # the points themselves (the outlier test)
    xy = np.ascontiguousarray(xy, dtype=np.float64)
    query = xy if same else np.ascontiguousarray(query, dtype=np.float64)
    n = len(query)
    if n == 0:
        return (np.zeros((0, 2)), np.zeros(0)) + ((np.zeros((0, k), dtype=np.int64),) if return_neighbours else ())
    if len(xy) <= k:
        raise ValueError(f"neighbour_fit needs more than k = {k} points, got {len(xy)}")
    x0, y0, side, nx, ny, start, order = _cell_grid(xy, query, _POINTS_PER_CELL)
    if same:  # already in the order of their cells
        query_order = order
    else:
        qx = np.clip(np.floor((query[:, 0] - x0) / side), 0, nx - 1)
        qy = np.clip(np.floor((query[:, 1] - y0) / side), 0, ny - 1)
        query_order = np.argsort(qy * nx + qx).astype(np.int32)
    # the query's own index where it is one of the points; -1 (never a point's index) otherwise
    own = np.ascontiguousarray(self_index, dtype=np.int32)
    rows = 1 if wp.get_device(device).is_cpu else n  # scratch rows: CPU threads run one after another

    def arr(a, dtype):  # CPU: the NumPy array itself, no copy
        return wp.array(a, dtype=dtype, device=device, copy=False)

    value = wp.empty((n, 2), dtype=wp.float64, device=device)
    spread = wp.empty(n, dtype=wp.float64, device=device)
    nb = wp.empty((n, k), dtype=wp.int32, device=device)
    wp.launch(
        neighbour_fit_kernel,
        dim=n,
        inputs=[
            arr(query_order, wp.int32),
            arr(xy, wp.vec2d),
            arr(np.ascontiguousarray(uv, dtype=np.float64), wp.vec2d),
            arr(query, wp.vec2d),
            arr(own, wp.int32),
            arr(start, wp.int32),
            arr(order, wp.int32),
            arr(np.take(xy, order, axis=0), wp.vec2d),  # (take: a row gather ~15 times cheaper than xy[order])
            x0,
            y0,
            side,
            nx,
            ny,
            rows,
            scratch("neighbour_near", (rows * k,), wp.vec2d, device),
            scratch("neighbour_work", (rows * k,), wp.vec4d, device),
            scratch("neighbour_resid", (rows * k,), wp.float64, device),
            value,
            spread,
            nb,
            arr(_network(k), wp.int32),
        ],
        device=device,
    )
    if return_neighbours:
        return value.numpy(), spread.numpy(), nb.numpy()
    return value.numpy(), spread.numpy()
