"""Render configuration: TOML tables with defaults, validated key by key.

A configuration is a dict of tables, ``camera``, ``target``, ``volume``, ``rays`` and ``sensor``. The
defaults are in ``raytrace/default.toml`` (the paper's set-up). ``load_config`` accepts a path, a TOML
string path-like, or a dict (possibly partial), merges it over the defaults, checks every key and
value, and returns a new nested dict. Unknown keys and bad values raise ``SynthbosError`` naming the
key as ``table.key``. ``load_config(config, setup=NAME)`` starts from a named set-up instead (``SETUPS``:
small TOML files beside ``default.toml`` holding only what they change, e.g. ``narrow.toml``).

Keys
----
[camera]
  pixels = [W, H]; pixel_pitch_um; focal_length_mm; f_number (> 0); lens = "thin" | "thick";
  wavelength_nm (diffraction spot); glass_index, lens_thickness_mm (thick lens).
[target]
  distance_mm (target to lens); pattern = "grid" | "random"; dots_per_32px (image-plane density);
  dot_diameter_px (image diameter, e^-2); dot_model = "point" | "disk" (a point source, or a disk of
  physical diameter dot_diameter_px * pitch / M emitting from its whole area); seed (random pattern);
  min_spacing_px (random pattern: least centre distance, default dot_diameter_px).
[volume]
  source = "uniform" | "linear" | "gaussian" | ... (see raytrace.sources); distance_from_target_mm
  (Z_D, target to the volume's mid-plane); size_mm = [x, y, z]; offset_mm = [x, y] (the volume's
  centre off the optical axis); gladstone_dale_m3_per_kg (K);
  density_scale_kg_m3 (applied to normalised slices only); grid = [nx, ny, nz] nodes; plus the
  source's own keys.
[rays]
  per_dot; seed; step_mm = "grid" (the smallest node spacing) or a length; stepping = "cells" | "fixed"
  (how RK4 steps through the volume, see ``raytrace.kernels.trace_volume``: "cells", the default, ends
  each step at the next node plane the ray crosses, at the back face, or after a quarter of the
  volume's depth, or after step_mm when that is a length; "fixed" takes equal steps of step_mm; the
  ground truths' straight-ray integrals sample the depth every step_mm either way); chunk (rays per launch);
  aim_iterations = "auto" | n: re-aim each ray n times so that, refracted by the flow, it still
  crosses the aperture stop at its sampled point ("auto": 1 for the thick lens, whose aberrations
  make the landing point depend on where a ray crosses the stop; 0 for the ideal thin lens, which
  images every ray from a point to one point).
  Speed settings (see ``raytrace.render.trace_rays``): field = "float32" | "float32_vec" |
  "texture_nearest" (the exact float32 nodes: scalar loads, 128-bit loads, a point-sampled texture;
  the same bits on the CPU, within ~1e-8 px on CUDA, whose compiler orders the trilinear sums'
  fused multiply-adds differently for each) | "float16" | "float16_nodes" | "texture" | "texture16" (approximate:
  float16 node pairs along x or nodes, which agree bitwise with each other; the texture unit's
  trilinear filter, with 8-bit weights on CUDA); dot_order = "pattern" | "morton" (the
  order in which threads take the dots); rays_per_thread = "auto" | n (each thread traces this many
  consecutive rays of one dot and adds their sums to the dot's once; "auto": 8 for straight rays and
  planar media, 1 through a 3-D medium); rays_per_group = "auto" | n (consecutive threads take this many
  chunks of rays of one dot); block_dim (threads per CUDA block); max_registers = "auto" | 0 | 80 | 64 (the
  compiler's choice, or at most that many registers a thread on CUDA). The launch settings never change a bit
  of the result. Defaults: field "float32_vec", dot_order "morton", rays_per_group "auto" (8 for planar media
  and straight rays, 64 through a 3-D medium), rays_per_thread "auto", block_dim 256, max_registers "auto"
  (64 for planar media and straight rays, 80 through a 3-D medium: the fastest exact choices measured on
  H200 and H100 GPUs, see docs/benchmarks.md, renderer speed; the CPU ignores max_registers).
[sensor]
  spot_diameter_px = "auto" | "diffraction" | px ("auto": dot_diameter_px for point dots, the
  diffraction spot 2.44 lambda f# (1 + M) for disks); peak_intensity (peak I0 of a point dot's spot).
[limits] (optional; checked before any work, raise them when the machine can take it)
  memory_gb (default: 80 % of this machine's memory, at most 64): estimated host memory of the images,
  the dots and the density grid; a data file is refused by its declared shape before it is read.
  ray_steps (default 1e10 on the CPU, about 10 minutes; 1e12 on a GPU): 2 images x dots x rays.per_dot
  x RK4 steps per ray x (1 + aim iterations).
  steps_per_ray (default 10000): RK4 steps of one ray across the volume's depth.

Ranges
------
Every number is checked against a physical (or float32-safe) range, listed in ``_RANGES`` below; a value
outside it is refused with the range in the message: e.g. pixel_pitch_um 0.1..1000, f_number 0.5..1000,
wavelength_nm 100..1e5, glass_index (1, 4], dot_diameter_px and spot_diameter_px 0.1..64, peak_intensity
1e-3..1e5 (the fixed-point image accumulator), densities <= 1e5 kg/m^3, aim_iterations 0..100, step_mm
1e-6..1e6, pixels <= 65536 a side. Seeds: target.seed 0..2^63-1 (NumPy honours all of them); rays.seed
0..2^32-1, because Warp's ``rand_init`` takes a 32-bit seed and a larger one would repeat a smaller one.
The medium's refractive index 1 + K rho must stay below 2.5.
"""

