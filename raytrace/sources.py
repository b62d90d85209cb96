"""Density sources: the function that turns the ``[volume]`` table of a configuration into a
density field on a regular grid.

Contract (relied on by ``raytrace.config`` and ``raytrace.medium``):

``density_from_config(volume) -> DensityField`` takes the validated ``[volume]`` table, whose common
keys (``COMMON_KEYS``) already carry defaults, and reads the source's own keys from the same table
(``SOURCE_KEYS``: defaults, None = required); an unknown or bad source key raises ``SynthbosError``
naming ``volume.<key>``. The field never holds NaN/inf or a density <= 0.

Coordinates: the volume's own frame, centred on its mid-point, x and y transverse (y up in the images),
z along the optical axis; node ``(k, j, i)`` sits at ``x = -Lx/2 + i Lx/(nx-1)`` (likewise y, z).

Sources
-------
Analytic sources (physical units, never rescaled by ``density_scale_kg_m3``; sampled on ``grid``
= [nx, ny, nz] nodes, default [64, 64, 16]; ``ambient`` = ``density_kg_m3``):

``uniform``     rho = rho0.
``linear``      rho = rho0 + g . x, ``gradient_kg_m4 = [gx, gy]`` (or [gx, gy, gz]); rho0 at the centre.
``gaussian``    rho = rho0 + a exp(-|x - c|^2 / (2 s^2)), ``amplitude_kg_m3`` a, ``sigma_mm`` s,
                ``centre_mm`` c.
``step``        a smoothed step (an interface or weak shock): rho = rho0 + (J/2) (1 + tanh(2 s / delta)),
                s = (x - p) . n / |n|, ``jump_kg_m3`` J, ``position_mm`` p (a point of the interface),
                ``normal`` n (2 or 3 components, pointing to the side of density rho0 + J) and
                ``thickness_mm`` delta, the maximum-slope thickness J / max|d rho/ds|.
``sinusoidal``  rho = rho0 + a sin(2 pi s / lambda + phi), s = x . d / |d|, ``amplitude_kg_m3`` a,
                ``wavelength_mm`` lambda, ``direction`` d (2 or 3 components), ``phase_deg`` phi.

Data sources (the grid comes from the data; ``grid`` must be left unset):

``slice``       snapshot ``snapshot`` (0..4) of the embedded buoyancy-driven mixing file
                (``data/buoyancy_snapshots.h5``, or ``path``), a normalised (mean 1) 2-D field
                multiplied by ``density_scale_kg_m3``, spanning ``size_mm[0]`` x ``size_mm[1]`` and
                extruded along z on nz = 2 nodes (so d rho/dz = 0 exactly); ambient = scale x mean.
``file``        density read by :func:`raytrace.loaders.load_density` from ``path`` (``format`` "auto"
                = from the extension, or jhtdb | nrrd | npy | npz | hdf5; ``dataset``; ``slice_index``
                along ``axis``; ``index_range`` = [[x0, x1], [y0, y1], [z0, z1]]). A 2-D result (a 2-D
                array or a picked slice) is extruded along z like ``slice``; a 3-D result is used as the
                volume. ``normalised``: "auto" (true for jhtdb, false otherwise), true (the data are
                multiplied by ``density_scale_kg_m3``) or false (the data are kg/m^3). Ambient = mean of
                the resulting field. ``axis_order``: the physical axis of each stored array axis,
                "auto" = "zyx" (3-D) / "yx" (2-D); "xyz" / "xy" for arrays stored as (nx, ny, nz) /
                (nx, ny) (see :func:`raytrace.loaders.load_density`).

Physical size of data sources: with ``spacing_mm = "auto"`` (default) the data are mapped onto
``size_mm`` (first and last nodes on the faces); for the ``file`` source this stretch is announced
(a :class:`DensityNotice` warning naming the node spacing in mm that results, and the change of aspect
ratio where the file carries its own spacing) and kept in ``DensityField.notes``. A file's own
coordinates (JHTDB, NRRD) are not used for the size: they are in the file's units (database units for
JHTDB: a 2 pi box), and are only reported as ``LoadedDensity.spacing`` for the user to turn into
``spacing_mm``. With ``spacing_mm``
given (one number, or [dx, dy, dz] along the file's x, y, z axes before any slice is taken; [dx, dy]
for a 2-D file) the extent along each data axis is spacing x (n - 1) and ``size_mm`` is ignored along
those axes; an extruded slice keeps ``size_mm[2]`` as its depth (e.g. a y-slice of a volume spans
dx (nx - 1) by dz (nz - 1)). ``DensityField.size_m`` always holds the extent actually used; for a
3-D file with ``spacing_mm`` the depth is dz (nz - 1), not ``size_mm[2]``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from synthbos import SynthbosError

from . import checks
from .defaults import DEFAULT_CONFIG
from .loaders import FORMATS, infer_format, load_density, read_snapshots

__all__ = [
    "ANALYTIC",
    "COMMON_KEYS",
    "DEFAULT_GRID",
    "SOURCE_KEYS",
    "DensityField",
    "DensityNotice",
    "density_from_config",
    "extruded",
    "node_coordinates",
]


class DensityNotice(UserWarning):
    """What a data source did to the data that the configuration did not spell out (shown once)."""

# Keys every source shares, with defaults. ``grid`` is [nx, ny, nz] nodes; None lets the source choose.
# The physical defaults come from default.toml (the paper's set-up); a bare volume table is a Gaussian.
COMMON_KEYS = {
    "source": "gaussian",
    **{k: DEFAULT_CONFIG["volume"][k] for k in
       ("distance_from_target_mm", "size_mm", "gladstone_dale_m3_per_kg", "density_scale_kg_m3")},
    "grid": None,
}

# Each source's own keys with defaults (None means required). Optional settings that are "off" by
# default use TOML-representable markers ("auto", "none", "all", "") since TOML has no null.
SOURCE_KEYS: dict[str, dict[str, object]] = {
    "uniform": {"density_kg_m3": 1.225},
    "linear": {"density_kg_m3": 1.225, "gradient_kg_m4": [0.0, 0.0]},
    "gaussian": {
        "density_kg_m3": 1.225,
        "amplitude_kg_m3": 0.05,
        "sigma_mm": 4.0,
        "centre_mm": [0.0, 0.0, 0.0],
    },
    "step": {
        "density_kg_m3": 1.225,
        "jump_kg_m3": 0.05,
        "position_mm": [0.0, 0.0, 0.0],
        "normal": [1.0, 0.0],
        "thickness_mm": 1.0,
    },
    "sinusoidal": {
        "density_kg_m3": 1.225,
        "amplitude_kg_m3": 0.01,
        "wavelength_mm": 8.0,
        "direction": [1.0, 0.0],
        "phase_deg": 0.0,
    },
    "slice": {"snapshot": 0, "path": ""},
    "file": {
        "path": None,
        "format": "auto",
        "dataset": "",
        "slice_index": "none",
        "axis": "z",
        "index_range": "all",
        "spacing_mm": "auto",
        "normalised": "auto",
        "axis_order": "auto",
    },
}

DEFAULT_GRID = [64, 64, 16]
ANALYTIC = ("uniform", "linear", "gaussian", "step", "sinusoidal")


@dataclass(frozen=True)
class DensityField:
    """Density on the nodes of a regular grid spanning the volume.

    Attributes
    ----------
    rho : (nz, ny, nx) float64 array
        Density in kg/m^3; node ``(k, j, i)`` sits at ``x = -Lx/2 + i Lx/(nx-1)`` (likewise y, z),
        in the volume's own frame centred on its mid-point.
    size_m : (Lx, Ly, Lz)
        Physical extent of the volume in metres.
    ambient : float
        Density of the undisturbed medium (kg/m^3), the medium of the reference image.
    notes : tuple of str
        What the source did that the configuration did not spell out (e.g. a file's grid stretched onto
        ``size_mm``); also issued as :class:`DensityNotice` warnings.
    """

    rho: np.ndarray
    size_m: tuple[float, float, float]
    ambient: float
    notes: tuple[str, ...] = ()


def node_coordinates(shape_zyx, size_m):
    """1-D node coordinates (x, y, z) in metres for a grid of ``shape_zyx`` spanning ``size_m``."""
    nz, ny, nx = shape_zyx
    return tuple(np.linspace(-L / 2.0, L / 2.0, n) for n, L in zip((nx, ny, nz), size_m, strict=True))


# ------------------------------------------------------------------ parameter checking


def _grid(volume):
    grid = volume.get("grid") or DEFAULT_GRID
    values = checks.vector("volume.grid", grid, (3,), integer=True, minimum=2, maximum=100_000)
    return tuple(int(g) for g in values)


def _params(volume, source):
    known = SOURCE_KEYS[source]
    extra = set(volume) - set(COMMON_KEYS) - set(known)
    if extra:
        raise SynthbosError(
            f"unknown key volume.{sorted(extra)[0]} for source {source!r}; "
            f"its keys are {sorted(known)} besides the common ones"
        )
    p = {k: volume.get(k, v) for k, v in known.items()}
    for k, v in p.items():
        if v is None:
            raise SynthbosError(f"volume.{k} is required for source {source!r}")
    return p


# Sane magnitudes of the sources' own numbers (lengths in mm, densities in kg/m^3): beyond them a value
# is a unit mistake; the density field itself is then checked by ``checks.check_density``.
_LENGTH_MM = 1.0e6
_DENSITY = checks.MAX_DENSITY_KG_M3


def _number(key, value, *, positive=False, bound=None):
    """A source's number, named ``volume.<key>``: finite, |value| <= bound, > 0 if ``positive``."""
    bounds = {} if bound is None else {"minimum": -bound, "maximum": bound}
    if positive:
        bounds["above"] = 0.0
        bounds.pop("minimum", None)
    return checks.number(f"volume.{key}", value, **bounds)


