"""Density sources: the function that turns the ``[volume]`` table of a configuration into a
density field on a regular grid.

Contract (relied on by ``raytrace.config`` and ``raytrace.medium``):

``density_from_config(volume) -> DensityField`` takes the validated ``[volume]`` table, whose common
keys (``COMMON_KEYS``) already carry defaults, and reads the source's own keys from the same table;
an unknown or bad source key raises ``SynthbosError`` naming ``volume.<key>``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synthbos import SynthbosError

__all__ = ["COMMON_KEYS", "SOURCE_KEYS", "DensityField", "density_from_config"]

# Keys every source shares, with defaults. ``grid`` is [nx, ny, nz] nodes; None lets the source choose.
COMMON_KEYS = {
    "source": "gaussian",
    "distance_from_target_mm": 250.0,
    "size_mm": [32.0, 32.0, 10.0],
    "gladstone_dale_m3_per_kg": 2.25e-4,
    "density_scale_kg_m3": 1.225,
    "grid": None,
}

# Each source's own keys with defaults (None means required).
SOURCE_KEYS: dict[str, dict[str, object]] = {
    "uniform": {"density_kg_m3": 1.225},
    "linear": {"density_kg_m3": 1.225, "gradient_kg_m4": [0.0, 0.0]},
    "gaussian": {"density_kg_m3": 1.225, "amplitude_kg_m3": 0.05, "sigma_mm": 4.0, "centre_mm": [0.0, 0.0, 0.0]},
}

_DEFAULT_GRID = [64, 64, 16]


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
    """

    rho: np.ndarray
    size_m: tuple[float, float, float]
    ambient: float


def node_coordinates(shape_zyx, size_m):
    """1-D node coordinates (x, y, z) in metres for a grid of ``shape_zyx`` spanning ``size_m``."""
    nz, ny, nx = shape_zyx
    return tuple(np.linspace(-L / 2.0, L / 2.0, n) for n, L in zip((nx, ny, nz), size_m, strict=True))


def _grid(volume):
    grid = volume.get("grid") or _DEFAULT_GRID
    if len(grid) != 3 or any(int(g) != g or g < 2 for g in grid):
        raise SynthbosError(f"volume.grid must be three whole numbers >= 2 (nx, ny, nz), got {grid!r}")
    return tuple(int(g) for g in grid)


def _params(volume, source):
    known = SOURCE_KEYS[source]
    extra = set(volume) - set(COMMON_KEYS) - set(known)
    if extra:
        raise SynthbosError(
            f"unknown key volume.{sorted(extra)[0]} for source {source!r}; "
            f"its keys are {sorted(known)} besides the common ones"
        )
    return {k: volume.get(k, v) for k, v in known.items()}


def density_from_config(volume: dict) -> DensityField:
    """Build the density field described by a ``[volume]`` table."""
    source = volume.get("source", COMMON_KEYS["source"])
    if source not in SOURCE_KEYS:
        raise SynthbosError(f"volume.source must be one of {sorted(SOURCE_KEYS)}, got {source!r}")
    p = _params(volume, source)
    size_m = tuple(float(s) * 1e-3 for s in volume["size_mm"])
    nx, ny, nz = _grid(volume)
    x, y, z = node_coordinates((nz, ny, nx), size_m)
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    rho0 = float(p["density_kg_m3"])
    if source == "uniform":
        rho = np.full((nz, ny, nx), rho0)
    elif source == "linear":
        gx, gy = (float(g) for g in p["gradient_kg_m4"])
        rho = rho0 + gx * X + gy * Y
    else:  # gaussian
        cx, cy, cz = (float(c) * 1e-3 for c in p["centre_mm"])
        s = float(p["sigma_mm"]) * 1e-3
        r2 = (X - cx) ** 2 + (Y - cy) ** 2 + (Z - cz) ** 2
        rho = rho0 + float(p["amplitude_kg_m3"]) * np.exp(-r2 / (2 * s * s))
    return DensityField(rho=np.ascontiguousarray(rho, dtype=np.float64), size_m=size_m, ambient=rho0)