from __future__ import annotations

import copy
import os
import tomllib
from pathlib import Path

from synthbos import SynthbosError

from . import checks, sources
from .defaults import DEFAULT_CONFIG, SETUPS, setup_tables
from .medium import FIELDS

__all__ = ["DEFAULT_CONFIG", "SETUPS", "config_to_toml", "load_config", "merge_tables", "read_toml", "setup_tables"]



# Keys allowed beyond the defaults, with their defaults.
_OPTIONAL = {
    "target": {"min_spacing_px": None},
    "rays": {
        "chunk": 4_194_304, "aim_iterations": "auto", "field": "float32_vec", "dot_order": "morton",
        "rays_per_group": "auto", "rays_per_thread": "auto", "block_dim": 256, "max_registers": "auto",
        "stepping": "cells",
    },
    "volume": {k: v for k, v in sources.COMMON_KEYS.items() if k not in DEFAULT_CONFIG["volume"]},
    # Resource limits, checked before any work (None: the default, see raytrace.checks).
    "limits": {"memory_gb": None, "ray_steps": None, "steps_per_ray": 10_000},
}


_SEED_MAX = 2**63 - 1

# Physical (or sane) range of every number of the fixed tables: key -> bounds for ``checks.number``.
# A value outside is a unit mistake or would break the float32 renderer; the message names the range.
_RANGES = {
    "camera.pixel_pitch_um": {"minimum": 0.1, "maximum": 1000.0},
    "camera.focal_length_mm": {"minimum": 1.0, "maximum": 1.0e5},
    "camera.f_number": {"minimum": 0.5, "maximum": 1000.0},
    "camera.wavelength_nm": {"minimum": 100.0, "maximum": 1.0e5},
    "camera.glass_index": {"above": 1.0, "maximum": 4.0},
    "camera.lens_thickness_mm": {"above": 0.0, "maximum": 1000.0},
    "target.distance_mm": {"above": 0.0, "maximum": 1.0e6},
    "target.dots_per_32px": {"above": 0.0, "maximum": 256.0},
    "target.dot_diameter_px": {"minimum": 0.1, "maximum": checks.MAX_SPOT_PX},
    "target.seed": {"integer": True, "minimum": 0, "maximum": _SEED_MAX},
    "target.min_spacing_px": {"minimum": 0.0, "maximum": 1024.0},
    "volume.distance_from_target_mm": {"above": 0.0, "maximum": 1.0e6},
    "volume.gladstone_dale_m3_per_kg": {"above": 0.0, "maximum": 1.0e-2},
    "volume.density_scale_kg_m3": {"above": 0.0, "maximum": checks.MAX_DENSITY_KG_M3},
    "rays.per_dot": {"integer": True, "minimum": 1, "maximum": 10**8},
    "rays.seed": {
        "integer": True, "minimum": 0, "maximum": 2**32 - 1,
        "why": " (the ray generator, Warp's rand_init, takes a 32-bit seed; larger seeds would repeat smaller ones)",
    },
    "rays.chunk": {"integer": True, "minimum": 1, "maximum": 2**28},
    "rays.aim_iterations": {"integer": True, "minimum": 0, "maximum": 100},
    "rays.rays_per_group": {"integer": True, "minimum": 1, "maximum": 2**16},
    "rays.rays_per_thread": {"integer": True, "minimum": 1, "maximum": 1024},
    "rays.block_dim": {"integer": True, "minimum": 32, "maximum": 1024},
    "rays.step_mm": {"minimum": 1.0e-6, "maximum": 1.0e6},
    "sensor.spot_diameter_px": {"minimum": 0.1, "maximum": checks.MAX_SPOT_PX},
    "sensor.peak_intensity": {"minimum": 1.0e-3, "maximum": 1.0e5},
    "limits.memory_gb": {"above": 0.0, "maximum": 1.0e6},
    "limits.ray_steps": {"minimum": 1.0, "maximum": 1.0e18},
    "limits.steps_per_ray": {"integer": True, "minimum": 1, "maximum": 10**8},
}
_PIXELS_MAX = 65536  # per side
_GRID_MAX = 100_000  # nodes per axis
_BYTES_PER_PIXEL = 48  # two int64 device images, their float64 and float32 copies
_BYTES_PER_DOT = 512  # positions, sums, flags and the random pattern's candidates


