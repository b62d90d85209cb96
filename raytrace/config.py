"""Render configuration: TOML tables with defaults, validated key by key.

A configuration is a dict of tables, ``camera``, ``target``, ``volume``, ``rays`` and ``sensor``. The
defaults are in ``raytrace/default.toml`` (the paper's set-up). ``load_config`` accepts a path, a TOML
string path-like, or a dict (possibly partial), merges it over the defaults, checks every key and
value, and returns a new nested dict. Unknown keys and bad values raise ``SynthbosError`` naming the
key as ``table.key``.

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
  per_dot; seed; step_mm = "grid" (the smallest node spacing) or a length; chunk (rays per launch);
  aim_iterations = "auto" | n: re-aim each ray n times so that, refracted by the flow, it still
  crosses the aperture stop at its sampled point ("auto": 1 for the thick lens, whose aberrations
  make the landing point depend on where a ray crosses the stop; 0 for the ideal thin lens, which
  images every ray from a point to one point).
[sensor]
  spot_diameter_px = "auto" | "diffraction" | px ("auto": dot_diameter_px for point dots, the
  diffraction spot 2.44 lambda f# (1 + M) for disks); peak_intensity (peak I0 of a point dot's spot).
"""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path

from synthbos import SynthbosError

from . import sources
from .defaults import DEFAULT_CONFIG

__all__ = ["DEFAULT_CONFIG", "config_to_toml", "load_config", "read_toml"]



# Keys allowed beyond the defaults, with their defaults.
_OPTIONAL = {
    "target": {"min_spacing_px": None},
    "rays": {"chunk": 4_194_304, "aim_iterations": "auto"},
    "volume": {k: v for k, v in sources.COMMON_KEYS.items() if k not in DEFAULT_CONFIG["volume"]},
}


