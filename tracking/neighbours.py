"""The neighbour tests: the local linear fit of scattered vectors from each point's nearest neighbours,
for one set of points or for a stack of pairs' dots on the device.

The reference of the tracker's outlier tests (a normalised median test on scattered data, Westerweel and
Scarano 2005, with a local linear reference as in Duncan et al. 2010): for every query point, the least
squares plane ``f = c + G d`` through the vectors of its ``k`` nearest points and the median distance of
those vectors from it. :func:`tracking.reference.neighbour_fit_numpy` is the array-program reference (a
k-d tree) that defines the result.

One set of points (:func:`neighbour_fit`, ``track_pair``'s tests) is a stack of one: the fit is
:func:`neighbour_fit_stack`'s. The stacked form (:func:`neighbour_fit_stack`,
:func:`neighbour_outliers_stack`, :func:`confirmed_by_neighbours_stack`) is
the tracker's outlier test and its confirmation of the predictor for all the pairs of a stack
in every launch, with no host round trip (the number of launches does not depend on the number of
pairs). A pair's dots are the rows of ``(B, N)`` device arrays and the subsets a test uses are masks;
each pair gets a grid of square cells over the box of its points and queries, built on the device by a
counting sort over all pairs' cells (atomics and one exclusive scan), searched in growing blocks of cells
around each query until one holds k points within its inner edge (:mod:`tracking.neighbour_kernels`).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
import warp as wp

from . import neighbour_kernels as nk
from .windows import median_network
from .workspace import on_device, scratch

__all__ = ["confirmed_by_neighbours_stack", "neighbour_fit", "neighbour_fit_stack", "neighbour_outliers_stack"]

#: Points per cell, on average, of the kernel's cell grid.
_POINTS_PER_CELL = 4.5



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
        The query's own row in ``xy`` (left out of its neighbours; the query must lie at that point), or -1.
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
    The fit is :func:`neighbour_fit_stack`'s for a stack of one: the points are its first ``M`` dots, a
    query that is not one of them a dot of its own after them.
    """
    xy = np.ascontiguousarray(xy, dtype=np.float64)
    query = xy if query is xy else np.ascontiguousarray(query, dtype=np.float64)
    n, m = len(query), len(xy)
    if n == 0:
        return (np.zeros((0, 2)), np.zeros(0)) + ((np.zeros((0, k), dtype=np.int64),) if return_neighbours else ())
    if m <= k:
        raise ValueError(f"neighbour_fit needs more than k = {k} points, got {m}")
    own = np.asarray(self_index, dtype=np.int64)
    mine = own >= 0
    if query is not xy and not np.array_equal(query[mine], xy[own[mine]]):
        raise ValueError("neighbour_fit: a query with a self_index must lie at that point of xy")
    # the dots of the stack of one: the points, then the queries that are not points
    extra = np.flatnonzero(~mine)
    row = own.copy()
    row[extra] = m + np.arange(extra.size)
    dots = np.concatenate([xy, query[extra]]) if extra.size else xy
    vectors = np.zeros_like(dots)
    vectors[:m] = uv
    points = np.zeros(len(dots), dtype=np.int32)
    points[:m] = 1
    queries = np.zeros(len(dots), dtype=np.int32)
    queries[row] = 1
    device = _device_of(device)
    on = functools.partial(on_device, ndim=2, device=device)
    dots, vectors = on(dots[None], wp.vec2d, name="xy"), on(vectors[None], wp.vec2d, name="uv")
    role = scratch("nstack_role", dots.shape, wp.int32, device)
    wp.launch(nk.roles_kernel, dim=dots.shape, inputs=[on(points[None], wp.int32, name="points"),
              on(queries[None], wp.int32, name="queries"), role], device=device)  # fmt: skip
    grid = _build_grids(dots, role, min_points=k + 1, sort_queries=True, device=device)
    value = wp.empty(dots.shape[1], dtype=wp.vec2d, device=device)
    spread = wp.empty(dots.shape[1], dtype=wp.float64, device=device)
    near = wp.empty((dots.shape[1], k), dtype=wp.int32, device=device) if return_neighbours else None
    _fit(dots, vectors, grid, k=int(k), exclude_self=True, neighbours=near, device=device, value=value, spread=spread)
    out = (value.numpy()[row].reshape(n, 2), spread.numpy()[row])
    return (*out, near.numpy()[row]) if return_neighbours else out


