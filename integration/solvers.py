"""Integrate a gradient field on a regular grid: DCT Poisson, sparse and weighted least squares.

All three solvers minimise the same quantity, the misfit between the differences of the unknown
field across the grid's edges and the *increments* the measured gradient implies over those edges::

    sum over edges e = (a, b) of  w_e (phi_b - phi_a - d_e)^2,

where ``d_e`` is the integral of the gradient along the edge, estimated to fourth order from the
gradient at four nodes in a row, ``h (-g[i-1] + 13 g[i] + 13 g[i+1] - g[i+2]) / 24``, and by the
trapezoid rule ``h (g[i] + g[i+1]) / 2`` where the row ends or a neighbour is missing. A field whose
gradient is sampled exactly is recovered to O(h^4) in the interior.

- :func:`poisson_dct`: all weights 1 on a full rectangle: the normal equations are the five-point
  Poisson equation with Neumann boundaries, solved exactly by a type-II discrete cosine transform.
- :func:`lsq_integrate`: the same least squares as a sparse system, with a mask (irregular domains),
  nodes of known value (Dirichlet) and, optionally, weights.
- :func:`weighted_lsq`: the weighted least squares of Rajendran, Zhang, Bane and Vlachos (2020), each
  increment weighted by the inverse of its variance propagated from the gradient's uncertainty.

The constant of integration is free in the first two unless nodes are known; :func:`set_reference`
fixes it from a reference value over a region.

The sparse system depends only on the domain (and the weights): a campaign integrates many results on
the same domain, so the last few systems (the matrix, the domain's connected parts) and their LU factors
are remembered (``synthbos.memo``) and a repeated domain costs only the right-hand side and the
triangular solves. The factors are SuperLU's with ``spsolve``'s
options, so the solution is bit for bit ``scipy.sparse.linalg.spsolve``'s.
"""

from __future__ import annotations

import functools
import threading

import numpy as np
from scipy import fft, ndimage, sparse
from scipy.sparse import csgraph
from scipy.sparse import linalg as splinalg

from synthbos import SynthbosError
from synthbos.memo import RecentResults

__all__ = ["border_region", "edge_increments", "lsq_integrate", "poisson_dct", "set_reference", "weighted_lsq"]

_W4 = np.array([-1.0, 13.0, 13.0, -1.0]) / 24.0
# LU factors of the last few least-squares matrices, per thread: a SuperLU object is used only by the
# thread that made it (no concurrent solves on one factorisation, no factor outliving its thread)
_factors = threading.local()


def edge_increments(g, h, *, valid=None, sigma=None):
    """Integral of ``g`` along each edge between neighbours of the last axis.

    Parameters
    ----------
    g : (ny, nx) array_like
        The derivative along the last axis at the nodes.
    h : float
        Node spacing along the last axis.
    valid : (ny, nx) bool array, optional
        Nodes where ``g`` is known; default: where it is finite.
    sigma : (ny, nx) array_like, optional
        Standard uncertainty of ``g`` at each node (same units as ``g``).

    Returns
    -------
    d : (ny, nx - 1) ndarray
        Increment across each edge (NaN where an end node is invalid).
    ok : (ny, nx - 1) bool ndarray
        Edges with both end nodes valid.
    var : (ny, nx - 1) ndarray or None
        Variance of each increment from ``sigma`` (independent errors), if ``sigma`` is given.

    Notes
    -----
    Fourth order: the integral over [x_i, x_i+1] of the cubic through nodes i-1..i+2 has weights
    (-1, 13, 13, -1) / 24; where a neighbour is missing, the trapezoid rule (1/2, 1/2).
    """
    g = np.asarray(g, dtype=np.float64)
    if valid is None:
        valid = np.isfinite(g)
    valid = valid & np.isfinite(g)
    gz = np.where(valid, g, 0.0)
    nx = g.shape[1]
    ok = valid[:, :-1] & valid[:, 1:]
    d = 0.5 * h * (gz[:, :-1] + gz[:, 1:])
    four = np.zeros_like(ok)
    if nx >= 4:
        four[:, 1:-1] = ok[:, 1:-1] & valid[:, :-3] & valid[:, 3:]
        d4 = h * (_W4[0] * gz[:, :-3] + _W4[1] * gz[:, 1:-2] + _W4[2] * gz[:, 2:-1] + _W4[3] * gz[:, 3:])
        d[:, 1:-1] = np.where(four[:, 1:-1], d4, d[:, 1:-1])
    d = np.where(ok, d, np.nan)
    var = None
    if sigma is not None:
        s2 = np.where(valid, np.asarray(sigma, dtype=np.float64) ** 2, 0.0)
        var = (0.5 * h) ** 2 * (s2[:, :-1] + s2[:, 1:])
        if nx >= 4:
            v4 = h**2 * (_W4[0] ** 2 * s2[:, :-3] + _W4[1] ** 2 * s2[:, 1:-2] + _W4[2] ** 2 * s2[:, 2:-1]
                         + _W4[3] ** 2 * s2[:, 3:])
            var[:, 1:-1] = np.where(four[:, 1:-1], v4, var[:, 1:-1])
    return d, ok, var