def _vector(key, value, sizes, *, nonzero=False, bound=None):
    bounds = {} if bound is None else {"minimum": -bound, "maximum": bound}
    v = checks.vector(f"volume.{key}", value, sizes, **bounds)
    v = v + [0.0] * (3 - len(v))
    if nonzero and not any(v):
        raise SynthbosError(f"volume.{key} must not be the zero vector")
    return np.array(v)


def _integer(key, value, *, low=None, high=None):
    return checks.number(f"volume.{key}", value, integer=True, minimum=low, maximum=high)


def _positive_field(rho, source):
    return checks.check_density(
        rho, where=f"volume: source {source!r}", ndim=(3,),
        hint="; reduce the gradient/amplitude/jump or raise volume.density_kg_m3",
    )


# ------------------------------------------------------------------ sources


def _analytic(source, p, size_m, grid):
    nx, ny, nz = grid
    x, y, z = node_coordinates((nz, ny, nx), size_m)
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    rho0 = _number("density_kg_m3", p["density_kg_m3"], positive=True, bound=_DENSITY)
    if source == "uniform":
        rho = np.full((nz, ny, nx), rho0)
    elif source == "linear":
        gx, gy, gz = _vector("gradient_kg_m4", p["gradient_kg_m4"], (2, 3), bound=1.0e12)
        rho = rho0 + gx * X + gy * Y + gz * Z
    elif source == "gaussian":
        cx, cy, cz = _vector("centre_mm", p["centre_mm"], (2, 3), bound=_LENGTH_MM) * 1e-3
        s = _number("sigma_mm", p["sigma_mm"], positive=True, bound=_LENGTH_MM) * 1e-3
        a = _number("amplitude_kg_m3", p["amplitude_kg_m3"], bound=_DENSITY)
        rho = rho0 + a * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2 + (Z - cz) ** 2) / (2 * s * s))
    elif source == "step":
        px, py, pz = _vector("position_mm", p["position_mm"], (2, 3), bound=_LENGTH_MM) * 1e-3
        n = _vector("normal", p["normal"], (2, 3), nonzero=True, bound=1.0e12)
        n = n / np.linalg.norm(n)
        jump = _number("jump_kg_m3", p["jump_kg_m3"], bound=_DENSITY)
        delta = _number("thickness_mm", p["thickness_mm"], positive=True, bound=_LENGTH_MM) * 1e-3
        s = (X - px) * n[0] + (Y - py) * n[1] + (Z - pz) * n[2]
        rho = rho0 + 0.5 * jump * (1.0 + np.tanh(2.0 * s / delta))
    else:  # sinusoidal
        d = _vector("direction", p["direction"], (2, 3), nonzero=True, bound=1.0e12)
        d = d / np.linalg.norm(d)
        a = _number("amplitude_kg_m3", p["amplitude_kg_m3"], bound=_DENSITY)
        lam = _number("wavelength_mm", p["wavelength_mm"], positive=True, bound=_LENGTH_MM) * 1e-3
        phase = math.radians(_number("phase_deg", p["phase_deg"], bound=1.0e6))
        s = X * d[0] + Y * d[1] + Z * d[2]
        rho = rho0 + a * np.sin(2.0 * np.pi * s / lam + phase)
    return _positive_field(rho, source), rho0