# --- the stacked form: the tests of many pairs in every launch ------------------------------------


#: Threads of a pair's box reduction (``pair_stats_kernel``): each takes every this many-th dot.
_STATS_STEP = 128
#: Bytes of fit scratch rows (``near``, ``work``, ``resid``: 56 bytes per neighbour) at most on a GPU;
#: the fit kernel's threads are capped to fit (each then takes several queries).
_FIT_SCRATCH_BYTES = 64 << 20
#: A grid's side is at least 1/4096 of the box's longer side (``tracking.neighbour_kernels.grid_params_kernel``).
_MAX_CELLS_PER_ROW = 4097


def _cell_stride(n):
    """Cells set aside per pair for ``n`` dots: a grid of ``m <= n`` points has ``nx * ny <= (ex / s + 1)
    (ey / s + 1) = m / per_cell + (ex + ey) / s + 1`` cells with ``ex / s, ey / s <= 4096`` (side ``s``),
    plus the end of the last run; a little more for rounding."""
    return int(n / _POINTS_PER_CELL) + 2 * _MAX_CELLS_PER_ROW + 8


@functools.lru_cache(maxsize=16)
def _device_network(k, device):
    """``median_network(k)`` on ``device`` (by name), copied there once."""
    return wp.array(median_network(k), dtype=wp.int32, device=device)


def _device_of(device, *arrays):
    """The device asked for, else that of the first Warp array given, else Warp's default."""
    if device is None:
        device = next((a.device for a in arrays if isinstance(a, wp.array)), None)
    return wp.get_device(device)


class _Grid(NamedTuple):
    """Every pair's cell grid over the dots of one role array (see ``tracking.neighbour_kernels``)."""

    count: wp.array  # (B, 2): points, queries
    origin: wp.array  # (B,) vec2d
    side: wp.array  # (B,) float64
    shape: wp.array  # (B,) vec2i, (0, 0) for a pair left out
    stride: int  # cells per pair
    point_start: wp.array  # (B * stride + 1,): the start of each cell's run of points; the last: their number
    cell_points: wp.array  # (B * N,): the points' global indices in the order of their cells
    cell_xy: wp.array  # (B * N,): their positions
    query_start: wp.array  # as point_start, for the queries
    query_order: wp.array  # the queries' global indices in the order of their cells


def _build_grids(xy, role, *, min_points, sort_queries, device):
    """Each pair's cell grid over its dots with a role (the box of the points and the queries, square cells
    of ``_POINTS_PER_CELL`` points on average: ``grid_params_kernel``), the points sorted by cell and, with
    ``sort_queries``, the queries too (else they are the points).
    Pairs with fewer than ``min_points`` points or no query get none."""
    nb, n = role.shape
    stride = _cell_stride(n)
    ncell = nb * stride + 1
    count = scratch("nstack_count", (nb, 2), wp.int32, device)
    lo = scratch("nstack_lo", (nb,), wp.vec2d, device)
    hi = scratch("nstack_hi", (nb,), wp.vec2d, device)
    origin = scratch("nstack_origin", (nb,), wp.vec2d, device)
    side = scratch("nstack_side", (nb,), wp.float64, device)
    shape = scratch("nstack_shape", (nb,), wp.vec2i, device)
    wp.launch(nk.pair_stats_init_kernel, dim=nb, inputs=[count, lo, hi], device=device)
    step = min(_STATS_STEP, n)
    wp.launch(nk.pair_stats_kernel, dim=(nb, step), inputs=[xy, role, step, count, lo, hi], device=device)
    wp.launch(
        nk.grid_params_kernel,
        dim=nb,
        inputs=[count, lo, hi, min_points, _POINTS_PER_CELL, origin, side, shape],
        device=device,
    )
    cell = scratch("nstack_cell", (nb, n), wp.int32, device)
    point_count = scratch("nstack_point_count", (ncell,), wp.int32, device)
    point_slot = scratch("nstack_point_slot", (nb, n), wp.int32, device)
    point_count.zero_()
    if sort_queries:
        query_count = scratch("nstack_query_count", (ncell,), wp.int32, device)
        query_slot = scratch("nstack_query_slot", (nb, n), wp.int32, device)
        query_count.zero_()
    else:
        query_count, query_slot = point_count, point_slot  # (not written)
    counts = (point_count, point_slot, query_count, query_slot)
    wp.launch(
        nk.count_cells_kernel,
        dim=(nb, n),
        inputs=[xy, role, origin, side, shape, stride, int(sort_queries), cell, *counts],
        device=device,
    )
    point_start = scratch("nstack_point_start", (ncell,), wp.int32, device)
    wp.utils.array_scan(point_count, point_start, inclusive=False)
    cell_points = scratch("nstack_cell_points", (nb * n,), wp.int32, device)
    cell_xy = scratch("nstack_cell_xy", (nb * n,), wp.vec2d, device)
    if sort_queries:
        query_start = scratch("nstack_query_start", (ncell,), wp.int32, device)
        wp.utils.array_scan(query_count, query_start, inclusive=False)
        query_order = scratch("nstack_query_order", (nb * n,), wp.int32, device)
    else:
        query_start, query_order = point_start, cell_points
    sorted_ = (cell_points, cell_xy, query_order)
    wp.launch(
        nk.fill_cells_kernel,
        dim=(nb, n),
        inputs=[xy, role, shape, cell, int(sort_queries), point_start, point_slot, query_start, query_slot, *sorted_],
        device=device,
    )
    return _Grid(count, origin, side, shape, stride, point_start, cell_points, cell_xy, query_start, query_order)


