"""The set-up of a camera pair, for density without a render configuration: the ``[setup]`` table.

``synthbos process --setup-file CAMERA.toml`` records it in the result file, ``synthbos integrate
--setup-file CAMERA.toml`` uses it (a ``[setup]`` table in a process configuration given to
``process --config`` counts too). The table names what Eq. 4 needs to turn image displacements into
density gradients, and what maps image pixels to the flow's mid-plane::

    [setup]
    z_d_mm = 250.0                 # Z_D: target (background) to the mid-plane of the flow
    depth_mm = 10.0                # L: depth of the flow along the line of sight
    target_distance_mm = 1000.0    # target to the lens (its aperture stop), where the chief rays meet
    pixel_pitch_um = 10.0          # the sensor's pixel pitch
    magnification = 0.1167         # M of the target plane; or focal_length_mm = 105.0 (M = f / (Z_T - f)),
                                   # or target_mm_per_px = 0.0857 (a calibrated scale at the target)
    ambient_density_kg_m3 = 1.225  # the density of the undisturbed medium: the constant of integration
    gladstone_dale_m3_per_kg = 2.25e-4   # K (n = 1 + K rho); default: air at 532 nm
    principal_point_px = [255.5, 255.5]  # where the optical axis meets the image; default: its centre

Exactly one of ``magnification``, ``focal_length_mm`` and ``target_mm_per_px`` gives the scale. The
density map's x, y (mm) are measured from the optical axis at the mid-plane.
"""

from __future__ import annotations

import math
from pathlib import Path

from synthbos import SynthbosError
from synthbos.values import cut, number, numbers

from .integrate import Geometry

__all__ = ["AIR_GLADSTONE_DALE_M3_PER_KG", "SETUP_KEYS", "check_setup_table", "geometry_from_setup",
           "read_setup_file"]

#: Gladstone-Dale constant of air, m^3/kg (the renderer's default, visible light).
AIR_GLADSTONE_DALE_M3_PER_KG = 2.25e-4

# Key -> (bounds for synthbos.values.number, meaning). Every length in mm, the pitch in um.
SETUP_KEYS = {
    "z_d_mm": ({"above": 0.0, "maximum": 1e5}, "target to the mid-plane of the flow, mm"),
    "depth_mm": ({"above": 0.0, "maximum": 1e5}, "depth of the flow along the line of sight, mm"),
    "target_distance_mm": ({"above": 0.0, "maximum": 1e6}, "target to the lens, mm"),
    "pixel_pitch_um": ({"above": 0.0, "maximum": 1e3}, "sensor pixel pitch, um"),
    "magnification": ({"above": 0.0, "maximum": 100.0}, "magnification of the target plane"),
    "focal_length_mm": ({"above": 0.0, "maximum": 1e5}, "focal length of the lens, mm"),
    "target_mm_per_px": ({"above": 0.0, "maximum": 1e4}, "mm at the target per image pixel"),
    "ambient_density_kg_m3": ({"above": 0.0, "maximum": 1e5}, "density of the undisturbed medium, kg/m^3"),
    "gladstone_dale_m3_per_kg": ({"above": 0.0, "maximum": 1e-2}, "Gladstone-Dale constant K, m^3/kg"),
}
REQUIRED = ("z_d_mm", "depth_mm", "target_distance_mm", "pixel_pitch_um", "ambient_density_kg_m3")
SCALES = ("magnification", "focal_length_mm", "target_mm_per_px")


def check_setup_table(table, where: str) -> dict:
    """Check a ``[setup]`` table (one line naming the key, its range and the value); return it unchanged."""
    _checked(table, where)
    return dict(table)