def extruded(volume: dict) -> bool:
    """Whether the ``[volume]`` table's source is a plane extruded along z (``slice``) by construction, so
    its medium is planar without being built (other sources, a 2-D file among them, may be too: see
    ``raytrace.medium.is_planar``).

    Examples
    --------
    >>> extruded({"source": "slice"}), extruded({"source": "gaussian"})
    (True, False)
    """
    return volume.get("source") == "slice"


def _extrude(plane):
    """A (ny, nx) slice as a (2, ny, nx) volume: identical planes, d rho/dz = 0 exactly."""
    return np.ascontiguousarray(np.broadcast_to(plane, (2, *plane.shape)))


def _slice_source(p, volume, size_m, memory_gb=None):
    path = p["path"]
    if not isinstance(path, str):
        raise SynthbosError(f'volume.path must be a file name (or "" for the embedded file), got {path!r}')
    dens, _, _ = read_snapshots(path or None, memory_gb=memory_gb)
    k = _integer("snapshot", p["snapshot"], low=0, high=len(dens) - 1)
    scale = float(volume["density_scale_kg_m3"])
    plane = dens[k] * scale
    return _extrude(plane), size_m, float(plane.mean())


def _optional(p, key, off):
    v = p[key]
    return None if (isinstance(v, str) and v.lower() == off) else v