def _num(name, value, **bounds):
    """A number of the configuration, checked against its documented range (``_RANGES``)."""
    return checks.number(name, value, **{**_RANGES.get(name, {}), **bounds})


def _choice(name, value, options):
    if not isinstance(value, str) or value not in options:
        raise SynthbosError(f"{name} must be one of {list(options)}, got {value!r}")
    return value


def _pair(name, value, *, integer=False, maximum=None):
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise SynthbosError(f"{name} must be a list of two numbers, got {value!r}")
    return [_num(f"{name}[{i}]", v, above=0, integer=integer, maximum=maximum) for i, v in enumerate(value)]


def _validate(cfg):
    cam, tgt, vol, rays, sen = (cfg[k] for k in ("camera", "target", "volume", "rays", "sensor"))
    cam["pixels"] = _pair("camera.pixels", cam["pixels"], integer=True, maximum=_PIXELS_MAX)
    for key in ("pixel_pitch_um", "focal_length_mm", "f_number", "wavelength_nm", "lens_thickness_mm", "glass_index"):
        cam[key] = _num(f"camera.{key}", cam[key])
    _choice("camera.lens", cam["lens"], ("thin", "thick"))

    tgt["distance_mm"] = _num("target.distance_mm", tgt["distance_mm"])
    _choice("target.pattern", tgt["pattern"], ("grid", "random"))
    tgt["dots_per_32px"] = _num("target.dots_per_32px", tgt["dots_per_32px"])
    tgt["dot_diameter_px"] = _num("target.dot_diameter_px", tgt["dot_diameter_px"])
    _choice("target.dot_model", tgt["dot_model"], ("point", "disk"))
    tgt["seed"] = _num("target.seed", tgt["seed"])
    if tgt["min_spacing_px"] is not None:
        tgt["min_spacing_px"] = _num("target.min_spacing_px", tgt["min_spacing_px"])

    vol["distance_from_target_mm"] = _num("volume.distance_from_target_mm", vol["distance_from_target_mm"])
    vol["size_mm"] = checks.vector("volume.size_mm", vol["size_mm"], (3,), above=0.0, maximum=1.0e6)
    vol["offset_mm"] = checks.vector("volume.offset_mm", vol["offset_mm"], (2,), minimum=-1.0e6, maximum=1.0e6)
    source = _choice("volume.source", vol["source"], tuple(sources.SOURCE_KEYS))
    for key, default in sources.SOURCE_KEYS[source].items():
        if key not in vol:
            if default is None:
                raise SynthbosError(f"volume.{key} is required for source {source!r}")
            vol[key] = copy.deepcopy(default)
    vol["gladstone_dale_m3_per_kg"] = _num("volume.gladstone_dale_m3_per_kg", vol["gladstone_dale_m3_per_kg"])
    vol["density_scale_kg_m3"] = _num("volume.density_scale_kg_m3", vol["density_scale_kg_m3"])
    if vol["grid"] is not None:
        vol["grid"] = [
            int(v) for v in checks.vector("volume.grid", vol["grid"], (3,), integer=True, minimum=2, maximum=_GRID_MAX)
        ]

    rays["per_dot"] = _num("rays.per_dot", rays["per_dot"])
    rays["seed"] = _num("rays.seed", rays["seed"])
    rays["chunk"] = _num("rays.chunk", rays["chunk"])
    if rays["aim_iterations"] != "auto":
        rays["aim_iterations"] = _num("rays.aim_iterations", rays["aim_iterations"])
    if rays["step_mm"] != "grid":
        rays["step_mm"] = _num("rays.step_mm", rays["step_mm"])
    rays["field"] = _choice("rays.field", rays["field"], FIELDS)
    rays["stepping"] = _choice("rays.stepping", rays["stepping"], ("fixed", "cells"))
    rays["dot_order"] = _choice("rays.dot_order", rays["dot_order"], ("pattern", "morton"))
    if rays["rays_per_group"] != "auto":
        rays["rays_per_group"] = _num("rays.rays_per_group", rays["rays_per_group"])
    if rays["rays_per_thread"] != "auto":
        rays["rays_per_thread"] = _num("rays.rays_per_thread", rays["rays_per_thread"])
    rays["block_dim"] = _num("rays.block_dim", rays["block_dim"])
    if rays["max_registers"] not in ("auto", 0, 64, 80) or isinstance(rays["max_registers"], bool):
        raise SynthbosError(
            f"rays.max_registers must be \"auto\", 0 (the compiler's choice), 64 or 80, got {rays['max_registers']!r}"
        )

    if sen["spot_diameter_px"] not in ("auto", "diffraction"):
        sen["spot_diameter_px"] = _num("sensor.spot_diameter_px", sen["spot_diameter_px"])
    sen["peak_intensity"] = _num("sensor.peak_intensity", sen["peak_intensity"])

    lim = cfg["limits"]
    if lim["memory_gb"] is not None:
        lim["memory_gb"] = _num("limits.memory_gb", lim["memory_gb"])
    if lim["ray_steps"] is not None:
        lim["ray_steps"] = _num("limits.ray_steps", lim["ray_steps"])
    lim["steps_per_ray"] = _num("limits.steps_per_ray", lim["steps_per_ray"])

    if cam["focal_length_mm"] >= tgt["distance_mm"]:
        raise SynthbosError(
            f"target.distance_mm={tgt['distance_mm']:g} must exceed camera.focal_length_mm={cam['focal_length_mm']:g}"
            " for the camera to focus on the target"
        )
    z_d, depth = vol["distance_from_target_mm"], vol["size_mm"][2]
    if z_d - depth / 2.0 <= 0.0:
        raise SynthbosError(
            f"volume.distance_from_target_mm={z_d:g} puts the volume (depth {depth:g} mm) through the target plane"
        )
    lens_front = tgt["distance_mm"] - (cam["lens_thickness_mm"] / 2.0 if cam["lens"] == "thick" else 0.0)
    if z_d + depth / 2.0 >= lens_front:
        raise SynthbosError(
            f"volume.distance_from_target_mm={z_d:g} puts the volume at or behind the lens "
            f"(target.distance_mm={tgt['distance_mm']:g}); it must lie between the target and the camera"
        )
    _check_memory_budget(cfg)
    return cfg