def _fit(xy, uv, grid, *, k, exclude_self, neighbours, device, value=None, spread=None):
    """The local linear fit at every query of ``grid`` from the ``k`` nearest of its pair's points (the
    query itself left out with ``exclude_self``): flat (B * N) ``value`` and ``spread`` (scratch unless
    given), set at the queries only; the neighbours' global indices into the (B * N, k) ``neighbours``
    unless None."""
    nb, n = xy.shape
    if value is None:
        value = scratch("nstack_value", (nb * n,), wp.vec2d, device)
        spread = scratch("nstack_spread", (nb * n,), wp.float64, device)
    if device.is_cpu:
        threads, rows = nb * n, 1  # CPU threads run one after another: one scratch row
    else:
        threads = rows = max(1, min(nb * n, _FIT_SCRATCH_BYTES // (56 * k)))
    store = neighbours is not None
    if not store:
        neighbours = scratch("nstack_no_neighbours", (1, k), wp.int32, device)
    wp.launch(
        nk.neighbour_fit_stack_kernel,
        dim=threads,
        inputs=[
            grid.query_order,
            grid.query_start,
            n,
            grid.stride,
            threads,
            int(exclude_self),
            grid.origin,
            grid.side,
            grid.shape,
            grid.point_start,
            grid.cell_points,
            grid.cell_xy,
            xy.flatten(),
            uv.flatten(),
            rows,
            scratch("nstack_near", (rows * k,), wp.vec2d, device),
            scratch("nstack_work", (rows * k,), wp.vec4d, device),
            scratch("nstack_resid", (rows * k,), wp.float64, device),
            _device_network(k, str(device)),
            int(store),
            value,
            spread,
            neighbours,
        ],
        device=device,
    )
    return value, spread


def _check_shapes(arrays):
    shapes = {tuple(a.shape[:2]) for a in arrays}
    if len(shapes) != 1:
        raise ValueError(f"the arrays' (B, N) shapes differ: {sorted(shapes)}")


def neighbour_fit_stack(xy, uv, points, queries, *, k, exclude_self=False, device=None):
    """Local linear fit of each pair's ``points`` at its ``queries``: the stacked
    :func:`neighbour_fit`.

    Parameters
    ----------
    xy, uv : (B, N) wp.vec2d arrays or (B, N, 2) arrays
        Dot positions and vectors of B pairs (finite where a point or a query).
    points, queries : (B, N) wp.int32 arrays or (B, N) arrays
        The dots fitted and the dots to fit at (nonzero).
    k : int, keyword-only
        Neighbours per fit.
    exclude_self : bool, keyword-only
        Leave a query out of its own neighbours (where it is a point too); else its ``self_index`` is -1.
    device : str or None, keyword-only
        Warp device; by default that of the first Warp array given, else Warp's default.

    Returns
    -------
    value : (B, N) wp.vec2d array
        For each pair, at its queries, ``neighbour_fit(xy[P], uv[P], xy[Q], self_index, k=k)[0]`` with
        ``P``, ``Q`` its points' and queries' rows in increasing order (the same to the bit, as are the
        neighbours: ties go to the lower row); NaN elsewhere and in pairs with no more than ``k`` points.
    spread : (B, N) wp.float64 array
        The median distance of the neighbours' vectors from the fit, likewise.
    """
    device = _device_of(device, xy, uv, points, queries)
    xy, uv = on_device(xy, wp.vec2d, 2, device, "xy"), on_device(uv, wp.vec2d, 2, device, "uv")
    points = on_device(points, wp.int32, 2, device, "points")
    queries = on_device(queries, wp.int32, 2, device, "queries")
    _check_shapes((xy, uv, points, queries))
    nb, n = points.shape
    value = wp.full((nb, n), wp.vec2d(np.nan, np.nan), dtype=wp.vec2d, device=device)
    spread = wp.full((nb, n), np.nan, dtype=wp.float64, device=device)
    if nb * n == 0:
        return value, spread
    k = int(k)
    role = scratch("nstack_role", (nb, n), wp.int32, device)
    wp.launch(nk.roles_kernel, dim=(nb, n), inputs=[points, queries, role], device=device)
    grid = _build_grids(xy, role, min_points=k + 1, sort_queries=True, device=device)
    flat = {"value": value.flatten(), "spread": spread.flatten()}
    _fit(xy, uv, grid, k=k, exclude_self=exclude_self, neighbours=None, device=device, **flat)
    return value, spread


def neighbour_outliers_stack(xy, uv, valid, *, k, threshold, epsilon, device=None):
    """Normalised median test of every pair's valid vectors against their neighbours' local linear fit.

    For each pair ``b`` the outlier flags of the dots ``S = flatnonzero(valid[b])`` (in that order), at
    their rows; 0 elsewhere: True where a vector is further from the local linear fit of its ``k`` nearest
    vectors than ``threshold`` times (their median distance from that fit + ``epsilon``), a normalised
    median test for scattered data (Westerweel and Scarano 2005, eq. 2, with a local linear reference as
    in Duncan et al. 2010 so that smooth gradients do not count as outliers), in two rounds.

    Parameters
    ----------
    xy : (B, N) wp.vec2d array or (B, N, 2) array
        Dot positions of B pairs of N rows each (finite where valid).
    uv : (B, N) wp.vec2d array or (B, N, 2) array
        Their displacements.
    valid : (B, N) wp.int32 array or (B, N) array
        The dots tested (nonzero).
    k : int, keyword-only
        Neighbours per fit (``TrackingSettings.outlier_neighbours``).
    threshold, epsilon : float, keyword-only
        ``outlier_threshold`` and ``outlier_epsilon``: a vector further from its fit than ``threshold *
        (spread + epsilon)`` is bad; no vector is bad where ``threshold`` is not finite.
    device : str or None, keyword-only
        Warp device; by default that of the first Warp array given, else Warp's default.

    Returns
    -------
    bad : (B, N) wp.int32 array on ``device``
        1 where a dot is an outlier (launched asynchronously; nothing is copied to the host).

    Notes
    -----
    No dot of a pair with ``|S| <= k + 3`` is bad. The first round fits every valid vector from its k
    nearest other valid dots; in pairs where it finds a bad one and keeps more than ``k + 3``, the second
    refits the dots with a bad neighbour from the kept ones only and tests them again (Westerweel and
    Scarano 2005, eq. 2, on scattered data with a local linear reference, Duncan et al. 2010).
    """
    device = _device_of(device, xy, uv, valid)
    xy, uv = on_device(xy, wp.vec2d, 2, device, "xy"), on_device(uv, wp.vec2d, 2, device, "uv")
    valid = on_device(valid, wp.int32, 2, device, "valid")
    _check_shapes((xy, uv, valid))
    nb, n = valid.shape
    bad = wp.zeros((nb, n), dtype=wp.int32, device=device)
    if nb * n == 0 or not math.isfinite(threshold):
        return bad
    k = int(k)
    min_points = k + 4
    role = scratch("nstack_role", (nb, n), wp.int32, device)
    wp.launch(nk.roles_kernel, dim=(nb, n), inputs=[valid, valid, role], device=device)
    grid = _build_grids(xy, role, min_points=min_points, sort_queries=False, device=device)
    near = scratch("nstack_neighbours", (nb * n, k), wp.int32, device)
    value, spread = _fit(xy, uv, grid, k=k, exclude_self=True, neighbours=near, device=device)
    bad_count = scratch("nstack_bad_count", (nb,), wp.int32, device)
    bad_count.zero_()
    flag_inputs = [uv, value, spread, role, grid.shape, float(threshold), float(epsilon)]
    wp.launch(nk.outlier_flags_kernel, dim=(nb, n), inputs=[*flag_inputs, 1, bad, bad_count], device=device)
    # second round: the kept points; queries where a neighbour was dropped
    role2 = scratch("nstack_role2", (nb, n), wp.int32, device)
    wp.launch(
        nk.refit_roles_kernel,
        dim=(nb, n),
        inputs=[role, grid.shape, grid.count, bad.flatten(), bad_count, near, min_points, role2],
        device=device,
    )
    grid = _build_grids(xy, role2, min_points=min_points, sort_queries=True, device=device)
    value, spread = _fit(xy, uv, grid, k=k, exclude_self=True, neighbours=None, device=device)
    flag_inputs = [uv, value, spread, role2, grid.shape, float(threshold), float(epsilon)]
    wp.launch(nk.outlier_flags_kernel, dim=(nb, n), inputs=[*flag_inputs, 0, bad, bad_count], device=device)
    return bad


def confirmed_by_neighbours_stack(xy, uv, good, query, *, k, threshold, epsilon, tolerance, device=None):
    """Whether each queried dot's displacement agrees with the local linear fit of its pair's good dots.

    For each pair ``b`` (the neighbours overrule a poor prediction, the correlation being least reliable
    in the windows at the image edge): the fit of the
    ``k`` nearest dots of ``G = flatnonzero(good[b])`` at each dot of ``query[b]`` (the query itself not
    left out), 1 where ``|uv - fit| <= min(threshold * (spread + epsilon), tolerance)``.

    Parameters
    ----------
    xy, uv : (B, N) wp.vec2d arrays or (B, N, 2) arrays
        Dot positions and displacements of B pairs (finite where good or queried).
    good, query : (B, N) wp.int32 arrays or (B, N) arrays
        The dots fitted and the dots tested (nonzero).
    k : int, keyword-only
        Neighbours per fit.
    threshold, epsilon : float, keyword-only
        ``outlier_threshold`` and ``outlier_epsilon``.
    tolerance : float, keyword-only
        ``predictor_tolerance``: the largest distance (px) from the fit confirmed.
    device : str or None, keyword-only
        Warp device; by default that of the first Warp array given, else Warp's default.

    Returns
    -------
    ok : (B, N) wp.int32 array on ``device``
        1 where a queried dot is confirmed; 0 elsewhere, and everywhere in a pair with no query or with
        ``|G| <= k + 3``, and where ``threshold`` is not finite.
    """
    device = _device_of(device, xy, uv, good, query)
    xy, uv = on_device(xy, wp.vec2d, 2, device, "xy"), on_device(uv, wp.vec2d, 2, device, "uv")
    good, query = on_device(good, wp.int32, 2, device, "good"), on_device(query, wp.int32, 2, device, "query")
    _check_shapes((xy, uv, good, query))
    nb, n = good.shape
    if nb * n == 0 or not math.isfinite(threshold):
        return wp.zeros((nb, n), dtype=wp.int32, device=device)
    k = int(k)
    role = scratch("nstack_role", (nb, n), wp.int32, device)
    wp.launch(nk.roles_kernel, dim=(nb, n), inputs=[good, query, role], device=device)
    grid = _build_grids(xy, role, min_points=k + 4, sort_queries=True, device=device)
    value, spread = _fit(xy, uv, grid, k=k, exclude_self=False, neighbours=None, device=device)
    ok = wp.empty((nb, n), dtype=wp.int32, device=device)
    wp.launch(
        nk.confirm_flags_kernel,
        dim=(nb, n),
        inputs=[uv, value, spread, role, grid.shape, float(threshold), float(epsilon), float(tolerance), ok],
        device=device,
    )
    return ok