def _file_source(p, volume, size_m, memory_gb=None):
    path = p["path"]
    if not isinstance(path, str) or not path:
        raise SynthbosError(f"volume.path must name a density file, got {path!r}")
    fmt = _optional(p, "format", "auto")
    if fmt is not None and fmt not in FORMATS:
        raise SynthbosError(f'volume.format must be "auto" or one of {list(FORMATS)}, got {fmt!r}')
    dataset = p["dataset"]
    if not isinstance(dataset, str):
        raise SynthbosError(f'volume.dataset must be a name (or ""), got {dataset!r}')
    sl = _optional(p, "slice_index", "none")
    if sl is not None:
        sl = _integer("slice_index", sl)
    axis = p["axis"]
    if axis not in ("x", "y", "z"):
        raise SynthbosError(f'volume.axis must be "x", "y" or "z", got {axis!r}')
    rng = _optional(p, "index_range", "all")
    if rng is not None:
        ok = isinstance(rng, list | tuple) and all(
            (isinstance(r, list | tuple) and len(r) == 2) or r == "all" for r in rng
        )
        if not ok:
            raise SynthbosError(
                f'volume.index_range must be "all" or [[x0, x1], [y0, y1], [z0, z1]] (a pair may be "all"), '
                f"got {rng!r}"
            )
        rng = [None if r == "all" else r for r in rng]
    norm = p["normalised"]
    if isinstance(norm, str) and norm.lower() == "auto":
        norm = None
    elif not isinstance(norm, bool):
        raise SynthbosError(f'volume.normalised must be true, false or "auto", got {norm!r}')
    spacing = _optional(p, "spacing_mm", "auto")
    if spacing is not None:
        vals = spacing if isinstance(spacing, list | tuple) else [spacing]
        if not 1 <= len(vals) <= 3:
            raise SynthbosError(f'volume.spacing_mm must be "auto", a number or a list, got {spacing!r}')
        for i, v in enumerate(vals):
            _number(f"spacing_mm[{i}]", v, positive=True, bound=_LENGTH_MM)

    order = _optional(p, "axis_order", "auto")
    if order is not None and not isinstance(order, str):
        raise SynthbosError(f'volume.axis_order must be "auto" or a string such as "xyz", got {order!r}')
    loaded = load_density(
        path,
        format=fmt,
        dataset=dataset or None,
        slice_index=sl,
        axis=axis,
        index_range=rng,
        spacing_mm=spacing,
        axis_order=order,
        memory_gb=memory_gb,
    )
    fmt = fmt or _inferred(path)
    if norm is None:
        norm = fmt == "jhtdb"
    data = loaded.data * (float(volume["density_scale_kg_m3"]) if norm else 1.0)
    vol = _extrude(data) if data.ndim == 2 else data
    if spacing is not None:
        sp = [s * 1e-3 for s in loaded.spacing]
        nz, ny, nx = vol.shape
        ext = [sp[0] * (nx - 1), sp[1] * (ny - 1)]
        ext.append(sp[2] * (nz - 1) if data.ndim == 3 else size_m[2])
        size_m = tuple(ext)
        notes = ()
    else:
        notes = (_stretch_note(path, data, loaded, size_m),)
        warnings.warn(notes[0], DensityNotice, stacklevel=4)
    return vol, size_m, float(vol.mean()), notes


