"""Displacements in, density out: Poisson and least-squares integration of BOS displacement fields.

- ``physics``: Eq. 4 inverted (displacement in px -> depth-averaged density gradient) and the map
  from image pixels to the volume's mid-plane.
- ``solvers``: :func:`poisson_dct` (full rectangle, Neumann, DCT), :func:`lsq_integrate` (sparse least
  squares with masks and known values), :func:`weighted_lsq` (uncertainty weights, Rajendran, Bane and
  Vlachos 2020), :func:`set_reference` (the constant of integration).
- ``scattered``: tracked dots onto a grid (linear on the Delaunay triangulation, :func:`triangulate`
  remembering the last few), filling a grid's gaps.

Pure arrays: no file I/O and no knowledge of the renderer.
"""

from .physics import displacement_to_density_gradient, midplane_scale, pixel_to_midplane
from .scattered import fill_missing, grid_for_points, scattered_to_grid, triangulate
from .solvers import border_region, edge_increments, lsq_integrate, poisson_dct, set_reference, weighted_lsq

SOLVERS = ("dct", "lsq", "wlsq")

__all__ = [
    "SOLVERS",
    "border_region",
    "displacement_to_density_gradient",
    "edge_increments",
    "fill_missing",
    "grid_for_points",
    "lsq_integrate",
    "midplane_scale",
    "pixel_to_midplane",
    "poisson_dct",
    "scattered_to_grid",
    "set_reference",
    "triangulate",
    "weighted_lsq",
]
