"""MkDocs hooks of the synthbos site (``hooks:`` in mkdocs.yml).

Two jobs:

- **The API reference finds the subpackages.** In the repository ``raytrace/``, ``tracking/`` ... sit at
  the root and install as ``synthbos.raytrace``, ``synthbos.tracking`` ... (setuptools' package-dir
  mapping). mkdocstrings reads sources without importing them, so before the build this hook lays out
  the installed shape of the package as a tree of symbolic links in a temporary folder (``synthbos/``
  with each mapped folder inside it) and puts that folder first on the Python handler's search path.
- **The configuration reference is written from the code.** A line ``<!-- config-table: NAME -->`` in a
  page becomes a table of every key or setting with its default, unit and allowed range, read from
  ``raytrace.config`` (the render configuration), ``raytrace.sources`` (the density sources),
  ``tracking.TrackingSettings``, ``correlation.CorrelationSettings`` and
  ``benchmarks.process.ImageOptions`` (their numpydoc docstrings give the descriptions), so the page
  cannot drift from the code. ``tests/test_docs.py`` checks that every key has a description.
  Likewise ``<!-- module-table: FOLDER -->`` lists a package folder's modules with their docstrings.
"""

from __future__ import annotations

import ast
import atexit
import dataclasses
import re
import shutil
import tempfile
import tomllib
from pathlib import Path

import mkdocs.plugins

REPO = Path(__file__).resolve().parent.parent
MARKER = re.compile(r"^<!-- (config|module)-table: ([a-z_]+) -->$", re.MULTILINE)

# What each key of the render configuration means (the defaults, ranges and units come from the code).
RENDER_KEYS = {
    "camera.pixels": "sensor size [W, H]",
    "camera.pixel_pitch_um": "pixel pitch",
    "camera.focal_length_mm": "focal length f of the lens",
    "camera.f_number": "f-number f/D: sets the aperture, hence the cone of rays from each dot",
    "camera.lens": '"thin" (ideal thin lens) or "thick" (a biconvex spherical lens, Snell\'s law at both surfaces)',
    "camera.wavelength_nm": "wavelength of the diffraction spot 2.44 lambda f# (1 + M)",
    "camera.glass_index": "refractive index of the thick lens",
    "camera.lens_thickness_mm": "centre thickness of the thick lens",
    "target.distance_mm": "target to lens, Z_T (magnification M = f / (Z_T - f))",
    "target.pattern": '"random" or "grid" dot pattern',
    "target.dots_per_32px": "dot density in the image plane, dots per 32 x 32 px",
    "target.dot_diameter_px": "dot image diameter (e^-2)",
    "target.dot_model": '"point" (a point source) or "disk" (a disk of physical diameter dot_diameter_px pitch / M)',
    "target.seed": "seed of the random pattern",
    "target.min_spacing_px": "random pattern: least centre distance (default: dot_diameter_px)",
    "volume.source": "density source (table below)",
    "volume.snapshot": 'embedded snapshot 0..4 (source "slice")',
    "volume.distance_from_target_mm": "Z_D, target to the volume's mid-plane",
    "volume.size_mm": "volume size [x, y, z]",
    "volume.offset_mm": "the volume's centre off the optical axis [x, y]",
    "volume.gladstone_dale_m3_per_kg": "Gladstone-Dale constant K, n = 1 + K rho",
    "volume.density_scale_kg_m3": "scale of normalised data (slice snapshots, normalised files)",
    "volume.grid": "[nx, ny, nz] nodes of an analytic source (default [64, 64, 16]); data sources take the data's",
    "rays.per_dot": "rays traced from each dot through the aperture",
    "rays.seed": "seed of the aperture samples (Warp's 32-bit rand_init)",
    "rays.step_mm": '"grid" (the smallest node spacing) or a length: the truths\' sampling, and the fixed step',
    "rays.chunk": "rays per kernel launch (bounds device memory)",
    "rays.aim_iterations": '"auto" (1 for the thick lens, 0 for the thin) or n re-aims so a bent ray still crosses '
                           "the stop at its sampled point",
    "rays.field": "how the volume is stored and read on the device (exact: float32, float32_vec, texture_nearest)",
    "rays.dot_order": '"morton" or "pattern": the order in which threads take the dots (never changes a bit)',
    "rays.rays_per_group": "consecutive threads take this many chunks of rays of one dot; \"auto\": 8 for planar "
                           "media and straight rays, 64 through 3-D media (never changes a bit)",
    "rays.rays_per_thread": "rays of one dot each thread traces, adding their sums once; \"auto\": 8 for planar media "
                            "and straight rays, 1 through 3-D media (never changes a bit)",
    "rays.block_dim": "threads per CUDA block (never changes a bit)",
    "rays.max_registers": "\"auto\" (64, or 80 through a 3-D medium), 0 (the compiler's choice), 64 or 80 registers "
                          "per CUDA thread (never changes a bit)",
    "rays.stepping": '"cells" (RK4 steps end at node planes) or "fixed" (equal steps of step_mm)',
    "sensor.spot_diameter_px": '"auto" (dot diameter for point dots, diffraction for disks), "diffraction", or px',
    "sensor.peak_intensity": "peak I0 of a point dot's spot",
    "limits.memory_gb": "estimated host memory a render may take (default: 80 % of this machine's, at most 64)",
    "limits.ray_steps": "rays x RK4 steps of a render (default 1e10 on the CPU, about 10 min; 1e12 on a GPU)",
    "limits.steps_per_ray": "RK4 steps of one ray across the volume's depth",
}

