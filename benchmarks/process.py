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
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import numpy as np

from synthbos import SynthbosError, atomic_output

from .registry import GRID, MethodResult, get_method

__all__ = ["load_image", "read_dots_csv", "run_method", "write_result"]


def load_image(path) -> np.ndarray:
    """Read one camera image (TIFF through tifffile, PNG and others through imageio) as float64."""
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"image {path} does not exist")
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            img = tifffile.imread(path)
        else:
            import imageio.v3 as iio

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
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows or [c.strip().lower() for c in rows[0]] != ["x", "y"]:
        raise SynthbosError(f"dots file {path} must start with the header line 'x,y'")
    try:
        xy = np.array([[float(a), float(b)] for a, b in (r for r in rows[1:] if r)], dtype=np.float64)
    except ValueError as err:
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
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
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
    return path