def _checked(table: dict, where: str) -> dict:
    """The ``[setup]`` values, each checked (one line naming the key, its range and the value)."""
    if not isinstance(table, dict):
        raise SynthbosError(f"{where}: setup must be a table ([setup])")
    known = (*SETUP_KEYS, "principal_point_px")
    unknown = sorted(set(table) - set(known))
    if unknown:
        raise SynthbosError(f"{where}: unknown [setup] key(s) {', '.join(unknown)}; known: {', '.join(known)}")
    missing = [k for k in REQUIRED if k not in table]
    if missing:
        raise SynthbosError(f"{where}: [setup] needs {', '.join(missing)}")
    scales = [k for k in SCALES if k in table]
    if len(scales) != 1:
        given = ", ".join(scales) if scales else "none"
        raise SynthbosError(f"{where}: [setup] needs exactly one of {', '.join(SCALES)} (the scale), got {given}")
    out = {k: number(f"setup.{k}", v, **SETUP_KEYS[k][0]) for k, v in table.items() if k in SETUP_KEYS}
    if "principal_point_px" in table:
        out["principal_point_px"] = numbers("setup.principal_point_px", table["principal_point_px"], sizes=(2,),
                                            minimum=-1e6, maximum=1e6)
    if not out["z_d_mm"] < out["target_distance_mm"]:
        raise SynthbosError(f"{where}: setup.z_d_mm = {out['z_d_mm']:g} must be less than setup.target_distance_mm = "
                            f"{out['target_distance_mm']:g}: the flow lies between the target and the lens")
    near, far = out["z_d_mm"] - out["depth_mm"] / 2, out["z_d_mm"] + out["depth_mm"] / 2
    if not (near > 0 and far < out["target_distance_mm"]):
        raise SynthbosError(f"{where}: the flow (setup.z_d_mm = {out['z_d_mm']:g} +- setup.depth_mm / 2 = "
                            f"{near:g} ... {far:g} mm from the target) must lie between the target (0) and the lens "
                            f"(setup.target_distance_mm = {out['target_distance_mm']:g})")
    if "focal_length_mm" in out and not out["focal_length_mm"] < out["target_distance_mm"]:
        raise SynthbosError(f"{where}: setup.focal_length_mm = {out['focal_length_mm']:g} must be less than "
                            f"setup.target_distance_mm = {out['target_distance_mm']:g} (a real image)")
    return out


def geometry_from_setup(table: dict, image_shape, *, where="[setup]") -> Geometry:
    """The :class:`~synthbos.benchmarks.integrate.Geometry` of a ``[setup]`` table and the images' (H, W).

    Parameters
    ----------
    table : dict
        The ``[setup]`` table (module docstring); checked here.
    image_shape : (H, W)
        The camera images' shape (the default principal point is their centre).
    where : str
        What the table came from, for the messages.

    Returns
    -------
    Geometry
        The numbers the integration needs, in metres; ``n0 = 1 + K rho_ambient``; the frame's origin
        is the optical axis (``volume_centre_m = (0, 0)``).

    Examples
    --------
    >>> g = geometry_from_setup({"z_d_mm": 250, "depth_mm": 10, "target_distance_mm": 1000, "pixel_pitch_um": 10,
    ...                          "focal_length_mm": 105, "ambient_density_kg_m3": 1.225}, (512, 512))
    >>> round(g.magnification, 4), g.principal_point_px, round(g.mm_per_px, 4)
    (0.1173, (255.5, 255.5), 0.0639)
    """
    s = _checked(table, where)
    pitch = s["pixel_pitch_um"] * 1e-6
    if "magnification" in s:
        m = s["magnification"]
    elif "focal_length_mm" in s:
        m = s["focal_length_mm"] / (s["target_distance_mm"] - s["focal_length_mm"])
    else:
        m = pitch / (s["target_mm_per_px"] * 1e-3)
    h, w = (int(n) for n in image_shape)
    k = s.get("gladstone_dale_m3_per_kg", AIR_GLADSTONE_DALE_M3_PER_KG)
    rho = s["ambient_density_kg_m3"]
    n0 = 1.0 + k * rho
    if not math.isfinite(n0) or n0 > 3.0:
        raise SynthbosError(f"{where}: the refractive index 1 + K rho_ambient = {n0:.4g} is no fluid's: "
                            "check setup.gladstone_dale_m3_per_kg and setup.ambient_density_kg_m3")
    centre = s.get("principal_point_px", ((w - 1) / 2.0, (h - 1) / 2.0))
    return Geometry(
        magnification=m, pixel_pitch_m=pitch, z_d_m=s["z_d_mm"] * 1e-3, z_stop_m=s["target_distance_mm"] * 1e-3,
        depth_m=s["depth_mm"] * 1e-3, gladstone_dale_m3_per_kg=k, n0=n0, principal_point_px=tuple(centre),
        volume_centre_m=(0.0, 0.0), ambient_density_kg_m3=rho, image_shape=(h, w),
    )


def read_setup_file(path) -> dict:
    """The ``[setup]`` table of a TOML file (checked); other tables must be those of a process configuration.

    A missing, unreadable or malformed file, a missing ``[setup]`` table or a bad value raises
    ``SynthbosError`` with one line.
    """
    from synthbos.raytrace.config import read_toml

    from .process import process_tables

    path = Path(path)
    raw = read_toml(path)
    if "setup" not in raw:
        raise SynthbosError(f"set-up file {path} has no [setup] table (z_d_mm, depth_mm, ...; see docs/own-images.md)")
    other = sorted(set(raw) - {"setup", *process_tables()})
    if other:
        raise SynthbosError(f"set-up file {path}: unknown table(s) {cut(', '.join(other))}; it holds "
                            "[setup] and may hold the tables of a process configuration")
    return check_setup_table(raw["setup"], f"set-up file {path}")
