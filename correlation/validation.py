"""Vector validation: the normalised median test, and the filling of rejected vectors on a vector grid."""

from __future__ import annotations

import numpy as np

from .median_test import median_scale, nan_median, normalised_residual

__all__ = ["FILL_SWEEPS", "fill_by_interpolation", "neighbour_median", "normalized_median_test", "replace_outliers"]

#: Jacobi sweeps of :func:`fill_by_interpolation` after its start from the neighbours' median. The
#: filled values of the turbulent PIV pairs of ``benchmarks/bench_openpiv.py`` change by less than
#: 0.01 px RMS between 10 and 200 sweeps: the start is close, and most holes are a few vectors wide.
FILL_SWEEPS = 30


def _extrapolated_pad(field):
    """Pad a grid by one node on each side, continuing it linearly (``2 f[0] - f[1]``) where possible."""
    f = np.asarray(field, dtype=np.float64)
    for axis in (0, 1):
        n = f.shape[axis]
        first, last = np.take(f, [0], axis), np.take(f, [n - 1], axis)
        if n >= 2:
            first = 2.0 * first - np.take(f, [1], axis)
            last = 2.0 * last - np.take(f, [n - 2], axis)
        f = np.concatenate([first, f, last], axis=axis)
    return f


def _neighbours(field, *, extrapolate=False):
    """(ny, nx, 8) stack of the eight neighbours of every node.

    Beyond the grid: NaN, or with ``extrapolate`` the linear continuation of the grid, so that a node
    on the edge of a field with a gradient sees the same neighbourhood as one inside.
    """
    ny, nx = np.shape(field)
    if extrapolate:
        padded = _extrapolated_pad(field)
    else:
        padded = np.pad(np.asarray(field, dtype=np.float64), 1, constant_values=np.nan)
    return np.stack(
        [
            padded[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx]
            for dy in (-1, 0, 1)
            for dx in (-1, 0, 1)
            if dy or dx
        ],
        axis=-1,
    )


def neighbour_median(field, valid=None):
    """Median of the valid 3x3 neighbours (centre excluded) of every node of a grid.

    Parameters
    ----------
    field : (ny, nx) array
    valid : (ny, nx) bool array, optional
        Nodes that may serve as neighbours (all finite nodes by default).

    Returns
    -------
    median : (ny, nx) float array
        NaN where a node has no valid neighbour.
    count : (ny, nx) int array
        Number of valid neighbours.
    """
    field = np.asarray(field, dtype=np.float64)
    if valid is not None:
        field = np.where(valid, field, np.nan)
    return nan_median(_neighbours(field))


