"""``synthbos process``: run a processing method on a pair file or on two camera images.

The library functions ``correlation.correlate_pair`` and ``tracking.track_pair`` do the work; this
module reads the inputs (pair files, 8/16-bit TIFF or PNG images, a CSV of predicted dot positions),
calls them, and writes the result file atomically.

Result files (HDF5)
-------------------
A grid method (``correlation``): ``/x``, ``/y`` (window centres, px), ``/u``, ``/v`` (px), ``/flags``,
``/peak_ratio``; the settings as root attributes.
A dots method (``tracking`` / ``tracking-cc``): ``/dots/x``, ``/dots/y`` (reference positions), ``/dots/u``,
``/dots/v`` (by centroid difference for ``tracking``, with correlation correction for ``tracking-cc``),
``/dots/status``, plus every other column of the tracking table under ``/dots/`` (the centroid-difference
displacement as ``u_centroid``, ``v_centroid``); settings as attributes.

Every dataset carries ``units`` and ``description`` attributes (``RESULT_DATASETS``); the bit-flag
datasets (``/flags``, ``/dots/status``) also carry ``flag_bits``, a JSON object mapping each bit's value
to its name and meaning, generated from the documentation of the flags in ``correlation`` and
``tracking`` (``FLAG_BITS``).
"""

from __future__ import annotations

import csv
import enum
import inspect
import json
import re
from pathlib import Path

import h5py
import imageio.v3 as iio
import numpy as np
import tifffile
from synthbos.correlation import multigrid
from synthbos.raytrace.pairfile import describe_datasets
from synthbos.tracking import DotStatus

from synthbos import SynthbosError, atomic_hdf5

from .registry import GRID, MethodResult, get_method

__all__ = ["FLAG_BITS", "RESULT_DATASETS", "flag_bits", "load_image", "read_dots_csv", "run_method", "write_result"]


def _int_flag_bits(flag_class: type[enum.IntFlag]) -> dict[int, tuple[str, str]]:
    """Bit -> (name, meaning) of an IntFlag whose docstring lists ``NAME[, NAME]`` lines, each followed
    by its indented meaning (numpydoc style)."""
    meaning, names = {}, []
    for line in inspect.cleandoc(flag_class.__doc__ or "").splitlines():
        heads = [h.strip() for h in line.split(",")]
        if line and not line[0].isspace() and all(h in flag_class.__members__ for h in heads):
            names = heads
            continue
        if names and line.startswith((" ", "\t")):
            for n in names:
                meaning[n] = f"{meaning.get(n, '')} {line.strip()}".strip()
        elif not line.strip():
            continue
        else:
            names = []
    return {int(m.value): (name, meaning.get(name, "")) for name, m in flag_class.__members__.items()}


def _constant_flag_bits(module, prefix: str = "FLAG_") -> dict[int, tuple[str, str]]:
    """Bit -> (name, meaning) of a module's ``FLAG_X = bit`` constants, each documented by a ``#:`` comment."""
    source = inspect.getsource(module)
    bits = {}
    for doc, name, value in re.findall(rf"^#: *(.*)\n({prefix}\w+) *= *(\d+)", source, flags=re.M):
        bits[int(value)] = (name, doc.strip())
    return bits


def flag_bits(bits: dict[int, tuple[str, str]]) -> str:
    """The ``flag_bits`` attribute: JSON ``{"<bit>": {"name": ..., "description": ...}}``."""
    return json.dumps({str(b): {"name": n, "description": d} for b, (n, d) in sorted(bits.items())})


def _module_flag_bits(module) -> dict[int, tuple[str, str]]:
    """A module's flags: its documented ``FLAG_X`` constants, else the members of an IntFlag it defines."""
    bits = _constant_flag_bits(module)
    if not bits:
        for value in vars(module).values():
            if isinstance(value, type) and issubclass(value, enum.IntFlag) and value.__module__ == module.__name__:
                bits.update(_int_flag_bits(value))
    return bits


# Bit-flag columns of the methods' tables, described from their own documentation.
FLAG_BITS = {
    "flags": _module_flag_bits(multigrid),
    "status": _int_flag_bits(DotStatus),
}

# The result file's datasets: path -> (units, description); written on each dataset as attributes.
_UV = "the method's measured displacement from the reference to the gradient image"
RESULT_DATASETS = {
    "x": ("px", "window centre x (column; pixel centres at integers)"),
    "y": ("px", "window centre y (row)"),
    "u": ("px", f"x component of {_UV}; replaced by the local median where flagged"),
    "v": ("px", f"y component of {_UV}; replaced by the local median where flagged"),
    "flags": ("1", "bit flags of each window, 0 = valid (bits in the attribute flag_bits)"),
    "peak_ratio": ("1", "correlation peak ratio (highest over second-highest peak) of the last pass"),
    "dots/x": ("px", "dot position x (column) in the reference image"),
    "dots/y": ("px", "dot position y (row) in the reference image"),
    "dots/u": ("px", f"x component of {_UV} (see the root attribute method)"),
    "dots/v": ("px", f"y component of {_UV} (see the root attribute method)"),
    "dots/u_centroid": ("px", "x displacement by centroid difference"),
    "dots/v_centroid": ("px", "y displacement by centroid difference"),
    "dots/u_cc": ("px", "x displacement with the correlation correction"),
    "dots/v_cc": ("px", "y displacement with the correlation correction"),
    "dots/x_gradient": ("px", "dot position x (column) in the gradient image"),
    "dots/y_gradient": ("px", "dot position y (row) in the gradient image"),
    "dots/diameter": ("px", "estimated dot diameter"),
    "dots/peak": ("a.u.", "dot peak intensity in the reference image (image units)"),
    "dots/status": ("1", "bit flags of each dot (bits in the attribute flag_bits); MATCHED marks a valid dot"),
    "dots/iteration": ("1", "identification iteration that found the dot in the reference image"),
    "dots/iteration_gradient": ("1", "identification iteration that found the dot in the gradient image"),
}