# What each key of the density sources means (``[volume]`` keys beside ``source``).
SOURCE_KEYS = {
    "density_kg_m3": "ambient density rho0",
    "gradient_kg_m4": "gradient [gx, gy] or [gx, gy, gz]; rho0 at the centre",
    "amplitude_kg_m3": "amplitude a",
    "sigma_mm": "Gaussian width s",
    "centre_mm": "centre c of the blob",
    "jump_kg_m3": "density jump J across the interface",
    "position_mm": "a point of the interface",
    "normal": "interface normal (2 or 3 components), towards rho0 + J",
    "thickness_mm": "maximum-slope thickness J / max|d rho/ds|",
    "wavelength_mm": "wavelength lambda",
    "direction": "wave direction (2 or 3 components)",
    "phase_deg": "phase phi",
    "snapshot": "embedded snapshot 0..4",
    "path": "data file (slice: another snapshots file; file: required)",
    "format": '"auto" (from the extension), jhtdb, nrrd, npy, npz or hdf5',
    "dataset": "dataset name inside an HDF5 or npz file",
    "slice_index": '"none" or the index of a 2-D slice along axis',
    "axis": "axis of slice_index",
    "index_range": '"all" or [[x0, x1], [y0, y1], [z0, z1]]',
    "spacing_mm": '"auto" (the data span size_mm) or the node spacing (one number or per axis)',
    "normalised": '"auto" (true for jhtdb), true (times density_scale_kg_m3) or false (kg/m^3)',
    "axis_order": '"auto" ("zyx" / "yx") or the physical axis of each stored axis, e.g. "xyz"',
}

UNITS = [  # key suffix -> unit, longest first
    ("_m3_per_kg", "m³/kg"), ("_kg_m3", "kg/m³"), ("_kg_m4", "kg/m⁴"), ("_mm", "mm"), ("_um", "µm"),
    ("_nm", "nm"), ("_px", "px"), ("_deg", "deg"), ("_gb", "GB"), ("32px", "per 32 × 32 px"),
]
NAMED_UNITS = {"pixels": "px", "per_dot": "rays", "chunk": "rays", "ray_steps": "ray-steps",
               "steps_per_ray": "steps", "block_dim": "threads", "max_registers": "registers",
               "rays_per_group": "chunks", "rays_per_thread": "rays", "peak_intensity": "image units"}


def unit_of(key: str) -> str:
    """The unit a key's name spells (``size_mm`` -> mm), or "" where it has none."""
    name = key.rsplit(".", 1)[-1]
    for suffix, unit in UNITS:
        if name.endswith(suffix):
            return unit
    return NAMED_UNITS.get(name, "")


def _number(x) -> str:
    """A bound or default in short form; 2^n - 1 for the seeds' limits."""
    if isinstance(x, int) and x > 10**6 and (x + 1) & x == 0:
        return f"2^{(x + 1).bit_length() - 1} - 1"
    return f"{x:g}"


def _value(value) -> str:
    if value is None:
        return "unset"
    if isinstance(value, str):
        return f'`"{value}"`'
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, (list, tuple)):
        return "`[" + ", ".join(_number(v) if isinstance(v, float) else str(v) for v in value) + "]`"
    return f"`{_number(value)}`" if isinstance(value, float) else f"`{value}`"