def normalized_median_test(u, v, *, epsilon=0.1, threshold=2.0, valid=None):
    """Flag outliers of a 2-component vector field by the normalised median test.

    Parameters
    ----------
    u, v : (ny, nx) arrays
        Vector components.
    epsilon : float
        Acceptable fluctuation level in pixels (Westerweel and Scarano 2005: 0.1 px).
    threshold : float
        Threshold on the normalised residual (2 in the paper).
    valid : (ny, nx) bool array, optional
        Vectors already known good enough to be neighbours; others are neither used as neighbours
        nor tested here.

    Returns
    -------
    (ny, nx) bool array
        True where the vector fails the test.

    Notes
    -----
    For each component, with ``U_m`` the median of the (valid) 3x3 neighbours and ``r_m`` the median of
    the neighbours' residuals ``|U_i - U_m|``, the normalised residual is
    ``r_0 = |U_0 - U_m| / (r_m + epsilon)`` (Westerweel and Scarano, Exp. Fluids 39 (2005) 1096,
    eq. 2; the core is :mod:`correlation.median_test`); the two components are combined as
    ``sqrt(r_0u^2 + r_0v^2)``. Beyond the edges the field is continued linearly, so that edge nodes of
    a field with a uniform gradient are not flagged (with missing neighbours the median of a one-sided
    neighbourhood is off by the gradient). Nodes with fewer than two valid neighbours are not flagged.
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if valid is None:
        valid = np.isfinite(u) & np.isfinite(v)
    r2 = np.zeros(u.shape)
    enough = np.ones(u.shape, dtype=bool)
    for comp in (u, v):
        nb = _neighbours(np.where(valid, comp, np.nan), extrapolate=True)
        med, scale, count = median_scale(nb)
        with np.errstate(invalid="ignore"):
            r0 = normalised_residual(np.abs(comp - med), scale, epsilon=epsilon)
        r2 += np.where(np.isfinite(r0), r0, 0.0) ** 2
        enough &= count >= 2
    return valid & enough & (np.sqrt(r2) > threshold)


def replace_outliers(u, v, invalid, *, max_sweeps=100):
    """Replace invalid vectors by the median of their valid neighbours.

    Parameters
    ----------
    u, v : (ny, nx) arrays
    invalid : (ny, nx) bool array
        Vectors to replace.
    max_sweeps : int
        Holes are filled from their rims inwards, one ring per sweep; what is left after
        ``max_sweeps`` (or a grid with no valid vector at all) gets the median of all valid
        vectors (or 0).

    Returns
    -------
    u, v : (ny, nx) float64 arrays
        New arrays; valid vectors unchanged.
    """
    u = np.array(u, dtype=np.float64)
    v = np.array(v, dtype=np.float64)
    todo = np.asarray(invalid, dtype=bool) | ~np.isfinite(u) | ~np.isfinite(v)
    for _ in range(max_sweeps):
        if not todo.any():
            break
        mu, count = neighbour_median(u, ~todo)
        mv, _ = neighbour_median(v, ~todo)
        fill = todo & (count > 0)
        if not fill.any():
            break
        u[fill], v[fill] = mu[fill], mv[fill]
        todo &= ~fill
    if todo.any():
        good = ~todo
        u[todo] = np.median(u[good]) if good.any() else 0.0
        v[todo] = np.median(v[good]) if good.any() else 0.0
    return u, v


def laplace_neighbours(invalid):
    """Flat indices of the invalid nodes and of their four neighbours (the node itself beyond the grid).

    Parameters
    ----------
    invalid : (ny, nx) bool array

    Returns
    -------
    nodes : (n,) int array
        Flat indices of the invalid nodes, in raster order.
    neighbours : (4, n) int array
        Flat indices of the node above, below, left and right of each, clamped to the grid: beyond
        the grid's edge the edge node stands in for the missing one (a zero normal derivative there).
    """
    invalid = np.asarray(invalid, dtype=bool)
    ny, nx = invalid.shape
    r, c = np.nonzero(invalid)
    up, down = np.maximum(r - 1, 0), np.minimum(r + 1, ny - 1)
    left, right = np.maximum(c - 1, 0), np.minimum(c + 1, nx - 1)
    return r * nx + c, np.stack([up * nx + c, down * nx + c, r * nx + left, r * nx + right])


def fill_by_interpolation(u, v, invalid, *, sweeps=FILL_SWEEPS):
    """Fill invalid vectors by harmonic (Laplace) interpolation from the valid ones around them.

    Parameters
    ----------
    u, v : (ny, nx) arrays
    invalid : (ny, nx) bool array
        Vectors to fill (non-finite ones are filled too).
    sweeps : int
        Jacobi sweeps after the start.

    Returns
    -------
    u, v : (ny, nx) float64 arrays
        New arrays; valid vectors unchanged.

    Notes
    -----
    The filled nodes solve the discrete Laplace equation (each is the mean of its four neighbours)
    with the valid vectors as boundary values and a zero normal derivative at the grid's edge: a
    field that is linear across a hole inside the grid is filled exactly, and a hole's values vary
    smoothly between its rims instead of taking one neighbour's value as the median does. (At the
    grid's edge the zero normal derivative lets the interior inform the edge; the linear continuation
    of the grid, exact for linear fields, gave 5-10 % larger errors on the turbulent PIV pairs of
    ``benchmarks/bench_openpiv.py``, whose rejected vectors often lie there.) The iteration starts
    from :func:`replace_outliers` (the median of the valid neighbours, ring by ring), which is already
    close, and runs ``sweeps`` Jacobi sweeps (all nodes updated from the previous sweep's values, the
    arithmetic of the Warp kernel ``pass_kernels.laplace_sweep``).

    Examples
    --------
    >>> import numpy as np
    >>> y, x = np.mgrid[0:6, 0:7].astype(float)
    >>> hole = np.zeros((6, 7), bool); hole[1:4, 2:5] = True
    >>> fu, fv = fill_by_interpolation(np.where(hole, 9.0, x - y), y, hole, sweeps=300)
    >>> bool(np.allclose(fu, x - y, atol=1e-6))
    True
    """
    todo = np.asarray(invalid, dtype=bool) | ~np.isfinite(np.asarray(u)) | ~np.isfinite(np.asarray(v))
    u, v = replace_outliers(u, v, todo)
    if not todo.any() or todo.all():
        return u, v
    nodes, (up, down, left, right) = laplace_neighbours(todo)
    out = []
    for f in (u, v):
        flat = f.ravel()
        for _ in range(sweeps):
            flat[nodes] = 0.25 * (flat[up] + flat[down] + flat[left] + flat[right])
        out.append(flat.reshape(f.shape))
    return out[0], out[1]