def _check_pair(gx, gy):
    gx = np.asarray(gx, dtype=np.float64)
    gy = np.asarray(gy, dtype=np.float64)
    if gx.ndim != 2 or gx.shape != gy.shape:
        raise SynthbosError(f"gradient components must be 2-D arrays of one shape, got {gx.shape} and {gy.shape}")
    if min(gx.shape) < 2:
        raise SynthbosError(f"the gradient grid needs at least 2 x 2 nodes, got {gx.shape}")
    return gx, gy


def poisson_dct(gx, gy, *, dx, dy):
    """Integrate a gradient field on a full rectangle: Neumann Poisson equation solved by DCT.

    Parameters
    ----------
    gx, gy : (ny, nx) array_like
        d phi / dx (along columns) and d phi / dy (along rows) at the nodes; all finite.
    dx, dy : float
        Node spacings along x and y.

    Returns
    -------
    phi : (ny, nx) ndarray
        The field whose edge differences best match the gradient's increments (least squares), with
        zero mean; add the constant with :func:`set_reference`.

    Notes
    -----
    The normal equations of the unweighted least squares (module docstring) are ``-L phi = A^T d``
    with ``L`` the five-point Laplacian with Neumann boundaries, which the orthonormal DCT-II
    diagonalises: eigenvalues ``(2 - 2 cos(pi k / nx)) + (2 - 2 cos(pi l / ny))``.
    """
    gx, gy = _check_pair(gx, gy)
    if not (np.isfinite(gx).all() and np.isfinite(gy).all()):
        raise SynthbosError("poisson_dct needs a gradient on the full rectangle; use lsq_integrate with a mask")
    ny, nx = gx.shape
    ddx, _, _ = edge_increments(gx, dx)
    ddy_t, _, _ = edge_increments(gy.T, dy)
    rhs = np.zeros((ny, nx))
    rhs[:, :-1] -= ddx
    rhs[:, 1:] += ddx
    rhs[:-1, :] -= ddy_t.T
    rhs[1:, :] += ddy_t.T
    # A^T A phi = A^T d, with (A^T d)[node] = increments arriving minus increments leaving: rhs above.
    lam = (2.0 - 2.0 * np.cos(np.pi * np.arange(ny) / ny))[:, None] + (2.0 - 2.0 * np.cos(np.pi * np.arange(nx) / nx))
    r = fft.dctn(rhs, type=2, norm="ortho")
    lam[0, 0] = 1.0
    p = r / lam
    p[0, 0] = 0.0
    return fft.idctn(p, type=2, norm="ortho")