def _range(bounds: dict | None) -> str:
    """A range entry of ``_RANGES``/``TRACKING_RANGES`` in words: [a, b], (a, b] ..."""
    if not bounds:
        return ""
    low = ("[", bounds["minimum"]) if "minimum" in bounds else ("(", bounds["above"]) if "above" in bounds else None
    high = (bounds["maximum"], "]") if "maximum" in bounds else (bounds["below"], ")") if "below" in bounds else None
    kind = "integer " if bounds.get("integer") else ""
    if low is None and high is None:
        return "finite" + (" or unset" if bounds.get("optional") else "")
    lo = f"{low[0]}{_number(low[1])}" if low else "(-inf"
    hi = f"{_number(high[0])}{high[1]}" if high else "inf)"
    return f"{kind}{lo}, {hi}"


def _cell(text) -> str:
    """A table cell: pipes escaped outside code spans (inside them the table parser leaves them alone)."""
    parts = str(text).split("`")
    return "`".join(part if i % 2 else part.replace("|", "\\|") for i, part in enumerate(parts))


def _row(*cells) -> str:
    return "| " + " | ".join(_cell(c) for c in cells) + " |"


def _vector_ranges(config) -> dict:
    """Bounds of the render keys that are vectors, checked in ``raytrace.config._validate``."""
    return {"camera.pixels": {"integer": True, "above": 0, "maximum": config._PIXELS_MAX},
            "volume.grid": {"integer": True, "minimum": 2, "maximum": config._GRID_MAX},
            "volume.size_mm": {"above": 0.0, "maximum": 1.0e6},
            "volume.offset_mm": {"minimum": -1.0e6, "maximum": 1.0e6}}


def render_table() -> str:
    """Every key of the render configuration (``raytrace.config``), table by table."""
    from synthbos.raytrace import config

    lines = [_row("key", "default", "unit", "allowed", "meaning"), _row(*["---"] * 5)]
    tables = {t: {**config.DEFAULT_CONFIG.get(t, {}), **config._OPTIONAL.get(t, {})}
              for t in ("camera", "target", "volume", "rays", "sensor", "limits")}
    for table, keys in tables.items():
        for key, default in keys.items():
            name = f"{table}.{key}"
            bounds = config._RANGES.get(name) or _vector_ranges(config).get(name)
            lines.append(_row(f"`[{table}]` `{key}`", _value(default), unit_of(key), _range(bounds),
                              RENDER_KEYS.get(name, "")))
    return "\n".join(lines)


def sources_table() -> str:
    """The density sources and each one's own ``[volume]`` keys with defaults (None: required)."""
    from synthbos.raytrace import sources

    lines = [_row("source", "key", "default", "unit", "meaning"), _row(*["---"] * 5)]
    for source, keys in sources.SOURCE_KEYS.items():
        for key, default in keys.items():
            shown = "required" if default is None else _value(default)
            lines.append(_row(f"`{source}`", f"`{key}`", shown, unit_of(key), SOURCE_KEYS.get(key, "")))
    return "\n".join(lines)


def docstring_fields(cls) -> dict[str, tuple[str, str]]:
    """Name -> (type, first sentence) from a numpydoc Attributes or Parameters section."""
    text = (cls.__doc__ or "").expandtabs()
    fields: dict[str, list] = {}
    current = None
    for line in text.splitlines():
        head = re.match(r"^    ([A-Za-z_][\w, ]*) : (.+)$", line)
        if head:
            current = [head.group(2).strip(), []]
            for name in head.group(1).split(","):
                fields[name.strip()] = current
        elif current is not None and line.startswith("        "):
            current[1].append(line.strip())
        elif line.strip() and not line.startswith("        "):
            current = None
    return {k: (kind, _first_sentence(" ".join(words))) for k, (kind, words) in fields.items()}


def _first_sentence(text: str) -> str:
    """The first sentence (up to a full stop before a capital or a quote), without numpydoc's '...'."""
    text = text.strip().removeprefix("...").removesuffix("...").strip()
    match = re.match(r"(.+?)\.(\s+[A-Z(\"`]|$)", text)
    return _inline((match.group(1) if match else text).strip())


def _inline(text: str) -> str:
    """reStructuredText roles and double backquotes as Markdown code."""
    return re.sub(r":(mod|func|class|meth|attr):`([^`]+)`", r"`\2`", text.replace("``", "`"))


