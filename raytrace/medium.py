"""The refracting medium: density -> refractive index (Gladstone-Dale) -> Warp arrays.

``n = 1 + K rho``. The renderer never stores ``n`` itself: it keeps ``n - 1`` (float32 would lose
most of the digits of a number 1.0003 that differ in the sixth place) and ``grad n`` from central
differences (one-sided on the faces) computed in float64, packed per node as (dn/dx, dn/dy, dn/dz, n-1).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import warp as wp

from synthbos import SynthbosError
from synthbos.memo import RecentResults

from . import medium_kernels, sources
from .checks import check_density

__all__ = [
    "EXACT_FIELDS", "FIELDS", "MAX_INDEX", "MediumData", "half_scale", "is_planar", "medium_from_config",
    "medium_from_density", "medium_struct",
    "straight_to_warp", "to_warp",
]


@dataclass(frozen=True)
class MediumData:
    """Host-side medium: packed node data and placement (global frame, metres)."""

    field: np.ndarray  # (nz, ny, nx, 4) float32: dn/dx, dn/dy, dn/dz, n - 1
    size: tuple[float, float, float]
    centre: tuple[float, float, float]
    n0: float  # refractive index of the undisturbed (ambient) medium
    gladstone_dale: float
    density: sources.DensityField

    @property
    def spacing(self) -> tuple[float, float, float]:
        nz, ny, nx = self.field.shape[:3]
        return tuple(L / (n - 1) for L, n in zip(self.size, (nx, ny, nz), strict=True))

    @cached_property
    def planar(self) -> bool:
        """:func:`is_planar` of the nodes, told once (it picks the struct, the register cap and the launch
        shape of every render of this medium)."""
        return is_planar(self.field)


# Largest refractive index a medium may reach: liquids and gases stay far below; more is a unit mistake.
MAX_INDEX = 2.5


def medium_from_density(density: sources.DensityField, *, gladstone_dale, centre) -> MediumData:
    """Refractive index data for a density field placed with its centre at ``centre`` (metres)."""
    rho = check_density(density.rho, where="volume", ndim=(3,))
    nz, ny, nx = rho.shape
    size = tuple(float(s) for s in density.size_m)
    spacing = [L / (n - 1) for L, n in zip(size, (nx, ny, nz), strict=True)]
    n_minus_1 = gladstone_dale * rho
    gz, gy, gx = np.gradient(n_minus_1, spacing[2], spacing[1], spacing[0])
    field = np.stack([gx, gy, gz, n_minus_1], axis=-1).astype(np.float32)
    return MediumData(
        field=np.ascontiguousarray(field), size=size, centre=tuple(float(c) for c in centre),
        n0=1.0 + gladstone_dale * float(density.ambient), gladstone_dale=float(gladstone_dale), density=density,
    )


# The densities of the last few volume tables: a campaign renders many pairs of each snapshot, and
# reading and resampling one costs ~15 ms of the plan's ~28 ms. Read-only; data files are not kept.
_DENSITIES = RecentResults(keep=2)


def medium_from_config(cfg: dict) -> MediumData:
    """Build the medium described by the ``[volume]`` table of a validated configuration."""
    vol = cfg["volume"]
    table = {k: v for k, v in vol.items() if k != "offset_mm"}
    memory_gb = cfg.get("limits", {}).get("memory_gb")

    def density_now():
        density = sources.density_from_config(table, memory_gb=memory_gb)
        np.asarray(density.rho).setflags(write=False)  # shared by the renders of this table
        return density

    if table.get("source") == "file":  # the file may change between renders
        density = density_now()
    else:
        density = _DENSITIES.get((), density_now, extra=json.dumps([table, memory_gb], sort_keys=True, default=str))
    top = vol["gladstone_dale_m3_per_kg"] * float(density.rho.max())
    if top > MAX_INDEX - 1.0:
        raise SynthbosError(
            f"volume: refractive index 1 + K rho reaches {1.0 + top:.4g} (K = volume.gladstone_dale_m3_per_kg = "
            f"{vol['gladstone_dale_m3_per_kg']:g}, rho up to {float(density.rho.max()):.4g} kg/m^3); "
            f"it must stay below {MAX_INDEX:g}"
        )
    ox, oy = (o * 1e-3 for o in vol["offset_mm"])
    return medium_from_density(
        density, gladstone_dale=vol["gladstone_dale_m3_per_kg"],
        centre=(ox, oy, vol["distance_from_target_mm"] * 1e-3),
    )


# How the renderer stores and reads the medium on the device (``rays.field``): the exact float32 nodes
# read with scalar or 128-bit loads, float16 node pairs or nodes (the same numbers), or a 3D texture
# (hardware-filtered in float32 or float16, or point-sampled with the same arithmetic as float32).
FIELDS = ("float32", "float32_vec", "float16", "float16_nodes", "texture", "texture16", "texture_nearest")
EXACT_FIELDS = ("float32", "float32_vec", "texture_nearest")  # bitwise the same samples as "float32"


def half_scale(field) -> np.ndarray:
    """Per channel power of two that brings the largest magnitude of ``field`` (..., 4) to [2^13, 2^14).

    Float16 then keeps 11 significant bits for the strongest values and weak fields stay clear of its
    subnormals; scaling by a power of two is exact.
    """
    top = np.abs(field).reshape(-1, field.shape[-1]).max(axis=0).astype(np.float64)
    exponent = np.where(top > 0, 13 - np.floor(np.log2(np.where(top > 0, top, 1.0))), 0.0)
    return np.exp2(exponent)


def is_planar(field) -> bool:
    """True when every node plane along z of ``field`` (nz, ny, nx, 4) holds the same values: a 2-D field
    carried through the depth (the embedded slices). Trilinear sampling is then bilinear sampling of one
    plane (the blend along z of equal values), which the exact fields do with half the loads; the
    samples differ at most by the rounding of that blend."""
    field = np.asarray(field)
    return bool(all(np.array_equal(field[k], field[0]) for k in range(1, field.shape[0])))


def straight_to_warp(medium: MediumData) -> medium_kernels.MediumStraight:
    """The box's placement only, for the reference image's straight rays (nothing to upload)."""
    m = medium_kernels.MediumStraight()
    m.half = wp.vec3(*(0.5 * s for s in medium.size))
    m.inv_spacing = wp.vec3(*(1.0 / s for s in medium.spacing))
    m.centre = wp.vec3(*medium.centre)
    return m


def medium_struct(field: str, planar: bool = True):
    """The struct of ``raytrace.medium_kernels`` that :func:`to_warp` gives for ``field`` (one of ``FIELDS``)
    and a ``planar`` medium or not (:func:`is_planar`).

    Examples
    --------
    >>> medium_struct("float32_vec").key, medium_struct("float32_vec", planar=False).key
    ('MediumVec', 'MediumVec3D')
    """
    if field not in FIELDS:
        raise SynthbosError(f"rays.field must be one of {list(FIELDS)}, got {field!r}")
    mk = medium_kernels
    return {"float32": mk.Medium, "float32_vec": mk.MediumVec if planar else mk.MediumVec3D, "float16": mk.MediumHalf,
            "float16_nodes": mk.MediumHalfNodes, "texture": mk.MediumTexture, "texture16": mk.MediumTexture,
            "texture_nearest": mk.MediumTexels}[field]


def to_warp(medium: MediumData, *, device=None, field="float32"):
    """Upload the medium to a Warp device as the struct ``render_rays`` reads (see ``FIELDS``).

    "float32" and "float32_vec" give ``medium_kernels.Medium`` / ``medium_kernels.MediumVec`` over the packed nodes
    (``MediumVec3D`` where the node planes differ);
    "float16" gives ``medium_kernels.MediumHalf`` (node pairs along x), "float16_nodes"
    ``medium_kernels.MediumHalfNodes``; "texture" and "texture16"
    ``medium_kernels.MediumTexture``; "texture_nearest" ``medium_kernels.MediumTexels``.
    """
    if field not in FIELDS:
        raise SynthbosError(f"rays.field must be one of {list(FIELDS)}, got {field!r}")
    planar = medium.planar if field in EXACT_FIELDS else False
    if field in ("float32", "float32_vec"):
        m = medium_struct(field, planar)()
        m.field = wp.array(medium.field, dtype=wp.vec4, device=device)
    elif field == "float16":
        scale = half_scale(medium.field)
        nodes = (medium.field * scale).astype(np.float16)
        pairs = np.concatenate([nodes[:, :, :-1], nodes[:, :, 1:]], axis=-1)
        m = medium_kernels.MediumHalf()
        m.pairs = wp.array(np.ascontiguousarray(pairs), dtype=medium_kernels.vec8h, device=device)
        m.unscale = wp.vec4(*(1.0 / scale))
    elif field == "float16_nodes":
        scale = half_scale(medium.field)
        m = medium_kernels.MediumHalfNodes()
        m.nodes = wp.array((medium.field * scale).astype(np.float16), dtype=wp.vec4h, device=device)
        m.unscale = wp.vec4(*(1.0 / scale))
    elif field == "texture_nearest":
        m = medium_kernels.MediumTexels()
        m.tex = wp.Texture3D(
            medium.field, filter_mode=wp.TextureFilterMode.CLOSEST, address_mode=wp.TextureAddressMode.CLAMP,
            normalized_coords=False, device=device,
        )
    else:
        data, unscale = medium.field, np.ones(4)
        if field == "texture16":
            scale = half_scale(medium.field)
            data, unscale = np.ascontiguousarray((medium.field * scale).astype(np.float16)), 1.0 / scale
        m = medium_kernels.MediumTexture()
        m.tex = wp.Texture3D(
            data, filter_mode=wp.TextureFilterMode.LINEAR, address_mode=wp.TextureAddressMode.CLAMP,
            normalized_coords=False, device=device,
        )
        m.unscale = wp.vec4(*unscale)
    if field in EXACT_FIELDS:
        m.planar = int(planar)
    m.half = wp.vec3(*(0.5 * s for s in medium.size))
    m.inv_spacing = wp.vec3(*(1.0 / s for s in medium.spacing))
    m.centre = wp.vec3(*medium.centre)
    return m