def _stretch_note(path, data, loaded, size_m):
    """The notice for spacing_mm = "auto": the data's nodes are stretched onto size_mm."""
    shape = data.shape[::-1]  # (nx, ny[, nz])
    ext = [s * 1e3 for s in size_m[: data.ndim]]
    step = [L / (n - 1) for L, n in zip(ext, shape, strict=True)]
    names = "xyz"[: data.ndim]
    msg = (
        f'volume.path {path}: spacing_mm = "auto", so its {"x".join(str(n) for n in shape)} nodes '
        f"({', '.join(names)}) are stretched onto size_mm "
        f"{' x '.join(f'{L:g}' for L in ext)} mm (node spacing {' x '.join(f'{d:.4g}' for d in step)} mm)"
    )
    if loaded.spacing is not None and loaded.spacing_units == "file" and len(loaded.spacing) == data.ndim:
        own = [d * (n - 1) for d, n in zip(loaded.spacing, shape, strict=True)]
        change = (ext[0] / ext[1]) / (own[0] / own[1])
        msg += (
            f"; the file's own spacing {' x '.join(f'{d:.4g}' for d in loaded.spacing)} (file units) "
            f"gives an x:y aspect ratio of {own[0] / own[1]:.4g}, this one {ext[0] / ext[1]:.4g} "
            f"(x {change:.4g} times as stretched as y)"
        )
    return msg + "; set volume.spacing_mm to the file's node spacing in mm to keep its proportions"


def _inferred(path):
    return infer_format(path)


def density_from_config(volume: dict, *, memory_gb=None) -> DensityField:
    """Build the density field described by a ``[volume]`` table.

    Parameters
    ----------
    volume : dict
        The ``[volume]`` table: the common keys (``COMMON_KEYS``) and the source's own keys
        (``SOURCE_KEYS[source]``); missing source keys take their defaults.
    memory_gb : float, optional
        ``limits.memory_gb``: a data file whose declared shape needs more is refused before reading.

    Returns
    -------
    DensityField
        ``rho`` (nz, ny, nx) float64 in kg/m^3, finite and > 0; ``size_m``; ``ambient``.

    Raises
    ------
    SynthbosError
        Unknown or bad key (named ``volume.<key>``), unreadable or invalid data file (named), or a
        density that is not finite and positive everywhere.
    """
    source = volume.get("source", COMMON_KEYS["source"])
    if not isinstance(source, str) or source not in SOURCE_KEYS:
        raise SynthbosError(f"volume.source must be one of {sorted(SOURCE_KEYS)}, got {source!r}")
    p = _params(volume, source)
    size = volume.get("size_mm", COMMON_KEYS["size_mm"])
    if not isinstance(size, list | tuple) or len(size) != 3:
        raise SynthbosError(f"volume.size_mm must be a list of three numbers, got {size!r}")
    size_m = tuple(_number(f"size_mm[{i}]", s, positive=True, bound=_LENGTH_MM) * 1e-3 for i, s in enumerate(size))
    notes = ()
    if source in ANALYTIC:
        with np.errstate(all="ignore"):  # overflow or 0/0 of extreme parameters: the field check names them
            rho, ambient = _analytic(source, p, size_m, _grid(volume))
    else:
        if volume.get("grid") is not None:
            raise SynthbosError(
                f"volume.grid does not apply to source {source!r}: its grid comes from the data"
            )
        _number(
            "density_scale_kg_m3",
            volume.get("density_scale_kg_m3", COMMON_KEYS["density_scale_kg_m3"]),
            positive=True,
            bound=_DENSITY,
        )
        volume = {"density_scale_kg_m3": COMMON_KEYS["density_scale_kg_m3"], **volume}
        if source == "slice":
            rho, size_m, ambient = _slice_source(p, volume, size_m, memory_gb)
        else:
            rho, size_m, ambient, notes = _file_source(p, volume, size_m, memory_gb)
    return DensityField(
        rho=np.ascontiguousarray(rho, dtype=np.float64), size_m=tuple(size_m), ambient=ambient, notes=notes
    )