def settings_table(cls, ranges: dict) -> str:
    """Every field of a settings dataclass: default, type, allowed range and the docstring's first sentence."""
    described = docstring_fields(cls)
    lines = [_row("setting", "default", "type", "allowed", "meaning"), _row(*["---"] * 5)]
    for field in dataclasses.fields(cls):
        kind, text = described.get(field.name, ("", ""))
        default = field.default_factory() if field.default is dataclasses.MISSING else field.default
        lines.append(_row(f"`{field.name}`", _value(default), kind.replace("``", "`"),
                          _range(ranges.get(field.name)), text))
    return "\n".join(lines)


def _tracking() -> str:
    from synthbos.tracking.settings import TRACKING_RANGES, TrackingSettings

    return settings_table(TrackingSettings, TRACKING_RANGES)


def _correlation() -> str:
    from synthbos.correlation.multigrid import CORRELATION_RANGES, CorrelationSettings

    return settings_table(CorrelationSettings, CORRELATION_RANGES)


def _image() -> str:
    from synthbos.benchmarks.process import ImageOptions

    return settings_table(ImageOptions, {})


TABLES = {"render": render_table, "sources": sources_table, "tracking": _tracking,
          "correlation": _correlation, "image": _image}


def undocumented() -> list[str]:
    """Keys and settings the tables above would show without a description (tests/test_docs.py)."""
    from synthbos.benchmarks.process import ImageOptions
    from synthbos.correlation.multigrid import CorrelationSettings
    from synthbos.raytrace import config, sources
    from synthbos.tracking.settings import TrackingSettings

    missing = [f"{t}.{k}" for t in ("camera", "target", "volume", "rays", "sensor", "limits")
               for k in {**config.DEFAULT_CONFIG.get(t, {}), **config._OPTIONAL.get(t, {})}
               if f"{t}.{k}" not in RENDER_KEYS]
    missing += [f"volume.{k} ({s})" for s, keys in sources.SOURCE_KEYS.items() for k in keys if k not in SOURCE_KEYS]
    for cls in (TrackingSettings, CorrelationSettings, ImageOptions):
        described = docstring_fields(cls)
        missing += [f"{cls.__name__}.{f.name}" for f in dataclasses.fields(cls)
                    if not described.get(f.name, ("", ""))[1]]
    return missing


def module_table(folder: str) -> str:
    """Each module of a package folder with the first paragraph of its docstring (read, not imported)."""
    lines = [_row("module", "what it does"), _row("---", "---")]
    for path in sorted((REPO / folder).glob("*.py")):
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
        first = " ".join(doc.split("\n\n")[0].split())
        lines.append(_row(f"`{path.name}`", _inline(first)))
    return "\n".join(lines)


def on_page_markdown(markdown, page, config, files):
    """Replace each ``<!-- config-table: NAME -->`` or ``<!-- module-table: FOLDER -->`` line by its table."""
    def table(match):
        kind, name = match.groups()
        if kind == "module":
            if not (REPO / name).is_dir():
                raise ValueError(f"{page.file.src_path}: module-table {name!r} is not a folder of the repository")
            return module_table(name)
        if name not in TABLES:
            raise ValueError(f"{page.file.src_path}: unknown config-table {name!r}; known: {sorted(TABLES)}")
        return TABLES[name]()

    return MARKER.sub(table, markdown)


def package_tree(dest: Path) -> Path:
    """Lay out the installed shape of ``synthbos`` under ``dest`` as symbolic links into the repository."""
    package_dir = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    for package, folder in sorted(package_dir.items()):
        target = dest.joinpath(*package.split("."))
        if "." not in package:
            target.mkdir(parents=True)
            for item in (REPO / folder).iterdir():
                if item.name != "__pycache__":
                    (target / item.name).symlink_to(item)
        else:
            target.symlink_to(REPO / folder, target_is_directory=True)
    return dest


@mkdocs.plugins.event_priority(100)  # before mkdocstrings reads its handler options
def on_config(config):
    """Put the package tree first on the mkdocstrings Python handler's search path."""
    tmp = Path(tempfile.mkdtemp(prefix="synthbos-docs-"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)
    package_tree(tmp)
    handlers = config.plugins["mkdocstrings"].config.handlers
    handlers.setdefault("python", {}).setdefault("paths", []).insert(0, str(tmp))
    return config