def _check_memory_budget(cfg):
    """Estimated host memory of the images, the dots and an analytic source's grid, before any work."""
    w, h = cfg["camera"]["pixels"]
    dots = cfg["target"]["dots_per_32px"] * w * h / 1024.0
    nbytes = w * h * _BYTES_PER_PIXEL + dots * _BYTES_PER_DOT
    vol = cfg["volume"]
    what = f"a {w} x {h} px render with about {dots:.3g} dots"
    if vol["source"] in sources.ANALYTIC:
        nx, ny, nz = vol["grid"] or sources.DEFAULT_GRID
        nbytes += float(nx) * ny * nz * checks.BYTES_PER_NODE
        what += f" and a {nx} x {ny} x {nz} volume.grid"
    checks.check_memory(nbytes, what, memory_gb=cfg["limits"]["memory_gb"])


def _merge(base, user, where=""):
    if not isinstance(user, dict):
        raise SynthbosError(f"a configuration must be a table of tables, got {user!r}")
    for table, values in user.items():
        if table not in base:
            raise SynthbosError(f"unknown configuration table [{table}]; tables are {sorted(base)}")
        if not isinstance(values, dict):
            raise SynthbosError(f"[{table}] must be a table of keys, got {values!r}")
        known = set(base[table]) | set(_OPTIONAL.get(table, {}))
        if table == "volume":
            source = values.get("source", base["volume"]["source"])
            known |= set(sources.SOURCE_KEYS.get(source, {}) if isinstance(source, str) else {})
        for key, value in values.items():
            if key not in known:
                raise SynthbosError(f"unknown configuration key {table}.{key}{where}")
            base[table][key] = value
    return base