def lsq_integrate(gx, gy, *, dx, dy, mask=None, known=None, sigma_x=None, sigma_y=None, unreferenced="mean"):
    """Integrate a gradient field by sparse least squares on a masked grid, with known values.

    Parameters
    ----------
    gx, gy : (ny, nx) array_like
        d phi / dx and d phi / dy at the nodes; NaN where not measured.
    dx, dy : float
        Node spacings along x and y.
    mask : (ny, nx) bool array, optional
        Nodes to solve for (default: every node where both components are finite, plus known nodes).
    known : (ny, nx) array_like, optional
        Known values of phi (Dirichlet), NaN elsewhere; they are held fixed.
    sigma_x, sigma_y : (ny, nx) array_like, optional
        Standard uncertainties of ``gx`` and ``gy``; each increment is then weighted by the inverse of
        its propagated variance (see :func:`weighted_lsq`). Default: all increments weigh 1.
    unreferenced : {"mean", "nan"}
        What a connected part of the domain without a known node gets: zero mean, or NaN (its level
        cannot be known).

    Returns
    -------
    phi : (ny, nx) ndarray
        NaN outside the mask. A connected part of the domain with known nodes takes its level from
        them; one without has zero mean (fix it with :func:`set_reference`).

    Raises
    ------
    SynthbosError
        If no edge of the grid has a measured increment (nothing to integrate).
    """
    gx, gy = _check_pair(gx, gy)
    ny, nx = gx.shape
    known = np.full((ny, nx), np.nan) if known is None else np.asarray(known, dtype=np.float64)
    is_known = np.isfinite(known)
    if not ((np.isfinite(gx) & np.isfinite(gy)).any() or is_known.any()):
        raise SynthbosError("no valid gradient vector: nothing to integrate")
    if mask is None:
        mask = (np.isfinite(gx) & np.isfinite(gy)) | is_known
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        raise SynthbosError("the mask leaves no node to integrate")
    vx, vy = mask & np.isfinite(gx), mask & np.isfinite(gy)
    ddx, okx, varx = edge_increments(gx, dx, valid=vx, sigma=sigma_x)
    ddy, oky, vary = edge_increments(gy.T, dy, valid=vy.T, sigma=None if sigma_y is None else np.asarray(sigma_y).T)
    ddy, oky = ddy.T, oky.T
    vary = None if vary is None else vary.T
    # Edges need both end nodes inside the mask (a known node outside the measured area still joins).
    okx &= mask[:, :-1] & mask[:, 1:]
    oky &= mask[:-1, :] & mask[1:, :]
    idx = np.arange(ny * nx).reshape(ny, nx)
    a = np.concatenate([idx[:, :-1][okx], idx[:-1, :][oky]])
    b = np.concatenate([idx[:, 1:][okx], idx[1:, :][oky]])
    d = np.concatenate([ddx[okx], ddy[oky]])
    if len(d) == 0:
        raise SynthbosError("no two neighbouring nodes carry a measured gradient: nothing to integrate")
    if varx is not None or vary is not None:
        vx_e = varx[okx] if varx is not None else np.full(okx.sum(), np.nan)
        vy_e = vary[oky] if vary is not None else np.full(oky.sum(), np.nan)
        var = np.concatenate([vx_e, vy_e])
        floor = np.nanmin(var[var > 0]) * 1e-6 if np.any(var > 0) else 1.0
        w = 1.0 / np.maximum(np.where(np.isfinite(var), var, np.nanmedian(var)), floor)
        w = w / np.median(w)
    else:
        w = np.ones(len(d))
    n = ny * nx
    # right-hand side A^T W d of the normal equations, A: +1 at b, -1 at a per edge
    rhs = np.bincount(b, w * d, minlength=n) - np.bincount(a, w * d, minlength=n)
    fixed = is_known.ravel() & mask.ravel()
    domain = mask.ravel()
    labels, inside, free_parts, hold, solve, sub, coupling = _systems.get(
        [a, b, w, domain, fixed], lambda: _system(a, b, w, n, domain, fixed), extra=n)
    values = np.where(fixed, known.ravel(), 0.0)
    phi = np.full(n, np.nan)
    phi[hold] = values[hold]
    if solve.any():
        r = rhs[solve] - coupling @ values[hold]
        phi[solve] = _spsolve(sub, r)
    for part in free_parts:
        sel = labels == part
        sel &= inside
        phi[sel] = np.nan if unreferenced == "nan" and fixed.any() else phi[sel] - phi[sel].mean()
    return phi.reshape(ny, nx)


#: The normal equations' matrix and the domain's parts for the last few edge sets, weights and masks
#: (a campaign's items integrate on the same few domains).
_systems = RecentResults(4)


def _system(a, b, w, n, mask, fixed):
    """What :func:`lsq_integrate` solves on the edges ``a -> b`` (weights ``w``) of a grid of ``n`` nodes,
    whatever the increments: each node's connected part, the nodes inside the domain, the parts without a
    known node (each gets one node pinned, then mean zero), the held and the solved nodes, the weighted
    graph Laplacian (A^T W A) on the solved nodes (CSC, canonical) and its columns of the held nodes."""
    lap = sparse.coo_matrix(
        (np.concatenate([w, w, -w, -w]), (np.concatenate([a, b, a, b]), np.concatenate([a, b, b, a]))),
        shape=(n, n),
    ).tocsr()
    adj = sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    _, labels = csgraph.connected_components(adj, directed=False)
    degree = np.bincount(a, minlength=n) + np.bincount(b, minlength=n)
    inside = mask & ((degree > 0) | fixed)  # a node joined to nothing stays unknown
    free_parts = np.setdiff1d(np.unique(labels[inside]), np.unique(labels[fixed]))
    order = np.flatnonzero(inside)
    parts, first = np.unique(labels[order], return_index=True)
    pinned = np.zeros(n, dtype=bool)
    pinned[order[first[np.isin(parts, free_parts)]]] = True
    hold = fixed | pinned
    solve = inside & ~hold
    rows = lap[solve]
    sub = rows[:, solve].tocsc()
    sub.sum_duplicates()  # canonical once, before it is shared (``_spsolve`` would do it on each call)
    coupling = rows[:, hold]
    for v in (labels, inside, free_parts, hold, solve):
        v.flags.writeable = False
    return labels, inside, free_parts, hold, solve, sub, coupling