def _num(name, value, *, positive=False, nonneg=False, integer=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SynthbosError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise SynthbosError(f"{name} must be finite, got {value!r}")
    if integer and int(value) != value:
        raise SynthbosError(f"{name} must be a whole number, got {value!r}")
    if positive and value <= 0:
        raise SynthbosError(f"{name} must be > 0, got {value!r}")
    if nonneg and value < 0:
        raise SynthbosError(f"{name} must be >= 0, got {value!r}")
    return int(value) if integer else float(value)


def _choice(name, value, options):
    if value not in options:
        raise SynthbosError(f"{name} must be one of {list(options)}, got {value!r}")
    return value


def _pair(name, value, *, integer=False):
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise SynthbosError(f"{name} must be a list of two numbers, got {value!r}")
    return [_num(f"{name}[{i}]", v, positive=True, integer=integer) for i, v in enumerate(value)]


def _validate(cfg):
    cam, tgt, vol, rays, sen = (cfg[k] for k in ("camera", "target", "volume", "rays", "sensor"))
    cam["pixels"] = _pair("camera.pixels", cam["pixels"], integer=True)
    for key in ("pixel_pitch_um", "focal_length_mm", "f_number", "wavelength_nm", "lens_thickness_mm"):
        cam[key] = _num(f"camera.{key}", cam[key], positive=True)
    cam["glass_index"] = _num("camera.glass_index", cam["glass_index"], positive=True)
    if cam["glass_index"] <= 1.0:
        raise SynthbosError(f"camera.glass_index must be > 1, got {cam['glass_index']!r}")
    _choice("camera.lens", cam["lens"], ("thin", "thick"))

    tgt["distance_mm"] = _num("target.distance_mm", tgt["distance_mm"], positive=True)
    _choice("target.pattern", tgt["pattern"], ("grid", "random"))
    tgt["dots_per_32px"] = _num("target.dots_per_32px", tgt["dots_per_32px"], positive=True)
    tgt["dot_diameter_px"] = _num("target.dot_diameter_px", tgt["dot_diameter_px"], positive=True)
    _choice("target.dot_model", tgt["dot_model"], ("point", "disk"))
    tgt["seed"] = _num("target.seed", tgt["seed"], nonneg=True, integer=True)
    if tgt["min_spacing_px"] is not None:
        tgt["min_spacing_px"] = _num("target.min_spacing_px", tgt["min_spacing_px"], nonneg=True)

    vol["distance_from_target_mm"] = _num(
        "volume.distance_from_target_mm", vol["distance_from_target_mm"], positive=True
    )
    if not isinstance(vol["size_mm"], (list, tuple)) or len(vol["size_mm"]) != 3:
        raise SynthbosError(f"volume.size_mm must be a list of three numbers, got {vol['size_mm']!r}")
    vol["size_mm"] = [_num(f"volume.size_mm[{i}]", v, positive=True) for i, v in enumerate(vol["size_mm"])]
    if not isinstance(vol["offset_mm"], (list, tuple)) or len(vol["offset_mm"]) != 2:
        raise SynthbosError(f"volume.offset_mm must be a list of two numbers, got {vol['offset_mm']!r}")
    vol["offset_mm"] = [_num(f"volume.offset_mm[{i}]", v) for i, v in enumerate(vol["offset_mm"])]
    source = _choice("volume.source", vol["source"], tuple(sources.SOURCE_KEYS))
    for key, default in sources.SOURCE_KEYS[source].items():
        if key not in vol:
            if default is None:
                raise SynthbosError(f"volume.{key} is required for source {source!r}")
            vol[key] = copy.deepcopy(default)
    vol["gladstone_dale_m3_per_kg"] = _num(
        "volume.gladstone_dale_m3_per_kg", vol["gladstone_dale_m3_per_kg"], nonneg=True
    )
    vol["density_scale_kg_m3"] = _num("volume.density_scale_kg_m3", vol["density_scale_kg_m3"], positive=True)

    rays["per_dot"] = _num("rays.per_dot", rays["per_dot"], positive=True, integer=True)
    rays["seed"] = _num("rays.seed", rays["seed"], nonneg=True, integer=True)
    rays["chunk"] = _num("rays.chunk", rays["chunk"], positive=True, integer=True)
    if rays["aim_iterations"] != "auto":
        rays["aim_iterations"] = _num("rays.aim_iterations", rays["aim_iterations"], nonneg=True, integer=True)
    if rays["step_mm"] != "grid":
        rays["step_mm"] = _num("rays.step_mm", rays["step_mm"], positive=True)

    if sen["spot_diameter_px"] not in ("auto", "diffraction"):
        sen["spot_diameter_px"] = _num("sensor.spot_diameter_px", sen["spot_diameter_px"], positive=True)
    sen["peak_intensity"] = _num("sensor.peak_intensity", sen["peak_intensity"], positive=True)

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
    return cfg


def _merge(base, user, where=""):
    for table, values in user.items():
        if table not in base:
            raise SynthbosError(f"unknown configuration table [{table}]; tables are {sorted(base)}")
        if not isinstance(values, dict):
            raise SynthbosError(f"[{table}] must be a table of keys, got {values!r}")
        known = set(base[table]) | set(_OPTIONAL.get(table, {}))
        if table == "volume":
            source = values.get("source", base["volume"]["source"])
            known |= set(sources.SOURCE_KEYS.get(source, {}))
        for key, value in values.items():
            if key not in known:
                raise SynthbosError(f"unknown configuration key {table}.{key}{where}")
            base[table][key] = value
    return base


def read_toml(path) -> dict:
    """Parse a TOML configuration file; a missing or malformed file raises SynthbosError."""
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"configuration file {path} does not exist")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise SynthbosError(f"configuration file {path} is not valid TOML: {err}") from None


def load_config(config=None) -> dict:
    """Read, merge over the defaults and validate a render configuration.

    Parameters
    ----------
    config : None, dict, str or Path
        None for the defaults; a dict of tables (partial is fine); or a path to a TOML file.

    Returns
    -------
    dict
        A complete, validated configuration (a new object; the input is not modified).
    """
    cfg = copy.deepcopy(DEFAULT_CONFIG)
    for table, extra in _OPTIONAL.items():
        for key, value in extra.items():
            cfg[table].setdefault(key, value)
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
    if "volume" in user and "source" in user["volume"]:
        new = sources.SOURCE_KEYS.get(user["volume"]["source"], {})
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