def load_image(path) -> np.ndarray:
    """Read one camera image (TIFF through tifffile, PNG and others through imageio) as float64."""
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"image {path} does not exist")
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            img = tifffile.imread(path)
        else:
            img = iio.imread(path)
    except Exception as err:  # the readers raise many types for unreadable files
        raise SynthbosError(f"cannot read image {path}: {err}") from None
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[-1] in (3, 4):  # colour: luminance of the RGB channels
        img = img[..., :3].astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    if img.ndim != 2:
        raise SynthbosError(f"image {path} must be a single 2-D frame, got shape {img.shape}")
    return img.astype(np.float64)


def read_dots_csv(path) -> np.ndarray:
    """Predicted reference-image dot positions from a CSV with a header line ``x,y`` (px)."""
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"dots file {path} does not exist")
    try:
        with path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except UnicodeDecodeError as err:
        raise SynthbosError(f"dots file {path} is not UTF-8 text (byte {err.start}); save it as UTF-8") from None
    except (OSError, csv.Error) as err:
        raise SynthbosError(f"cannot read dots file {path}: {err}") from None
    if not rows or [c.strip().lower() for c in rows[0]] != ["x", "y"]:
        raise SynthbosError(f"dots file {path} must start with the header line 'x,y'")
    for line, row in enumerate(rows[1:], start=2):
        if row and len(row) != 2:
            raise SynthbosError(f"dots file {path}, line {line}: expected two values x,y, got {len(row)}")
    try:
        xy = np.array([[float(a), float(b)] for a, b in (r for r in rows[1:] if r)], dtype=np.float64)
    except ValueError as err:  # a value that is not a number
        raise SynthbosError(f"dots file {path}: {err}") from None
    if xy.size == 0 or not np.isfinite(xy).all():
        raise SynthbosError(f"dots file {path} has no dots or non-finite positions")
    return xy.reshape(-1, 2)


def run_method(method, reference, gradient, *, prior_xy=None, settings=None, device=None) -> MethodResult:
    """Run the registered method ``method`` on an image pair and return its ``MethodResult``."""
    return get_method(method).run(reference, gradient, prior_xy=prior_xy, settings=settings, device=device)


def write_result(path, result: MethodResult, *, extra_attrs=None) -> Path:
    """Write a result file atomically (layout in the module docstring)."""
    path = Path(path)
    with atomic_hdf5(path) as f:
        if get_method(result.method).kind == GRID:
            for name in ("x", "y", "u", "v", "flags", "peak_ratio"):
                f.create_dataset(name, data=np.asarray(result.table[name]))
        else:
            g = f.create_group("dots")
            g.create_dataset("x", data=result.xy[:, 0])
            g.create_dataset("y", data=result.xy[:, 1])
            g.create_dataset("u", data=result.uv[:, 0])
            g.create_dataset("v", data=result.uv[:, 1])
            for name, values in result.table.items():
                if name in ("u", "v"):  # the centroid-difference displacement, kept under its own name
                    g.create_dataset(f"{name}_centroid", data=np.asarray(values))
                elif name not in ("x", "y"):
                    g.create_dataset(name, data=np.asarray(values))
        f.attrs["method"] = result.method
        f.attrs["settings"] = json.dumps(result.settings, default=str)
        for key, value in (extra_attrs or {}).items():
            f.attrs[key] = value
        _describe(f)
    return path


def _describe(f) -> None:
    """Units, description and flag bits on every dataset of a result file (a column the schema does not
    know yet gets a generic description rather than none)."""
    describe_datasets(f, RESULT_DATASETS)
    for name, obj in _datasets(f):
        column = name.rpartition("/")[2]
        if column in FLAG_BITS:
            obj.attrs["flag_bits"] = flag_bits(FLAG_BITS[column])
        if "units" not in obj.attrs:
            obj.attrs["units"] = ""
            obj.attrs["description"] = f"column {column!r} of the {f.attrs['method']} table (see its documentation)"


def _datasets(group, prefix=""):
    for key, obj in group.items():
        if isinstance(obj, h5py.Dataset):
            yield f"{prefix}{key}", obj
        else:
            yield from _datasets(obj, f"{prefix}{key}/")