def _spsolve(a, r):
    """``scipy.sparse.linalg.spsolve(a, r)`` for a CSC matrix, remembering the LU factors of ``a``."""
    if not _spsolve_uses_superlu():
        return splinalg.spsolve(a, r)
    a.sum_duplicates()  # canonical form (spsolve does the same): one matrix, one key
    try:
        if not hasattr(_factors, "recent"):
            _factors.recent = RecentResults(4)
        lu = _factors.recent.get([a.indptr, a.indices, a.data], lambda: splinalg.splu(a), extra=a.shape)
    except RuntimeError:  # exactly singular: spsolve's own warning and NaN
        return splinalg.spsolve(a, r)
    return lu.solve(r)


@functools.cache
def _spsolve_uses_superlu() -> bool:
    """Whether ``spsolve`` factorises with SuperLU here (it takes UMFPACK where scikit-umfpack is installed)."""
    try:
        import scikits.umfpack  # noqa: F401
    except ImportError:
        return True
    return False


def weighted_lsq(gx, gy, sigma_x, sigma_y, *, dx, dy, mask=None, known=None, unreferenced="mean"):
    """Uncertainty-weighted least-squares integration (Rajendran, Zhang, Bane and Vlachos 2020).

    Parameters
    ----------
    gx, gy : (ny, nx) array_like
        d phi / dx and d phi / dy at the nodes; NaN where not measured.
    sigma_x, sigma_y : (ny, nx) array_like
        Standard uncertainty of each gradient component, in its units (a displacement uncertainty in
        px times the factor of ``integration.displacement_to_density_gradient``).
    dx, dy, mask, known, unreferenced
        As in :func:`lsq_integrate`.

    Returns
    -------
    phi : (ny, nx) ndarray

    Notes
    -----
    Each edge increment ``d_e = sum_k c_k h g_k`` (the quadrature of :func:`edge_increments`) is
    weighted by ``1 / var(d_e)`` with ``var(d_e) = sum_k (c_k h sigma_k)^2``, so that vectors with large
    uncertainty pull the solution less, as in Rajendran, Zhang, Bane and Vlachos (2020), Exp. Fluids
    61, 239 (weighted least squares with the measurement uncertainty as weights).
    """
    if sigma_x is None or sigma_y is None:
        raise SynthbosError("weighted_lsq needs the uncertainties of both gradient components")
    return lsq_integrate(gx, gy, dx=dx, dy=dy, mask=mask, known=known, sigma_x=sigma_x, sigma_y=sigma_y,
                         unreferenced=unreferenced)


def border_region(domain):
    """The outermost ring of nodes of a domain: nodes of ``domain`` next to a node outside it or on the
    grid's edge (4-connectivity)."""
    domain = np.asarray(domain, bool)
    return domain & ~ndimage.binary_erosion(domain, border_value=0)


def set_reference(phi, *, value, region=None):
    """Add the constant that gives ``phi`` the mean ``value`` over ``region``.

    Parameters
    ----------
    phi : (ny, nx) array_like
        An integrated field known up to a constant (NaN where unknown).
    value : float or (ny, nx) array_like
        The reference density: one number, or the known values over ``region`` (their mean is used).
    region : (ny, nx) bool array, optional
        Where the reference holds; default: the border of the domain where ``phi`` is finite
        (:func:`border_region`), the image border for a full rectangle.

    Returns
    -------
    phi : ndarray
        ``phi + c`` with ``mean(phi + c) = mean(value)`` over the finite nodes of ``region``.
    """
    phi = np.asarray(phi, dtype=np.float64)
    if region is None:
        region = border_region(np.isfinite(phi))
    region = np.asarray(region, dtype=bool)
    ref = np.broadcast_to(np.asarray(value, dtype=np.float64), phi.shape)
    use = region & np.isfinite(phi) & np.isfinite(ref)
    if not use.any():
        raise SynthbosError("the reference region holds no integrated node: cannot fix the constant of integration")
    return phi + (ref[use].mean() - phi[use].mean())