def read_toml(path) -> dict:
    """Parse a TOML configuration file; a missing or malformed file raises SynthbosError."""
    path = Path(path)
    if path.is_dir():
        raise SynthbosError(f"configuration file {path} is a folder, not a TOML file")
    if not path.is_file():
        raise SynthbosError(f"configuration file {path} does not exist")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise SynthbosError(
            f"configuration file {path} is not UTF-8 text (byte {err.start}); save it as UTF-8"
        ) from None
    except tomllib.TOMLDecodeError as err:
        raise SynthbosError(f"configuration file {path} is not valid TOML: {err}") from None
    except OSError as err:
        raise SynthbosError(f"cannot read configuration file {path}: {os.strerror(err.errno or 0)}") from None


def merge_tables(*layers) -> dict:
    """Configuration tables merged key by key, later layers winning (a new dict; the inputs are not modified).

    Examples
    --------
    >>> merge_tables({"camera": {"f_number": 32.0}}, {"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 10}})
    {'camera': {'f_number': 32.0, 'pixels': [64, 64]}, 'rays': {'per_dot': 10}}
    """
    merged = {}
    for layer in layers:
        for table, values in copy.deepcopy(layer).items():
            if isinstance(values, dict) and isinstance(merged.get(table), dict):
                merged[table].update(values)
            else:
                merged[table] = values
    return merged


def load_config(config=None, *, setup="default") -> dict:
    """Read, merge over the defaults and validate a render configuration.

    Parameters
    ----------
    config : None, dict, str or Path
        None for the defaults; a dict of tables (partial is fine); or a path to a TOML file.
    setup : str
        A named set-up (``SETUPS``) merged over the defaults before ``config``: ``config`` changes that
        set-up instead of the default.

    Returns
    -------
    dict
        A complete, validated configuration (a new object; the input is not modified).
    """
    cfg = copy.deepcopy(DEFAULT_CONFIG)
    for table, extra in _OPTIONAL.items():
        for key, value in extra.items():
            cfg.setdefault(table, {}).setdefault(key, value)
    _merge(cfg, setup_tables(setup), f" in set-up {setup!r}")
    where = ""
    if config is None:
        user = {}
    elif isinstance(config, dict):
        user = copy.deepcopy(config)
    else:
        path = Path(config)
        user = read_toml(path)
        where = f" in {path}"
    # A new source brings its own keys: drop the default source's keys not shared with it.
    if isinstance(user, dict) and isinstance(user.get("volume"), dict) and "source" in user["volume"]:
        source = user["volume"]["source"]
        new = sources.SOURCE_KEYS.get(source, {}) if isinstance(source, str) else {}
        for key in sources.SOURCE_KEYS.get(DEFAULT_CONFIG["volume"]["source"], {}):
            if key not in new:
                cfg["volume"].pop(key, None)
    _merge(cfg, user, where)
    return _validate(cfg)


def config_to_toml(cfg: dict) -> str:
    """Serialise a configuration as TOML text (for file attributes and campaign folders)."""
    lines = []
    for table, values in cfg.items():
        lines.append(f"[{table}]")
        for key, value in values.items():
            if value is None:
                continue
            lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(value):
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")
