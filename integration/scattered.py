"""Scattered measurements (tracked dots) onto a regular grid, for the grid solvers.

Dots are scattered; the solvers of ``integration.solvers`` work on a grid. The interpolation is
piecewise linear on the Delaunay triangulation of the dots (exact for a field linear over each
triangle, second order otherwise); grid nodes outside the dots' convex hull, or in a triangle with a
vertex that carries no value, are left NaN and so fall outside the solvers' mask.

The triangulation is the costly part, and a campaign interpolates the same points again and again
(a pair's truth, once per item): :func:`triangulate` remembers the last few triangulations by the
points' bytes. Qhull is deterministic, so a remembered triangulation is the one it would build again.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import Delaunay, QhullError

from synthbos import SynthbosError
from synthbos.memo import RecentResults

__all__ = ["fill_missing", "grid_for_points", "scattered_to_grid", "triangulate"]

_triangulations = RecentResults(8)  # a few pairs' truths and the latest items' points


def triangulate(points):
    """The Delaunay triangulation of points, remembered for the last few point sets.

    Parameters
    ----------
    points : (N, 2) array_like
        Point coordinates, all finite.

    Returns
    -------
    scipy.spatial.Delaunay
        ``Delaunay(points)`` with scipy's default options. A call with points of the same bytes as one
        of the last few calls returns that call's object (shared: treat it as read-only).

    Raises
    ------
    scipy.spatial.QhullError
        If Qhull cannot triangulate the points (fewer than 3, all collinear).
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    return _triangulations.get([pts], lambda: Delaunay(pts))


#: Most nodes of a grid (about a 3000 x 3000 image at one node per pixel).
MAX_NODES = 1e7


def grid_for_points(x, y, *, spacing=None, extent=None, max_nodes=MAX_NODES):
    """A regular grid of nodes covering scattered points.

    Parameters
    ----------
    x, y : array_like
        Point coordinates.
    spacing : float, optional
        Node spacing; default: the mean point spacing ``sqrt(area / N)`` of the points' bounding box.
    extent : (x0, x1, y0, y1), optional
        Span of the grid; default: the points' bounding box.
    max_nodes : float, keyword-only
        A grid of more nodes is refused (``SynthbosError``): a spacing far finer than the points'.

    Returns
    -------
    gx, gy : 1-D ndarrays
        Node coordinates along x and y, centred in the extent.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3:
        raise SynthbosError(f"need at least 3 points to build a grid, got {int(ok.sum())}")
    x0, x1, y0, y1 = extent if extent is not None else (x[ok].min(), x[ok].max(), y[ok].min(), y[ok].max())
    if spacing is None:
        spacing = np.sqrt(max((x1 - x0) * (y1 - y0), 1e-300) / ok.sum())
    if not (np.isfinite(spacing) and spacing > 0):
        raise SynthbosError(f"grid spacing must be a positive number, got {spacing!r}")
    nodes = ((x1 - x0) / spacing + 1.0) * ((y1 - y0) / spacing + 1.0)
    if not nodes <= max_nodes:
        raise SynthbosError(f"a grid of spacing {spacing:.4g} over {x1 - x0:.4g} x {y1 - y0:.4g} would have "
                            f"{nodes:.3g} nodes, more than {max_nodes:.3g} (points on a line? a spacing too fine?)")
    nx = int(np.floor((x1 - x0) / spacing)) + 1
    ny = int(np.floor((y1 - y0) / spacing)) + 1
    ox = x0 + 0.5 * ((x1 - x0) - (nx - 1) * spacing)
    oy = y0 + 0.5 * ((y1 - y0) - (ny - 1) * spacing)
    return ox + spacing * np.arange(nx), oy + spacing * np.arange(ny)


def scattered_to_grid(x, y, values, grid_x, grid_y):
    """Interpolate values at scattered points linearly onto the nodes of a grid.

    Parameters
    ----------
    x, y : (N,) array_like
        Point coordinates; points with a non-finite coordinate are dropped.
    values : (N,) or (N, k) array_like
        Values at the points; NaN marks a point without a value.
    grid_x, grid_y : 1-D array_like
        Node coordinates of the grid.

    Returns
    -------
    out : (ny, nx) or (ny, nx, k) ndarray
        Piecewise-linear interpolant on the Delaunay triangulation of the points that carry every
        value; NaN outside their convex hull.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    v = np.asarray(values, dtype=np.float64)
    single = v.ndim == 1
    v = v.reshape(len(x), -1)
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(v).all(axis=1)
    if ok.sum() < 3:
        raise SynthbosError(f"need at least 3 points with a valid value to interpolate, got {int(ok.sum())}")
    interp = LinearNDInterpolator(triangulate(np.stack([x[ok], y[ok]], axis=1)), v[ok], fill_value=np.nan)
    gx, gy = np.meshgrid(np.asarray(grid_x, float), np.asarray(grid_y, float))
    out = interp(gx, gy)
    return out[..., 0] if single else out


def fill_missing(values, measured):
    """Fill the unmeasured nodes of a grid: linearly between measured nodes, then from the nearest one.

    Parameters
    ----------
    values : (ny, nx) array_like
    measured : (ny, nx) bool array
        Nodes whose value is known (at least one).

    Returns
    -------
    (ny, nx) ndarray
        ``values`` at measured nodes; inside their convex hull the linear interpolant on their Delaunay
        triangulation (node index coordinates); beyond it the value of the nearest filled node.
    """
    out = np.array(values, dtype=np.float64)
    measured = np.asarray(measured, bool) & np.isfinite(out)
    if measured.all():
        return out
    if not measured.any():
        raise SynthbosError("no measured node to fill the grid from")
    jj, ii = np.nonzero(measured)
    out = np.where(measured, out, np.nan)
    if len(ii) >= 3 and np.ptp(ii) > 0 and np.ptp(jj) > 0:
        try:
            lin = scattered_to_grid(ii.astype(float), jj.astype(float), out[measured],
                                    np.arange(out.shape[1], dtype=float), np.arange(out.shape[0], dtype=float))
            out = np.where(measured, out, lin)
        except QhullError:  # collinear nodes: nearest only
            pass
    idx = ndimage.distance_transform_edt(~np.isfinite(out), return_distances=False, return_indices=True)
    return out[tuple(idx)]
