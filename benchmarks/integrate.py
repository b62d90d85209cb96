"""``synthbos integrate``: from a result file's displacements to the depth-averaged density, and its error.

The algorithms live in ``synthbos.integration`` (pure arrays); this module reads the inputs, maps them
onto a grid at the volume's mid-plane, calls a solver, and (with the pair file) scores the density
against the renderer's two truths.

Steps
-----
1. Displacements (px) to density gradients (kg/m^4), Eq. 4 inverted with the set-up's numbers:
   ``grad rho_avg = -n0 dX pitch / (M Z_D K L)``. The set-up: the pair file's attributes with ``--pair``,
   a render configuration with ``--config``, a camera pair's ``[setup]`` with ``--setup-file``
   (:mod:`.setup_file`), else the set-up the result recorded (its ``setup`` attribute, written by
   ``process`` from its pair file or its ``--setup-file``); a result that records none is refused.
2. The grid. A correlation result keeps its own grid of window centres. Tracked dots are interpolated
   linearly on the Delaunay triangulation of the valid dots (``integration.scattered_to_grid``) onto a
   square grid whose spacing is the mean dot spacing (``--spacing`` px to change it); nodes outside the
   dots' convex hull stay unmeasured. Image pixels map to the mid-plane along the chief rays
   (``integration.pixel_to_midplane``), so ``/x_mm`` and ``/y_mm`` are in the volume's own frame.
3. The solver: ``dct`` (Neumann Poisson by DCT on the full rectangle; unmeasured nodes are filled
   first, linearly between measured nodes and by the nearest one beyond them), ``lsq`` (sparse least
   squares on the measured nodes only) or ``wlsq`` (least squares weighted by each vector's
   uncertainty, Rajendran, Zhang, Bane and Vlachos 2020; see :func:`uncertainty_px` for the proxies used).
4. The constant of integration: the mean density over a reference region equals a reference density.
   Default: the configuration's ambient density over the border of the measured domain (its outermost
   ring of nodes). ``--reference-density`` sets the value, ``--reference-region x0,x1,y0,y1`` (mm, volume
   frame) the region; with ``--dirichlet`` the ``lsq``/``wlsq`` solvers hold the region at that value.
   ``--mask-region x0,x1,y0,y1`` (mm) removes nodes (a model in the flow, a bad area) from the domain.

The floor
---------
Given a pair file alone (``synthbos integrate PAIR.h5 -o DENSITY.h5``), the pair's exact per-dot
displacements (``/dots/displacement_px`` at ``/dots/reference_px``, valid dots) take the place of a
tracked result, through the same steps and with the same scores: the density error left when the
displacements are exact, set by the dot spacing and the solver. What the input is, is told by its
content (:func:`input_kind`).

Output file (HDF5)
------------------
``/density_kg_m3`` (ny, nx), ``/x_mm`` (nx), ``/y_mm`` (ny), ``/measured`` (ny, nx) bool, ``/x_px``,
``/y_px`` (the grid in image pixels), each with ``units`` and ``description``; ``/x_mm`` and ``/y_mm`` are
HDF5 dimension scales, so xarray shows the maps with named dimensions ``(y_mm, x_mm)``; with ``--pair`` also
``/truth_cone_kg_m3`` and ``/truth_chief_kg_m3`` on the same grid (the per-dot truths of the pair file,
interpolated like the dots) and the error summary as root attributes (``cone_rms_kg_m3``,
``cone_p90_kg_m3``, ``cone_rms_rel``, ... relative to the truth's range; ``cone_offset_kg_m3`` is the
mean error over the reference region, the part due to the constant of integration). Root attributes
also: ``geometry`` (JSON of the set-up used), ``setup_source`` (where it came from), ``negative_nodes``
(nodes of negative density, which no fluid has: the command warns in one line), ``method``, ``input``.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path

import h5py
import numpy as np
from synthbos.integration import (
    SOLVERS,
    border_region,
    displacement_to_density_gradient,
    fill_missing,
    grid_for_points,
    lsq_integrate,
    midplane_scale,
    pixel_to_midplane,
    poisson_dct,
    scattered_to_grid,
    set_reference,
    weighted_lsq,
)
from synthbos.raytrace.pairfile import name_dimensions

from synthbos import SynthbosError, atomic_output
from synthbos.memo import RecentResults
from synthbos.values import numbers, optional_number

from . import scoring
from .method_api import grid_result
from .registry import DENSE, MethodResult, get_method

__all__ = [
    "DensityMap",
    "Geometry",
    "GradientGrid",
    "density_floor_errors",
    "density_from_result",
    "exact_grid",
    "floor_current",
    "floor_file",
    "geometry_from_config",
    "geometry_from_pair",
    "gradient_grid",
    "input_kind",
    "pair_floor",
    "score_density",
    "solve_density",
    "truth_on_grid",
    "uncertainty_px",
    "write_density",
]

# Uncertainty proxies of the weighted least squares (px).
SIGMA_FLOOR_PX = 0.02
PEAK_RATIO_SCALE_PX = 0.1


@dataclass(frozen=True)
class Geometry:
    """The set-up numbers the integration needs (metres, the renderer's conventions)."""

    magnification: float
    pixel_pitch_m: float
    z_d_m: float
    z_stop_m: float
    depth_m: float
    gladstone_dale_m3_per_kg: float
    n0: float
    principal_point_px: tuple
    volume_centre_m: tuple  # lateral (x, y)
    ambient_density_kg_m3: float
    image_shape: tuple  # (H, W)

    @property
    def mm_per_px(self) -> float:
        """Millimetres at the mid-plane per image pixel."""
        return 1e3 * midplane_scale(magnification=self.magnification, pixel_pitch_m=self.pixel_pitch_m,
                                    z_d_m=self.z_d_m, z_stop_m=self.z_stop_m)

    def gradient(self, u_px, v_px):
        return displacement_to_density_gradient(
            u_px, v_px, magnification=self.magnification, z_d_m=self.z_d_m, depth_m=self.depth_m,
            gladstone_dale_m3_per_kg=self.gladstone_dale_m3_per_kg, n0=self.n0, pixel_pitch_m=self.pixel_pitch_m)

    def to_mm(self, x_px, y_px):
        x, y = pixel_to_midplane(x_px, y_px, principal_point_px=self.principal_point_px,
                                 magnification=self.magnification, pixel_pitch_m=self.pixel_pitch_m,
                                 z_d_m=self.z_d_m, z_stop_m=self.z_stop_m, volume_centre_m=self.volume_centre_m)
        return x * 1e3, y * 1e3


def geometry_from_config(cfg) -> Geometry:
    """The set-up of a render configuration (dict, path, or None for the embedded default)."""
    from synthbos.raytrace import load_config
    from synthbos.raytrace.camera import camera_from_config
    from synthbos.raytrace.medium import medium_from_config

    cfg = load_config(cfg)
    cam, med = camera_from_config(cfg), medium_from_config(cfg)
    W, H = cam.pixels
    return Geometry(
        magnification=cam.magnification, pixel_pitch_m=cam.pitch, z_d_m=med.centre[2], z_stop_m=cam.z_stop,
        depth_m=med.size[2], gladstone_dale_m3_per_kg=med.gladstone_dale, n0=med.n0,
        principal_point_px=tuple(cam.principal_point), volume_centre_m=tuple(med.centre[:2]),
        ambient_density_kg_m3=float(med.density.ambient), image_shape=(H, W),
    )


def geometry_from_pair(pair) -> Geometry:
    """The set-up stored in a pair file's attributes (older files: rebuilt from its configuration)."""
    a = pair.attrs
    if "volume_depth_m" not in a:
        return geometry_from_config(tomllib.loads(a["config"]))
    return Geometry(
        magnification=float(a["magnification"]), pixel_pitch_m=float(a["pixel_pitch_m"]), z_d_m=float(a["z_d_m"]),
        z_stop_m=float(a["z_stop_m"]), depth_m=float(a["volume_depth_m"]),
        gladstone_dale_m3_per_kg=float(a["gladstone_dale_m3_per_kg"]), n0=float(a["n0"]),
        principal_point_px=(float(a["principal_point_x_px"]), float(a["principal_point_y_px"])),
        volume_centre_m=(float(a["volume_centre_x_m"]), float(a["volume_centre_y_m"])),
        ambient_density_kg_m3=float(a["ambient_density_kg_m3"]), image_shape=tuple(pair.reference.shape),
    )


def setup_attr(geometry: Geometry, source: str) -> str:
    """The result file's ``setup`` attribute: the set-up's numbers and where they came from, as JSON."""
    return json.dumps({**asdict(geometry), "source": source})


def geometry_from_attr(text, *, path="the result") -> Geometry:
    """The :class:`Geometry` a result file recorded in its ``setup`` attribute (:func:`setup_attr`)."""
    try:
        values = json.loads(text)
        values.pop("source", None)
        values["principal_point_px"] = tuple(float(v) for v in values["principal_point_px"])
        values["volume_centre_m"] = tuple(float(v) for v in values["volume_centre_m"])
        values["image_shape"] = tuple(int(v) for v in values["image_shape"])
        geometry = Geometry(**values)
    except (json.JSONDecodeError, TypeError, KeyError, ValueError, AttributeError):
        raise SynthbosError(f"{path}: its setup attribute is not the JSON of a set-up; give --pair, --setup-file "
                            "or --config") from None
    for name, value in asdict(geometry).items():
        if isinstance(value, float) and not (np.isfinite(value) and value > 0):
            raise SynthbosError(f"{path}: its recorded set-up has {name} = {value!r}; give --pair, --setup-file "
                                "or --config")
    return geometry


def uncertainty_px(result: MethodResult) -> np.ndarray:
    """A per-vector displacement uncertainty (px), the weights of ``wlsq``.

    Proxies, documented because neither method reports a calibrated uncertainty:

    * correlation: ``SIGMA_FLOOR_PX + PEAK_RATIO_SCALE_PX / (peak_ratio - 1)``; the uncertainty grows as
      the primary correlation peak stops standing out of the secondary one (the peak-ratio measure of
      Charonko and Vlachos 2013);
    * tracking: ``hypot(SIGMA_FLOOR_PX, |d_cc - d_centroid| / sqrt(2))``, the disagreement of the two
      displacement estimates the tracker makes of the same dot (centroid difference and correlation
      correction);
    * any other method: ``SIGMA_FLOOR_PX`` everywhere (``wlsq`` is then ``lsq``).
    """
    t = result.table
    if "peak_ratio" in t:
        pr = np.asarray(t["peak_ratio"], dtype=np.float64).ravel()
        return SIGMA_FLOOR_PX + PEAK_RATIO_SCALE_PX / np.maximum(pr - 1.0, 1e-3)
    if "u_cc" not in t:
        return np.full(len(result.xy), SIGMA_FLOOR_PX)
    du = np.asarray(t["u_cc"], float) - np.asarray(t["u"], float)
    dv = np.asarray(t["v_cc"], float) - np.asarray(t["v"], float)
    spread = np.hypot(du, dv) / np.sqrt(2.0)
    return np.hypot(SIGMA_FLOOR_PX, np.where(np.isfinite(spread), spread, 0.0))


#: The integration grid of a dense field (px): about the mean dot spacing of the default pattern (7.2 px),
#: the grid tracked dots are integrated on, since a dense field is scored at the dots like tracking
#: (correlation's own grid is its window spacing, 16 px by default).
DENSE_SPACING_PX = 8.0


def dense_on_grid(result: MethodResult, spacing_px: float) -> MethodResult:
    """A dense result sampled (bilinearly) on a regular grid of ``spacing_px``, centred on the image."""
    h, w = result.grid_shape
    axes = []
    for n in (w, h):
        count = int((n - 1) // spacing_px) + 1
        axes.append(((n - 1) - (count - 1) * spacing_px) / 2 + spacing_px * np.arange(count))
    gx, gy = np.meshgrid(*axes)
    field = np.where(np.asarray(result.valid, bool)[:, None], result.uv, np.nan).reshape(h, w, 2)
    uv = scoring.sample_field(field, np.stack([gx, gy], axis=-1))
    return grid_result(result.method, gx, gy, uv[..., 0], uv[..., 1], settings=result.settings)


@dataclass
class GradientGrid:
    """Density gradients on the integration grid."""

    x_px: np.ndarray  # (nx,) node columns in image pixels
    y_px: np.ndarray  # (ny,)
    gx: np.ndarray  # (ny, nx) kg/m^4, NaN where unmeasured
    gy: np.ndarray
    sigma: np.ndarray  # (ny, nx) kg/m^4, uncertainty of each component
    measured: np.ndarray  # (ny, nx) bool
    x_mm: np.ndarray
    y_mm: np.ndarray

    @property
    def spacing_m(self):
        dx = (self.x_mm[1] - self.x_mm[0]) * 1e-3 if len(self.x_mm) > 1 else 1.0
        dy = (self.y_mm[1] - self.y_mm[0]) * 1e-3 if len(self.y_mm) > 1 else 1.0
        return dx, dy


def _valid_vectors(result: MethodResult):
    uv = np.asarray(result.uv, dtype=np.float64)
    xy = np.asarray(result.xy, dtype=np.float64)
    ok = np.all(np.isfinite(uv), axis=1) & np.all(np.isfinite(xy), axis=1)
    if result.valid is not None:
        ok &= np.asarray(result.valid, bool)
    return ok


def gradient_grid(result: MethodResult, geometry: Geometry, *, spacing_px=None) -> GradientGrid:
    """Map a method's displacements to density gradients on a grid (see the module docstring, step 2)."""
    if result.xy is None or len(result.xy) == 0:
        raise SynthbosError("the result holds no vectors: nothing to integrate")
    ok = _valid_vectors(result)
    if not ok.any():
        raise SynthbosError("the result holds no valid vector: nothing to integrate")
    if get_method(result.method).kind == DENSE:
        result, spacing_px = dense_on_grid(result, spacing_px or DENSE_SPACING_PX), None
        ok = _valid_vectors(result)
    sigma_px = uncertainty_px(result)
    if result.grid_shape is not None and spacing_px is None:
        ny, nx = result.grid_shape
        x_px = result.xy[:, 0].reshape(ny, nx)[0]
        y_px = result.xy[:, 1].reshape(ny, nx)[:, 0]
        u = np.where(ok, result.uv[:, 0], np.nan).reshape(ny, nx)
        v = np.where(ok, result.uv[:, 1], np.nan).reshape(ny, nx)
        s = np.where(ok, sigma_px, np.nan).reshape(ny, nx)
        return _to_gradients(u, v, s, x_px, y_px, geometry)
    if ok.sum() < 3:
        raise SynthbosError(f"the result holds {int(ok.sum())} valid vector(s); integration needs at least 3")
    return _scattered_grid(result.xy[ok], result.uv[ok], sigma_px[ok], geometry, spacing_px=spacing_px)


def exact_grid(pair, geometry: Geometry, *, spacing_px=None) -> GradientGrid:
    """The pair's exact displacements at its valid dots on the grid a tracked result gets (the floor).

    Every dot weighs alike in ``wlsq`` (the uncertainty ``SIGMA_FLOOR_PX``).
    """
    ok = pair.valid & np.all(np.isfinite(pair.displacement_px), axis=1) & np.all(np.isfinite(pair.reference_px), 1)
    if ok.sum() < 3:
        raise SynthbosError(f"the pair file holds {int(ok.sum())} valid dot(s); integration needs at least 3")
    sigma = np.full(int(ok.sum()), SIGMA_FLOOR_PX)
    return _scattered_grid(pair.reference_px[ok], pair.displacement_px[ok], sigma, geometry, spacing_px=spacing_px)


def _scattered_grid(xy, uv, sigma_px, geometry: Geometry, *, spacing_px=None) -> GradientGrid:
    """Displacements at scattered points (all valid) interpolated onto the square grid of step 2."""
    x, y = xy[:, 0], xy[:, 1]
    x_px, y_px = grid_for_points(x, y, spacing=spacing_px)
    grid = scattered_to_grid(x, y, np.stack([uv[:, 0], uv[:, 1], sigma_px], axis=1), x_px, y_px)
    return _to_gradients(grid[..., 0], grid[..., 1], grid[..., 2], x_px, y_px, geometry)


def _to_gradients(u, v, s, x_px, y_px, geometry: Geometry) -> GradientGrid:
    """Displacements and their uncertainties (px) on a grid to density gradients (kg/m^4)."""
    measured = np.isfinite(u) & np.isfinite(v)
    if measured.sum() < 2:
        raise SynthbosError("fewer than two grid nodes carry a valid vector: nothing to integrate")
    gx, gy = geometry.gradient(u, v)
    factor = abs(float(geometry.gradient(1.0, 0.0)[0]))
    x_mm, _ = geometry.to_mm(x_px, np.zeros_like(x_px))
    _, y_mm = geometry.to_mm(np.zeros_like(y_px), y_px)
    return GradientGrid(x_px=np.asarray(x_px, float), y_px=np.asarray(y_px, float), gx=gx, gy=gy,
                        sigma=factor * s, measured=measured, x_mm=x_mm, y_mm=y_mm)


@dataclass
class DensityMap:
    """A reconstructed depth-averaged density on a grid at the volume's mid-plane."""

    density: np.ndarray  # (ny, nx) kg/m^3, NaN where not reconstructed
    grid: GradientGrid
    reference_region: np.ndarray  # (ny, nx) bool
    solver: str
    reference: str  # how the constant was fixed, in words


def solve_density(grid: GradientGrid, *, solver="lsq", reference_value=None, reference_region=None,
                  dirichlet=False, ambient=None) -> DensityMap:
    """Integrate a gradient grid with one solver and fix the constant of integration.

    Parameters
    ----------
    grid : GradientGrid
    solver : {"dct", "lsq", "wlsq"}
    reference_value : float or (ny, nx) array, optional
        The reference density (a number, or known values over the region, NaN elsewhere); default
        ``ambient``.
    reference_region : (ny, nx) bool array, optional
        Where the reference holds; default: the border of the measured domain.
    dirichlet : bool
        Hold the region at the reference (``lsq``/``wlsq`` only) instead of matching its mean.
    ambient : float
        The configuration's ambient density, the default reference.
    """
    if solver not in SOLVERS:
        raise SynthbosError(f"unknown solver {solver!r}; choose one of {', '.join(SOLVERS)}")
    region = border_region(grid.measured) if reference_region is None else np.asarray(reference_region, bool)
    if not region.any():
        raise SynthbosError("the reference region holds no node of the grid")
    if reference_value is None:
        if ambient is None:
            raise SynthbosError("no reference density given and no ambient density known")
        reference_value = float(ambient)
        words = f"ambient density {ambient:.6g} kg/m^3"
    else:
        words = ("given density" if np.ndim(reference_value) == 0 else "known densities")
    words += " over " + ("the border of the measured domain" if reference_region is None else "the given region")
    dx, dy = grid.spacing_m
    known = None
    if dirichlet:
        if solver == "dct":
            raise SynthbosError("--dirichlet needs the lsq or wlsq solver")
        known = np.where(region, np.broadcast_to(reference_value, region.shape), np.nan)
        words += " (held fixed)"
    domain = grid.measured if known is None else grid.measured | np.isfinite(known)
    if solver == "dct":
        phi = poisson_dct(fill_missing(grid.gx, grid.measured), fill_missing(grid.gy, grid.measured), dx=dx, dy=dy)
        phi = np.where(grid.measured, phi, np.nan)
    elif solver == "lsq":
        phi = lsq_integrate(grid.gx, grid.gy, dx=dx, dy=dy, mask=domain, known=known, unreferenced="nan")
    else:
        phi = weighted_lsq(grid.gx, grid.gy, grid.sigma, grid.sigma, dx=dx, dy=dy, mask=domain, known=known,
                           unreferenced="nan")
    if known is None:
        phi = set_reference(phi, value=reference_value, region=region)
    return DensityMap(density=phi, grid=grid, reference_region=region, solver=solver, reference=words)


def density_from_result(result, geometry, *, solver="lsq", spacing_px=None, **reference) -> DensityMap:
    """Result in, density map out: :func:`gradient_grid` then :func:`solve_density`."""
    grid = gradient_grid(result, geometry, spacing_px=spacing_px)
    reference.setdefault("ambient", geometry.ambient_density_kg_m3)
    return solve_density(grid, solver=solver, **reference)


def truth_on_grid(pair, grid: GradientGrid):
    """The pair's per-dot cone and chief-ray densities, interpolated like the dots onto the grid.

    Returns (cone, chief), each (ny, nx) kg/m^3, NaN outside the valid dots' convex hull.
    """
    if pair.density_cone_kg_m3 is None:
        raise SynthbosError("the pair file has no density truth (rendered before /dots/density_cone_kg_m3 existed)")
    ok = pair.valid & np.all(np.isfinite(pair.reference_px), axis=1)
    x, y = pair.reference_px[ok, 0], pair.reference_px[ok, 1]
    values = np.stack([pair.density_cone_kg_m3[ok], pair.density_chief_kg_m3[ok]], 1)
    x_px, y_px = np.asarray(grid.x_px, np.float64), np.asarray(grid.y_px, np.float64)
    # the same for every item of a pair measured on the same grid (a correlation's, or tracking and
    # tracking-cc on the same dots): remembered by the contents of the dots, the truths and the grid
    both = _truths_on_grid.get([x, y, values, x_px, y_px], lambda: scattered_to_grid(x, y, values, x_px, y_px))
    return both[..., 0].copy(), both[..., 1].copy()


_truths_on_grid = RecentResults(8)


DENSITY_SOLVER = "lsq"  # the solver campaigns score every method with


def _no_density_scores() -> dict:
    empty = {k: np.zeros(0) for k in ("density_error_cone", "density_error_chief", "density_map",
                                      "density_truth_cone", "density_truth_chief", "density_x_mm", "density_y_mm")}
    return empty | {"density_range_cone": np.float64(np.nan), "density_range_chief": np.float64(np.nan)}


def score_density(pair, result: MethodResult, *, solver=DENSITY_SOLVER) -> dict:
    """A campaign item's density scores: integrate one method's result and compare with both truths.

    The constant of integration comes from the known density over the border of the measured domain
    (the cone truth there), so the scores measure the integration of the measured gradients, not a
    guess of the ambient density. Returns arrays for the item's score file: ``density_error_cone`` and
    ``density_error_chief`` (signed errors at the scored nodes, kg/m^3), ``density_range_cone`` and
    ``density_range_chief`` (the truths' ranges) and, for the figure, the maps ``density_map``,
    ``density_truth_cone``, ``density_truth_chief`` with ``density_x_mm``, ``density_y_mm``. Empty
    arrays when the pair has no density truth or nothing could be integrated.
    """
    if pair.density_cone_kg_m3 is None:
        return _no_density_scores()
    try:
        grid = gradient_grid(result, geometry_from_pair(pair))
    except SynthbosError:
        return _no_density_scores()
    return score_density_grid(pair, grid, solver=solver)


def score_density_grid(pair, grid: GradientGrid, *, solver=DENSITY_SOLVER) -> dict:
    """:func:`score_density` of a gradient grid already made: a result's, or the pair's exact
    displacements' (:func:`exact_grid`, the floor)."""
    if pair.density_cone_kg_m3 is None:
        return _no_density_scores()
    try:
        cone, chief = truth_on_grid(pair, grid)
        region = border_region(grid.measured & np.isfinite(cone))
        dmap = solve_density(grid, solver=solver, reference_value=np.where(region, cone, np.nan),
                             reference_region=region)
    except SynthbosError:
        return _no_density_scores()
    ok = np.isfinite(dmap.density) & np.isfinite(cone) & np.isfinite(chief)
    return {
        "density_error_cone": (dmap.density - cone)[ok],
        "density_error_chief": (dmap.density - chief)[ok],
        "density_range_cone": np.float64(np.ptp(cone[ok])) if ok.any() else np.float64(np.nan),
        "density_range_chief": np.float64(np.ptp(chief[ok])) if ok.any() else np.float64(np.nan),
        "density_map": dmap.density, "density_truth_cone": cone, "density_truth_chief": chief,
        "density_x_mm": grid.x_mm, "density_y_mm": grid.y_mm,
    }


#: Smallest reach (px) of a measured point past the image's edge accepted by :func:`check_belongs`:
#: a dot is fitted from the part of its image inside the frame, so its centre may lie outside.
EDGE_REACH_PX = 2.0


def density_floor_errors(path) -> dict:
    """The density errors of a pair file's exact per-dot displacements (:func:`exact_grid`, the floor set by
    the dot spacing and the solver), pooled as a campaign pools a method's (``storage.load_scores``):
    ``density_{truth}`` (kg/m^3) and ``density_{truth}_rel`` (over the truth's range), for the cone and the
    chief-ray truths."""
    from synthbos.raytrace import read_pair

    pair = read_pair(path)
    s = score_density_grid(pair, exact_grid(pair, geometry_from_pair(pair)))
    out = {}
    for truth in ("cone", "chief"):
        e = np.abs(s[f"density_error_{truth}"])
        rng = float(s[f"density_range_{truth}"])
        out[f"density_{truth}"] = e
        out[f"density_{truth}_rel"] = e / rng if rng > 0 else np.full(len(e), np.nan)
    return out


def floor_file(path) -> Path:
    """Where a campaign keeps a pair file's :func:`density_floor_errors` (:func:`pair_floor`): in its folder
    ``floors``, beside ``pairs`` and ``scores`` (whose files stay one per score item).

    Examples
    --------
    >>> floor_file("run/pairs/s2_p00.h5").as_posix()
    'run/floors/s2_p00.npz'
    """
    path = Path(path)
    return path.parent.parent / "floors" / f"{path.stem}.npz"


def floor_current(path) -> bool:
    """Whether a pair file's :func:`floor_file` is there and not older than the pair file (False while the
    pair file is not there: a pair deleted to be rendered again)."""
    out, pair = floor_file(path), Path(path)
    return out.exists() and pair.exists() and out.stat().st_mtime >= pair.stat().st_mtime


def pair_floor(path) -> dict:
    """:func:`density_floor_errors` of a campaign's pair file, kept in its :func:`floor_file`: computed and
    written (atomically) the first time, read back after, unless the pair file is newer. A campaign's workers
    make them while the work goes on (the pipeline's jobs, a Dask worker's pipeline task), so its floor
    table only reads them, and a run again finds them there."""
    out = floor_file(path)
    if floor_current(path):
        with np.load(out) as f:
            return {k: f[k] for k in f.files}
    floor = density_floor_errors(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(out) as tmp, open(tmp, "wb") as f:
        np.savez(f, **floor)
    return floor


def edge_reach_px(result: MethodResult) -> float:
    """How far past the image's edge (px) a result's points may lie: the larger of ``EDGE_REACH_PX`` and
    the radius of the result's largest dot (its table's ``diameter``, e^-2 diameter of the fitted Gaussian)."""
    d = np.asarray(result.table.get("diameter", ()), dtype=np.float64).ravel()
    d = d[np.isfinite(d)]
    return max(EDGE_REACH_PX, 0.5 * float(d.max())) if d.size else EDGE_REACH_PX


def check_belongs(result_attrs: dict, result: MethodResult, geometry: Geometry, *, what="pair") -> None:
    """Refuse a result and a pair (or set-up) that do not belong together: image size, magnification,
    points beyond the image (by more than a dot's reach, :func:`edge_reach_px`: dots at the edge are
    fitted with their centres up to a radius outside)."""
    shape = result_attrs.get("image_shape")
    if shape is not None and tuple(int(s) for s in shape) != tuple(geometry.image_shape):
        H, W = geometry.image_shape
        raise SynthbosError(f"the result was measured on {int(shape[1])} x {int(shape[0])} px images but the "
                            f"{what}'s are {W} x {H} px: they do not belong together")
    m = result_attrs.get("magnification")
    if m is not None and abs(float(m) - geometry.magnification) > 1e-9 * geometry.magnification:
        raise SynthbosError(f"the result's magnification {float(m):.6g} differs from the {what}'s "
                            f"{geometry.magnification:.6g}: they do not belong together")
    xy = np.asarray(result.xy, float)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    H, W = geometry.image_shape
    reach = edge_reach_px(result)
    if len(xy) and (xy.min() < -0.5 - reach or xy[:, 0].max() > W - 0.5 + reach or xy[:, 1].max() > H - 0.5 + reach):
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        raise SynthbosError(f"the result's points (x {lo[0]:.5g} .. {hi[0]:.5g}, y {lo[1]:.5g} .. {hi[1]:.5g} px) "
                            f"reach more than {reach:.3g} px beyond the {what}'s {W} x {H} px image: "
                            "they do not belong together")


def write_density(path, dmap: DensityMap, *, truths=None, summary=None, attrs=None) -> Path:
    """Write the density file atomically (layout in the module docstring)."""
    path = Path(path)
    g = dmap.grid
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        def put(name, data, units, description):
            ds = f.create_dataset(name, data=data)
            ds.attrs["units"] = units
            ds.attrs["description"] = description

        put("density_kg_m3", dmap.density, "kg/m^3",
            f"depth-averaged density at the volume's mid-plane, solver {dmap.solver}; NaN where not reconstructed")
        put("x_mm", g.x_mm, "mm", "node x in the volume's frame (centred on its mid-point), at its mid-plane")
        put("y_mm", g.y_mm, "mm", "node y in the volume's frame (centred on its mid-point), at its mid-plane")
        put("x_px", g.x_px, "px", "node x in the image (column)")
        put("y_px", g.y_px, "px", "node y in the image (row)")
        put("measured", g.measured, "1", "nodes that carry a measured vector")
        put("reference_region", dmap.reference_region, "1", "nodes where the reference density fixed the constant")
        if truths is not None:
            cone, chief = truths
            put("truth_cone_kg_m3", cone, "kg/m^3",
                "true depth-averaged density averaged over each dot's cone of rays, interpolated from the dots")
            put("truth_chief_kg_m3", chief, "kg/m^3",
                "true depth-averaged density along each dot's chief ray, interpolated from the dots")
        ny, nx = dmap.density.shape
        dims = {name: ("y_mm", "x_mm") for name, ds in f.items() if ds.shape == (ny, nx)}
        name_dimensions(f, {"x_mm": (None, "mm", f["x_mm"].attrs["description"]),
                            "y_mm": (None, "mm", f["y_mm"].attrs["description"])},
                        {**dims, "x_px": ("x_mm",), "y_px": ("y_mm",)})
        f.attrs["solver"] = dmap.solver
        f.attrs["reference"] = dmap.reference
        for key, value in (summary or {}).items():
            f.attrs[key] = value
        for key, value in (attrs or {}).items():
            f.attrs[key] = value
    return path


def density_summary(dmap: DensityMap, truths) -> dict:
    """Error summary against both truths, as flat ``{truth}_{stat}`` entries (see ``scoring.density_errors``)."""
    out = {}
    for name, truth in zip(("cone", "chief"), truths, strict=True):
        stats = scoring.density_errors(dmap.density, truth, region=dmap.reference_region)
        out.update({f"{name}_{k}": v for k, v in stats.items()})
    return out


def _region_mm(grid: GradientGrid, box):
    x0, x1, y0, y1 = box
    X, Y = np.meshgrid(grid.x_mm, grid.y_mm)
    return (X >= min(x0, x1)) & (X <= max(x0, x1)) & (Y >= min(y0, y1)) & (Y <= max(y0, y1))


def mask_grid(grid: GradientGrid, masked) -> GradientGrid:
    """Remove the nodes ``masked`` (an object, a region known to be bad) from the measured domain."""
    keep = grid.measured & ~np.asarray(masked, bool)
    if keep.sum() < 2:
        raise SynthbosError("the mask covers every measured node: nothing to integrate")
    grid.measured = keep
    grid.gx = np.where(keep, grid.gx, np.nan)
    grid.gy = np.where(keep, grid.gy, np.nan)
    return grid


def input_kind(path) -> str:
    """What ``synthbos integrate`` was given, by the file's content: ``"pair"`` (a pair file of ``synthbos
    render``: ``/images/reference`` and ``/dots/displacement_px``) or ``"result"`` (a result file of
    ``synthbos process``: a ``method`` attribute); anything else raises SynthbosError."""
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"input file {path} does not exist")
    if not h5py.is_hdf5(path):
        raise SynthbosError(f"{path} is not an HDF5 file: give a result file of 'synthbos process' or a pair "
                            "file of 'synthbos render'")
    try:
        with h5py.File(path, "r") as f:
            if "density_kg_m3" in f:
                raise SynthbosError(f"{path} is a density file of 'synthbos integrate': give the result file or "
                                    "the pair file it came from")
            if "images/reference" in f and "dots/displacement_px" in f:
                return "pair"
            if "method" in f.attrs:
                return "result"
    except OSError as err:
        raise SynthbosError(f"cannot read {path}: {err}") from None
    raise SynthbosError(f"{path} is neither a result file of 'synthbos process' (no 'method' attribute) nor a pair "
                        "file of 'synthbos render' (no /images/reference and /dots/displacement_px)")


def _input_grid(input_path, *, pair_path, config, spacing_px, setup_file=None):
    """The gradient grid, the pair (or None) and the file attributes of ``synthbos integrate``'s input: a
    result (with its pair file, a set-up, or the set-up it recorded) or a pair file alone (its exact
    displacements)."""
    from synthbos.raytrace import read_pair

    from .process import read_result

    given = [name for name, v in (("--pair", pair_path), ("--config", config), ("--setup-file", setup_file)) if v]
    if len(given) > 1:
        raise SynthbosError(f"give one of --pair, --config and --setup-file (each gives the set-up), not "
                            f"{' and '.join(given)}")
    if input_kind(input_path) == "pair":
        if given:
            raise SynthbosError(f"{input_path} is a pair file: it integrates alone (its exact displacements and "
                                f"its own set-up); leave out --pair and --config (and --setup-file)")
        pair = read_pair(input_path)
        geometry = geometry_from_pair(pair)
        attrs = {"method": "exact", "input": str(input_path), "pair": str(input_path),
                 "setup_source": f"pair file {input_path}",
                 "note": "the pair's exact per-dot displacements: the floor set by the dot spacing and the solver"}
        return exact_grid(pair, geometry, spacing_px=spacing_px), geometry, pair, attrs
    result, rattrs = read_result(input_path)
    pair = None
    if pair_path is not None:
        pair = read_pair(pair_path)
        geometry, source = geometry_from_pair(pair), f"pair file {pair_path}"
        check_belongs(rattrs, result, geometry)
    else:
        geometry, source = _result_geometry(input_path, rattrs, config=config, setup_file=setup_file)
        check_belongs({k: v for k, v in rattrs.items() if k == "image_shape"}, result, geometry, what="set-up")
    check_displacements(result, geometry)
    attrs = {"method": result.method, "input": str(input_path), "setup_source": source}
    if pair_path is not None:
        attrs["pair"] = str(pair_path)
    return gradient_grid(result, geometry, spacing_px=spacing_px), geometry, pair, attrs


def _result_geometry(path, rattrs, *, config=None, setup_file=None) -> tuple[Geometry, str]:
    """The set-up of a result integrated without its pair file, and where it came from: a render
    configuration (``--config``), a set-up file (``--setup-file``), else the set-up the result recorded;
    refused when none is known."""
    from .setup_file import geometry_from_setup, read_setup_file

    if config is not None:
        return geometry_from_config(config), f"render configuration {config}"
    if setup_file is not None:
        table = read_setup_file(setup_file)
        if rattrs.get("image_shape") is None:
            raise SynthbosError(f"{path} does not record its images' size; integrate it with --pair or --config")
        where = f"set-up file {setup_file}"
        return geometry_from_setup(table, rattrs["image_shape"], where=where), where
    if "setup" in rattrs:
        try:
            source = json.loads(rattrs["setup"]).get("source", "unknown")
        except (json.JSONDecodeError, AttributeError, TypeError):
            source = "unknown"
        return geometry_from_attr(rattrs["setup"], path=path), f"the set-up {path} recorded ({source})"
    raise SynthbosError(f"{path} records no set-up (processed from camera images without --setup-file): give "
                        "--setup-file CAMERA.toml, --pair PAIR.h5 or --config RENDER.toml")


def integrate_file(result_path, out, *, pair_path=None, config=None, setup_file=None, solver="lsq",
                   spacing_px=None, reference_density=None, reference_region_mm=None, dirichlet=False,
                   mask_region_mm=None) -> dict:
    """The work of ``synthbos integrate``: read, integrate, (score,) write; return the summary.

    ``result_path``: a result file (scored when ``pair_path`` is given), or a pair file alone, whose exact
    displacements are integrated and scored against its own truths (the floor). The set-up: the pair
    file's, a render configuration (``config``), a set-up file (``setup_file``, :mod:`.setup_file`), or
    the one the result recorded. The summary's ``negative`` counts the nodes of negative density.
    """
    check_integrate_options(spacing_px=spacing_px, reference_density=reference_density,
                            regions={"--reference-region": reference_region_mm, "--mask-region": mask_region_mm})
    grid, geometry, pair, attrs = _input_grid(result_path, pair_path=pair_path, config=config,
                                              setup_file=setup_file, spacing_px=spacing_px)
    if mask_region_mm is not None:
        grid = mask_grid(grid, _region_mm(grid, mask_region_mm))
    region = None
    if reference_region_mm is not None:
        x0, x1, y0, y1 = reference_region_mm
        region = _region_mm(grid, reference_region_mm)
        if not (region & grid.measured).any():
            raise SynthbosError(f"the reference region x {x0:g}..{x1:g} mm, y {y0:g}..{y1:g} mm holds no measured node")
    dmap = solve_density(grid, solver=solver, reference_value=reference_density, reference_region=region,
                         dirichlet=dirichlet, ambient=geometry.ambient_density_kg_m3)
    negative = check_density_range(dmap)
    truths = truth_on_grid(pair, grid) if pair is not None else None
    summary = density_summary(dmap, truths) if truths is not None else {}
    attrs["geometry"] = json.dumps(asdict(geometry))
    attrs["negative_nodes"] = negative
    write_density(out, dmap, truths=truths, summary=summary, attrs=attrs)
    return {"density": dmap, "summary": summary, "negative": negative, "setup_source": attrs["setup_source"]}


# Bounds of the integrate options (px, kg/m^3): a grid finer than a pixel only interpolates.
SPACING_PX = (1.0, 1e4)


def check_integrate_options(*, spacing_px=None, reference_density=None, regions=None) -> None:
    """Refuse integrate options out of range, before any file is read: ``--spacing`` (``SPACING_PX``),
    ``--reference-density`` (> 0 and at most ``MAX_DENSITY_KG_M3``) and the regions (finite mm)."""
    from synthbos.raytrace.checks import MAX_DENSITY_KG_M3

    optional_number("--spacing (px)", spacing_px, minimum=SPACING_PX[0], maximum=SPACING_PX[1])
    optional_number("--reference-density (kg/m^3)", reference_density, above=0.0, maximum=MAX_DENSITY_KG_M3)
    for name, box in (regions or {}).items():
        if box is not None:
            numbers(f"{name} (mm)", box, sizes=(4,), minimum=-1e6, maximum=1e6)


def check_displacements(result: MethodResult, geometry: Geometry) -> None:
    """Refuse displacements no BOS image can show: a valid vector longer than the image's diagonal."""
    ok = _valid_vectors(result)
    if not ok.any():
        return
    largest = float(np.max(np.hypot(result.uv[ok, 0], result.uv[ok, 1])))
    H, W = geometry.image_shape
    if largest > np.hypot(H, W):
        raise SynthbosError(f"the result holds a displacement of {largest:.4g} px, longer than the {W} x {H} px "
                            "image's diagonal: it is no measurement to integrate")


def check_density_range(dmap: DensityMap) -> int:
    """Refuse a reconstructed density that is no fluid's: above ``MAX_DENSITY_KG_M3``, or negative
    everywhere (the set-up, the reference density or the displacements are in the wrong units). Return
    the number of nodes where it is negative (unphysical: the caller warns)."""
    from synthbos.raytrace.checks import MAX_DENSITY_KG_M3

    rho = dmap.density[np.isfinite(dmap.density)]
    if rho.size and (rho.max() < 0 or rho.max() > MAX_DENSITY_KG_M3):
        raise SynthbosError(f"the integrated density spans {rho.min():.4g} .. {rho.max():.4g} kg/m^3, which no "
                            f"fluid has (0 .. {MAX_DENSITY_KG_M3:g}): check the reference density, the set-up "
                            "(--pair, --setup-file or --config) and the result's units")
    return int(np.count_nonzero(rho < 0))
