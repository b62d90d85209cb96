"""``synthbos process``: run a processing method on a pair file or on two camera images.

The library functions ``correlation.correlate_pair`` and ``tracking.track_pair`` do the work; this
module reads the inputs (pair files, camera images, a mask image, a CSV of predicted dot positions, a
process configuration), prepares the images (luminance, inversion of dark-dot images), calls the
registered method, and writes the result file atomically.

Process settings (``--settings PROCESS.toml``; formerly ``--config``, still accepted)
-----------------------------------------------------------------------------------
One table per settings class of the method registry, whose keys are that class's fields (unknown
keys are refused, values checked by the class), and an ``[image]`` table::

    [correlation]              # correlation.CorrelationSettings
    window_sizes = [64, 32, 16]
    overlaps = 0.5

    [tracking]                 # tracking.TrackingSettings
    diameter = 4.0
    max_displacement = 6.0

    [setup]                    # optional: the camera pair's set-up (benchmarks.setup_file), recorded in
    z_d_mm = 250.0             # the result so that `synthbos integrate` needs no other
    ...

    [image]
    mask = "mask.png"          # relative to the configuration file
    mask_excludes = "dark"     # "dark": black mask pixels are left out (white = measured);
                               # "bright": white mask pixels are left out
    invert = "auto"            # "auto" | true | false: make the dots bright on a dark background

Command-line flags override the file.

Result files (HDF5)
-------------------
A grid method (``correlation``): ``/x``, ``/y`` (window centres, px), ``/u``, ``/v`` (px), ``/flags``,
``/peak_ratio``, ``/correlation``; any other grid method ``/x``, ``/y``, ``/u``, ``/v`` and its own columns.
A dense method (``optical-flow``): the same layout with one vector per pixel (``/x``, ``/y`` the pixel
centres, all of the image's shape).
A dots method (``tracking`` / ``tracking-cc``): ``/dots/x``, ``/dots/y`` (reference positions), ``/dots/u``,
``/dots/v`` (by centroid difference for ``tracking``, with correlation correction for ``tracking-cc``),
``/dots/status``, ``/dots/masked``, plus every other column of the tracking table under ``/dots/`` (the
centroid-difference displacement as ``u_centroid``, ``v_centroid``), among them ``/dots/dot_id``: the
prior's row each dot belongs to (the pair file's dot index for a pair prior, the ``--dots`` CSV's data row,
0-based; -1 without a prior).
Named dimensions (HDF5 dimension scales, for xarray and netCDF readers): ``/grid_y``, ``/grid_x`` (the
window centres of each grid row and column, px) on the 2-D datasets of a grid or dense result;
``/dots/dot`` (the row index) on every ``/dots`` column.
Root attributes: ``method``, ``kind``, ``settings`` (JSON of the settings used), ``image`` (JSON of the
image options used: mask, its polarity, whether the images were inverted and why), ``counts`` (JSON:
measured, replaced, failed, masked, total), ``config`` (the configuration file's text, when one was
given), ``input``, ``seconds``, ``device`` (the Warp device that processed, from the command line),
``setup`` (JSON: the set-up the images were taken with, ``integrate.Geometry``'s fields and ``source``;
from the pair file, or from ``--setup-file`` / the configuration's ``[setup]``; absent when unknown).
Both: ``valid`` (``/valid`` or ``/dots/valid``), the vectors the method counts as measured and unflagged;
from the command line also ``image_shape`` (H, W) and, for a pair file, its ``magnification``.
``read_result`` reads a result file back.

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
from dataclasses import asdict, dataclass
from pathlib import Path

import h5py
import imageio.v3 as iio
import numpy as np
import tifffile
from synthbos.correlation import flags as correlation_flags
from synthbos.raytrace.pairfile import describe_datasets, is_scale, name_dimensions
from synthbos.tracking import DotStatus

from synthbos import SynthbosError, atomic_hdf5
from synthbos.values import cut, shorten

from .registry import DENSE, DOTS, GRID, METHODS, MethodResult, get_method

__all__ = [
    "FLAG_BITS",
    "RESULT_DATASETS",
    "SHORT_FLAGS",
    "ImageOptions",
    "apply_invert",
    "check_prior",
    "check_result_file",
    "decide_invert",
    "flag_bits",
    "image_options_dict",
    "load_image",
    "load_mask",
    "process_pair",
    "process_settings",
    "process_tables",
    "read_dots_csv",
    "read_process_config",
    "read_result",
    "result_setup",
    "run_method",
    "write_result",
]

#: Rec. 709 luminance weights of linear R, G, B.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])

MASK_POLARITIES = ("dark", "bright")
#: Longest path a setting may name (Linux's PATH_MAX).
MAX_PATH = 4096
#: Smallest camera image processed (px along each side).
MIN_IMAGE_PX = 8
#: Prior positions closer than this (px) are the same dot twice.
DUPLICATE_PX = 0.5


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
    "flags": _module_flag_bits(correlation_flags),
    "status": _int_flag_bits(DotStatus),
}

# The result file's datasets: path -> (units, description); written on each dataset as attributes.
_UV = "the method's measured displacement from the reference to the gradient image"
RESULT_DATASETS = {
    "x": ("px", "window centre x (column; pixel centres at integers)"),
    "y": ("px", "window centre y (row)"),
    "u": ("px", f"x component of {_UV}; the local median where replaced or failed, NaN where masked"),
    "v": ("px", f"y component of {_UV}; the local median where replaced or failed, NaN where masked"),
    "flags": ("1", "bit flags of each window, 0 = measured (bits in the attribute flag_bits)"),
    "peak_ratio": ("1", "correlation peak ratio (highest over second-highest peak) of the last pass"),
    "valid": ("1", "true where the window's vector was measured and not flagged as an outlier"),
    "correlation": ("1", "correlation coefficient of the two deformed windows at the peak, last pass"),
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
    "dots/valid": ("1", "true where the dot was matched in both images and its displacement is finite"),
    "dots/masked": ("1", "1 where the dot's reference position lies in the mask (its u, v are NaN)"),
    "dots/u_pred": ("px", "x displacement predicted for the dot by the correlation predictor (NaN without it)"),
    "dots/v_pred": ("px", "y displacement predicted for the dot by the correlation predictor (NaN without it)"),
    "dots/pred_correlation": ("1", "normalised correlation of the predictor's windows at the dot: about 1 for a "
                                   "good prediction, about 0 for an unrelated gradient image (NaN without it)"),
    "dots/dot_id": ("1", "the prior's row the dot belongs to: the pair file's dot index (/dots/dot) for a pair "
                         "prior, the data row of the --dots CSV (0 = the line after the header), -1 without a prior"),
    "dots/dot": ("1", "row index of the /dots datasets (the dimension 'dot')"),
    "grid_x": ("px", "x (column) of each grid column's window centres, the dimension 'grid_x' of the 2-D datasets"),
    "grid_y": ("px", "y (row) of each grid row's window centres, the dimension 'grid_y' of the 2-D datasets"),
}


@dataclass(frozen=True)
class ImageOptions:
    """How camera images are prepared: the ``[image]`` table of a process configuration.

    Attributes
    ----------
    mask : str or None
        Path of a mask image of the same size as the camera images.
    mask_excludes : {"dark", "bright"}
        Which mask pixels are left out of the processing: "dark" (the default; a white mask marks
        the region to measure) or "bright" (a white mask marks what to leave out). The mask is split
        at the midpoint of its own range, so 0/1, 0/255 and 0/65535 masks all work.
    invert : "auto", True or False
        Invert the images (dark dots on a bright background become bright dots on a dark one), as
        dot tracking expects. "auto" inverts when the reference image's background (its median) is
        nearer to its bright end (99th percentile) than to its dark end (1st percentile).
        Correlation is unaffected by inversion.
    """

    mask: str | None = None
    mask_excludes: str = "dark"
    invert: str | bool = "auto"

    def __post_init__(self):
        if self.mask is not None and not isinstance(self.mask, str):
            raise SynthbosError(f"image option mask must be a path, got {shorten(self.mask)}")
        if isinstance(self.mask, str) and (not 0 < len(self.mask) <= MAX_PATH or "\0" in self.mask):
            raise SynthbosError(f"image option mask must be a path of 1 to {MAX_PATH} characters without NUL, "
                                f"got {shorten(self.mask)}")
        if self.mask_excludes not in MASK_POLARITIES:
            raise SynthbosError(
                f"image option mask_excludes must be one of {', '.join(MASK_POLARITIES)}, got {self.mask_excludes!r}"
            )
        if not (isinstance(self.invert, bool) or self.invert == "auto"):
            raise SynthbosError(f'image option invert must be "auto", true or false, got {self.invert!r}')


def _to_2d(img, path, notes):
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[-1] in (3, 4):  # colour, samples last
        if notes is not None:
            notes.append(f"{path}: colour image ({img.shape[-1]} channels) converted to luminance "
                         "(0.2126 R + 0.7152 G + 0.0722 B)")
        img = img[..., :3].astype(np.float64) @ LUMINANCE
    elif img.ndim == 3 and img.shape[0] in (3, 4) and min(img.shape[1:]) > 4:  # planar colour
        if notes is not None:
            notes.append(f"{path}: planar colour image ({img.shape[0]} channels) converted to luminance")
        img = np.tensordot(LUMINANCE, img[:3].astype(np.float64), axes=1)
    elif img.ndim == 3 and img.shape[0] == 1:
        img = img[0]
    if img.ndim != 2:
        raise SynthbosError(f"image {path} must be a single 2-D frame, got shape {img.shape}")
    if img.dtype.kind not in "biuf":
        raise SynthbosError(f"image {path} has pixel type {img.dtype}; expected integer or floating-point pixels")
    img = img.astype(np.float64)
    bad = ~np.isfinite(img)
    if bad.any():
        raise SynthbosError(f"image {path} has {int(bad.sum())} non-finite pixels (NaN or infinity)")
    return img


def _read_tiff(path, notes):
    """A TIFF's first series, with white high: WhiteIsZero (MINISWHITE) pixels are inverted."""
    with tifffile.TiffFile(path) as tif:
        img = tif.asarray()
        page = tif.pages[0]
        if page.photometric != tifffile.PHOTOMETRIC.MINISWHITE:
            return img
        bits = int(page.bitspersample)
    if img.dtype == bool:
        img = ~img
    elif img.dtype.kind == "u":
        img = (2 ** min(bits, 8 * img.dtype.itemsize) - 1) - img.astype(np.float64)
    elif img.dtype.kind == "i":
        img = -img.astype(np.float64)
    else:
        img = 1.0 - img.astype(np.float64)
    if notes is not None:
        notes.append(f"{path}: TIFF stored WhiteIsZero (0 = white), read inverted so that white is high")
    return img


def load_image(path, *, notes=None) -> np.ndarray:
    """Read one camera image as a float64 array.

    Parameters
    ----------
    path : str or Path
        TIFF (every compression tifffile reads, LZW and Deflate through imagecodecs; 8-, 12-, 16-,
        32-bit integer or floating-point pixels) or PNG, BMP, JPEG through imageio.
    notes : list, optional
        Messages for the user are appended here (a colour image converted to luminance, a TIFF stored
        WhiteIsZero read inverted).

    Returns
    -------
    (H, W) float64 array
        The pixel values as stored (no rescaling: a 12-bit image keeps 0 to 4095), except that a TIFF
        whose PhotometricInterpretation is WhiteIsZero (0 = white) is inverted so that white is high, as
        in every other image: ``2**BitsPerSample - 1 - value`` (``1 - value`` for floating point,
        ``not value`` for bilevel). Colour images become their luminance.

    Raises
    ------
    synthbos.SynthbosError
        Missing or unreadable file, more than one frame, non-finite pixels.
    """
    path = Path(path)
    try:
        exists = path.is_file()
    except (OSError, ValueError) as err:  # a name too long for the file system, a NUL byte
        raise SynthbosError(f"image {cut(str(path))}: {getattr(err, 'strerror', None) or err}") from None
    if not exists:
        raise SynthbosError(f"image {path} does not exist")
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            img = _read_tiff(path, notes)
        else:
            img = iio.imread(path)
    except Exception as err:  # the readers raise many types for unreadable files
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise SynthbosError(f"cannot read image {path}: {message}") from None
    return _to_2d(img, path, notes)


def load_mask(path, shape, *, excludes="dark", notes=None) -> np.ndarray:
    """Read a mask image as a boolean array, True on the pixels to leave out.

    Parameters
    ----------
    path : str or Path
        Mask image (any format :func:`load_image` reads; colour is reduced to luminance).
    shape : (H, W)
        The camera images' shape; the mask must have it.
    excludes : {"dark", "bright"}
        Which side of the midpoint of the mask's range is left out (see :class:`ImageOptions`).
        A constant mask leaves out everything or nothing: 0 counts as dark, anything else as bright.
        A TIFF stored WhiteIsZero is read with white high (:func:`load_image`).
    notes : list, optional
        What was read is appended: how many pixels are left out, and a WhiteIsZero TIFF's inversion.

    Returns
    -------
    (H, W) bool array
    """
    if excludes not in MASK_POLARITIES:
        raise SynthbosError(f"mask polarity must be one of {', '.join(MASK_POLARITIES)}, got {excludes!r}")
    m = load_image(path, notes=notes)
    if m.shape != tuple(shape):
        raise SynthbosError(f"mask {path} has shape {m.shape} but the images are {tuple(shape)}")
    lo, hi = m.min(), m.max()
    dark = m == 0 if lo == hi else m < 0.5 * (lo + hi)
    excluded = dark if excludes == "dark" else ~dark
    if excluded.all():
        raise SynthbosError(f"mask {path} leaves out every pixel (mask_excludes = {excludes!r}); "
                            "is its polarity the other way round?")
    if notes is not None:
        notes.append(f"mask {path}: {int(excluded.sum())} of {excluded.size} pixels ({excluded.mean():.1%}) left "
                     f"out, the {excludes} ones")
    return excluded


def decide_invert(image, *, invert="auto"):
    """Whether to invert an image pair so that its dots are bright, and why.

    Parameters
    ----------
    image : (H, W) array
        The reference image.
    invert : "auto", True or False

    Returns
    -------
    (bool, str)
        The decision and a one-line reason for the result file and the user.
    """
    if isinstance(invert, bool):
        return invert, "set by the user"
    lo, med, hi = np.percentile(image, [1, 50, 99])
    if hi <= lo:
        return False, "auto: the image has no contrast"
    level = (med - lo) / (hi - lo)
    if level > 0.5:
        return True, f"auto: bright background (median at {level:.0%} of the 1-99 % range), dark dots"
    return False, f"auto: dark background (median at {level:.0%} of the 1-99 % range), bright dots"


def apply_invert(reference, gradient):
    """``c - image`` for both images with one ``c``, their common maximum: dark dots become bright."""
    c = max(float(np.max(reference)), float(np.max(gradient)))
    return c - reference, c - gradient


def process_tables() -> tuple[str, ...]:
    """The tables a process configuration may hold: ``image``, ``setup`` and every settings table."""
    return ("image", "setup", *_settings_tables())


def _settings_tables():
    """Table name -> a registered method that reads it (the first one in the registry)."""
    tables = {}
    for m in METHODS.values():
        tables.setdefault(m.settings_key, m)
    return tables


def read_process_config(path) -> dict:
    """Read and check a process configuration (the tables in the module docstring).

    Returns
    -------
    dict
        ``{"image": ImageOptions, <settings table>: {field: value}, ...}``: every settings table is
        checked by building its settings class, so unknown keys and bad values fail here; a mask
        path is made relative to the configuration file's folder. A ``[setup]`` table (the camera
        pair's set-up, :mod:`synthbos.benchmarks.setup_file`) is checked and returned as ``"setup"``.
    """
    from synthbos.raytrace.config import read_toml

    path = Path(path)
    raw = read_toml(path)
    tables = _settings_tables()
    known = list(process_tables())
    unknown = sorted(set(raw) - set(known))
    if unknown:
        raise SynthbosError(f"process configuration {path}: unknown table(s) {', '.join(unknown)}; "
                            f"known: {', '.join(known)}")
    out = {}
    for name, method in tables.items():
        values = raw.get(name, {})
        if not isinstance(values, dict):
            raise SynthbosError(f"process configuration {path}: {name} must be a table")
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
        method.settings(values)  # refuses unknown keys and bad values
        out[name] = values
    image = raw.get("image", {})
    if not isinstance(image, dict):
        raise SynthbosError(f"process configuration {path}: image must be a table")
    fields = set(ImageOptions.__dataclass_fields__)
    bad = sorted(set(image) - fields)
    if bad:
        raise SynthbosError(f"process configuration {path}: unknown [image] key(s) {', '.join(bad)}; "
                            f"known: {', '.join(sorted(fields))}")
    image = dict(image)
    if isinstance(image.get("mask"), str):
        image["mask"] = str(path.parent / image["mask"])
    out["image"] = ImageOptions(**image)
    if "setup" in raw:  # the camera pair's set-up (benchmarks.setup_file), checked now, used by the caller
        from .setup_file import check_setup_table

        out["setup"] = check_setup_table(raw["setup"], f"process configuration {path}")
    return out


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


def run_method(method, reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None) -> MethodResult:
    """Run the registered method ``method`` on an image pair and return its ``MethodResult``.

    ``mask`` (bool, True = left out) goes to the method's run function.
    """
    m = get_method(method)
    return m.run(
        reference, gradient, prior_xy=prior_xy, settings=m.settings() if settings is None else settings,
        device=device, mask=mask
    )


def write_result(path, result: MethodResult, *, extra_attrs=None) -> Path:
    """Write a result file atomically (layout in the module docstring)."""
    path = Path(path)
    method = get_method(result.method)
    with atomic_hdf5(path) as f:
        if method.kind in (GRID, DENSE):
            for name, values in result.table.items():
                f.create_dataset(name, data=np.asarray(values))
            if result.valid is not None:
                f.create_dataset("valid", data=np.asarray(result.valid, bool).reshape(np.shape(result.table["u"])))
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
            if result.valid is not None:
                g.create_dataset("valid", data=np.asarray(result.valid, bool))
        f.attrs["method"] = result.method
        f.attrs["kind"] = method.kind
        f.attrs["settings"] = json.dumps(result.settings, default=str)
        if result.counts:
            f.attrs["counts"] = json.dumps(result.counts)
        for key, value in (extra_attrs or {}).items():
            f.attrs[key] = value
        _describe(f)
        if method.kind == DENSE:
            for axis, words in (("x", "column"), ("y", "row")):
                f[axis].attrs["description"] = f"pixel centre {axis} ({words}) of the reference image"
        _result_dimensions(f, method.kind)
    return path


def _result_dimensions(f, kind) -> None:
    """Named dimensions (HDF5 dimension scales): ``(grid_y, grid_x)`` of a grid or dense result, ``(dot,)``
    of a dots result's columns (none where a plugin's table already holds a column of a scale's name)."""
    if kind in (GRID, DENSE):
        x, y = np.asarray(f["x"][()], np.float64), np.asarray(f["y"][()], np.float64)
        if x.ndim != 2 or "grid_x" in f or "grid_y" in f:
            return
        ny, nx = x.shape
        dims = {name: ("grid_y", "grid_x") for name, ds in f.items()
                if isinstance(ds, h5py.Dataset) and ds.shape == (ny, nx)}
        scales = {"grid_x": (np.nanmean(x, axis=0), *RESULT_DATASETS["grid_x"]),
                  "grid_y": (np.nanmean(y, axis=1), *RESULT_DATASETS["grid_y"])}
        name_dimensions(f, scales, dims)
    else:
        g = f["dots"]
        n = len(g["x"])
        if "dot" in g:
            return
        dims = {name: ("dot",) for name, ds in g.items() if isinstance(ds, h5py.Dataset) and ds.shape == (n,)}
        name_dimensions(g, {"dot": (np.arange(n, dtype=np.int64), *RESULT_DATASETS["dots/dot"])}, dims)


# Datasets every result file of a kind holds.
RESULT_NEEDS = {
    GRID: ("x", "y", "u", "v"),
    DENSE: ("x", "y", "u", "v"),
    DOTS: ("dots/x", "dots/y", "dots/u", "dots/v"),
}


def check_result_file(f, path):
    """Check an open result file before reading it; return its method and kind.

    Refused with one line: a file of another command (a density file, a pair file), an unknown method
    or kind, a missing dataset, datasets of different lengths, or declared shapes that need more than
    the memory limit (``limits.memory_gb``'s default).
    """
    from synthbos.raytrace.checks import check_file_memory

    if "density_kg_m3" in f:
        raise SynthbosError(f"{path} is a density file of 'synthbos integrate', not a result file of "
                            "'synthbos process'")
    if "images" in f:
        raise SynthbosError(f"{path} is a pair file of 'synthbos render', not a result file of 'synthbos process'")
    if "method" not in f.attrs:
        raise SynthbosError(f"{path} is not a synthbos result file: no 'method' attribute")
    method = get_method(_text(f.attrs["method"]))
    kind = _text(f.attrs.get("kind", method.kind))
    if kind != method.kind:
        raise SynthbosError(f"{path}: its kind attribute {shorten(kind)} is not that of method {method.name} "
                            f"({method.kind})")
    missing = [f"/{n}" for n in RESULT_NEEDS[kind] if not isinstance(f.get(n), h5py.Dataset)]
    if missing:
        raise SynthbosError(f"{path} is not a {method.name} result file: missing {', '.join(missing)}")
    alike = RESULT_NEEDS[kind] if kind == DOTS else ("u", "v")  # (a dense field's x, y may be its axes)
    if len({f[n].size for n in alike}) != 1:
        raise SynthbosError(f"{path}: its datasets {', '.join(alike)} differ in length")
    check_file_memory([d for _, d in _datasets(f)], f"result file {path}")
    return method, kind


def _text(value):
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)


def read_result(path):
    """Read a result file written by ``write_result``; return ``(MethodResult, root attributes)``.

    A missing, unreadable or malformed file, or an empty one, raises ``SynthbosError``.
    """
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"result file {path} does not exist")
    try:
        with h5py.File(path, "r") as f:
            method, _ = check_result_file(f, path)
            attrs = {k: (v.decode("utf-8", "replace") if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            try:
                settings = json.loads(attrs.get("settings", "{}"))
            except json.JSONDecodeError:
                settings = {}
            if method.kind in (GRID, DENSE):
                need = ("x", "y", "u", "v", *(("flags", "peak_ratio") if method.name == "correlation" else ()))
                missing = [f"/{n}" for n in need if n not in f]
                if missing:
                    raise SynthbosError(f"{path} is not a {method.name} result file: missing {', '.join(missing)}")
                table = {n: f[n][()] for n in f if isinstance(f[n], h5py.Dataset) and not is_scale(f[n])
                         and n not in ("valid", "correlation")}
                shape = tuple(np.shape(table["u"]))
                valid = f["valid"][()].ravel().astype(bool) if "valid" in f else None
                xy = np.stack([np.ravel(table["x"]), np.ravel(table["y"])], axis=1).astype(np.float64)
                uv = np.stack([np.ravel(table["u"]), np.ravel(table["v"])], axis=1).astype(np.float64)
                if len(shape) != 2:
                    raise SynthbosError(f"{path}: a grid result needs 2-D /u, got shape {shape}")
            else:
                missing = [f"/dots/{n}" for n in ("x", "y", "u", "v") if f"dots/{n}" not in f]
                if missing:
                    raise SynthbosError(f"{path} is not a {method.name} result file: missing {', '.join(missing)}")
                g = f["dots"]
                table = {n: g[n][()] for n in g if n != "valid" and not is_scale(g[n])}
                table["u_cc"] = table.get("u_cc", table["u"])
                table["v_cc"] = table.get("v_cc", table["v"])
                shape = None
                valid = g["valid"][()].astype(bool) if "valid" in g else None
                xy = np.stack([table["x"], table["y"]], axis=1).astype(np.float64)
                uv = np.stack([table["u"], table["v"]], axis=1).astype(np.float64)
                if "u_centroid" in table:  # the table's own u, v were the centroid difference
                    table["u"], table["v"] = table["u_centroid"], table["v_centroid"]
    except OSError as err:
        raise SynthbosError(f"cannot read result file {path}: {err}") from None
    if len(xy) == 0:
        raise SynthbosError(f"{path} holds no vectors (an empty result)")
    return MethodResult(method.name, xy, uv, shape, table, settings, valid), attrs


def _describe(f) -> None:
    """Units, description and flag bits on every dataset of a result file (a column the schema does not
    know yet gets a generic description rather than none)."""
    describe_datasets(f, RESULT_DATASETS)
    for name, obj in _datasets(f):
        column = name.rpartition("/")[2]
        if column in FLAG_BITS:
            obj.attrs["flag_bits"] = flag_bits(FLAG_BITS[column])
        if "units" not in obj.attrs:  # a plugin's own column: its units are not known here
            obj.attrs["units"] = "unknown"
            obj.attrs["description"] = f"column {column!r} of the {f.attrs['method']} table (see its documentation)"


def _datasets(group, prefix=""):
    for key, obj in group.items():
        if isinstance(obj, h5py.Dataset):
            yield f"{prefix}{key}", obj
        else:
            yield from _datasets(obj, f"{prefix}{key}/")


def image_options_dict(options: ImageOptions, inverted: bool, reason: str) -> dict:
    """The image options used, for the ``image`` attribute of a result file."""
    return {**asdict(options), "inverted": bool(inverted), "invert_reason": reason}


#: Short command-line flags: flag name -> (settings table, field, parser of the flag's text).
def _int_list(text):
    try:
        return tuple(int(t) for t in str(text).split(",") if t.strip())
    except ValueError:
        raise SynthbosError(f"--windows takes whole numbers separated by commas, e.g. 64,32,16; got {text!r}") from None


SHORT_FLAGS = {
    "windows": ("correlation", "window_sizes", _int_list),
    "overlap": ("correlation", "overlaps", float),
    "diameter": ("tracking", "diameter", float),
    "max_displacement": ("tracking", "max_displacement", float),
}


def process_settings(method, *, config=None, flags=None, image=None):
    """The settings object and image options of one run, from a configuration file and flags.

    Parameters
    ----------
    method : str
        A registered method.
    config : str or Path, optional
        Process configuration (module docstring).
    flags : dict, optional
        Values of the short flags (:data:`SHORT_FLAGS` names; None = not given). They override the
        file; a flag of a settings table the method does not read is refused.
    image : dict, optional
        ``[image]`` options given on the command line (``mask``, ``mask_excludes``, ``invert``;
        None = not given), overriding the file's.

    Returns
    -------
    settings, ImageOptions
    """
    m = get_method(method)
    table = m.settings_key
    cfg = read_process_config(config) if config is not None else {"image": ImageOptions()}
    values = dict(cfg.get(table, {}))
    for name, given in (flags or {}).items():
        if given is None:
            continue
        flag_table, field, parse = SHORT_FLAGS[name]
        if flag_table != table:
            raise SynthbosError(f"--{name.replace('_', '-')} is a {flag_table} setting; "
                                f"--method {method} reads [{table}]")
        values[field] = parse(given)
    settings = m.settings(values)
    options = cfg["image"]
    given = {k: v for k, v in (image or {}).items() if v is not None}
    if given:
        options = ImageOptions(**{**asdict(options), **given})
    return settings, options


def process_pair(method, reference, gradient, *, settings=None, options=None, prior_xy=None, device=None,
                 notes=None):
    """Prepare an image pair (mask, inversion) and run a registered method on it.

    Parameters
    ----------
    method : str
    reference, gradient : (H, W) arrays
    settings : the method's settings object, optional
    options : ImageOptions, optional
    prior_xy : (N, 2) array, optional
        Predicted reference-image dot positions (methods that use a prior).
    device : str, optional
    notes : list, optional
        One-line messages for the user are appended (the inversion decision, what the mask left out).

    Returns
    -------
    MethodResult, dict
        The result and the image options used (:func:`image_options_dict`).
    """
    options = options or ImageOptions()
    if np.shape(reference) != np.shape(gradient):
        raise SynthbosError(f"images differ in shape: reference {np.shape(reference)}, gradient {np.shape(gradient)}")
    if min(np.shape(reference)) < MIN_IMAGE_PX:
        h, w = np.shape(reference)
        raise SynthbosError(f"the images are {w} x {h} px; processing needs at least {MIN_IMAGE_PX} x "
                            f"{MIN_IMAGE_PX} px")
    if prior_xy is not None:
        outside = check_prior(prior_xy, np.shape(reference))
        if outside and notes is not None:
            h, w = np.shape(reference)
            notes.append(f"{outside} of the {len(prior_xy)} dots of the prior lie outside the {w} x {h} px image: "
                         "they are not measured")
    mask = None
    if options.mask is not None:
        mask = load_mask(options.mask, np.shape(reference), excludes=options.mask_excludes, notes=notes)
    inverted, reason = decide_invert(reference, invert=options.invert)
    if inverted:
        reference, gradient = apply_invert(np.asarray(reference, float), np.asarray(gradient, float))
        if notes is not None:
            notes.append(f"images inverted ({reason})")
    res = run_method(method, reference, gradient, prior_xy=prior_xy, settings=settings, device=device, mask=mask)
    if get_method(method).kind == DOTS and "dot_id" not in res.table:  # a plugin's dots table: the prior's rows
        with_prior = prior_xy is not None and get_method(method).uses_prior
        res.table["dot_id"] = np.arange(len(res.xy)) if with_prior else np.full(len(res.xy), -1)
    return res, image_options_dict(options, inverted, reason)


def result_setup(image_shape, *, pair=None, pair_path=None, setup_file=None, config=None) -> str | None:
    """The ``setup`` attribute of a result file (JSON, ``integrate.setup_attr``), or None when unknown.

    Parameters
    ----------
    image_shape : (H, W)
        The processed images' shape.
    pair : Pair, optional
        The pair file processed (``pair_path`` its path): its render set-up.
    setup_file : str or Path, optional
        A set-up file (``--setup-file``, :mod:`synthbos.benchmarks.setup_file`).
    config : str or Path, optional
        The process configuration, whose ``[setup]`` table counts when there is no set-up file.

    A pair file with a set-up file or a ``[setup]`` table is refused: the pair holds its own.
    """
    from .integrate import geometry_from_pair, setup_attr
    from .setup_file import geometry_from_setup, read_setup_file

    table, where = None, None
    if setup_file is not None:
        table, where = read_setup_file(setup_file), f"set-up file {setup_file}"
    elif config is not None:
        table, where = read_process_config(config).get("setup"), f"process configuration {config}"
    if pair is not None:
        if table is not None:
            raise SynthbosError(f"the pair file {pair_path} holds its own set-up: leave out the [setup] of the {where}")
        return setup_attr(geometry_from_pair(pair), f"pair file {pair_path}")
    if table is None:
        return None
    return setup_attr(geometry_from_setup(table, image_shape, where=where), where)


def check_prior(prior_xy, shape) -> int:
    """Refuse a tracking prior that can only give nonsense: the same dot twice (two positions closer than
    ``DUPLICATE_PX``), or no position inside the ``(H, W)`` image. Returns how many positions lie outside
    it (a target larger than the view: those dots are not measured).

    Examples
    --------
    >>> check_prior([[10.0, 10.0], [5000.0, 20.0]], (256, 256))
    1
    """
    from scipy.spatial import cKDTree

    xy = np.asarray(prior_xy, dtype=np.float64).reshape(-1, 2)
    pairs = cKDTree(xy).query_pairs(DUPLICATE_PX, output_type="ndarray")
    if len(pairs):
        i, j = (int(k) for k in pairs[np.argmin(pairs.max(axis=1))])
        raise SynthbosError(f"the dots prior lists {len(np.unique(pairs))} positions that are another's within "
                            f"{DUPLICATE_PX} px (e.g. entries {min(i, j) + 1} and {max(i, j) + 1} at "
                            f"{xy[i, 0]:.4g}, {xy[i, 1]:.4g}): each dot must be listed once")
    h, w = shape
    inside = (xy[:, 0] > -0.5) & (xy[:, 0] < w - 0.5) & (xy[:, 1] > -0.5) & (xy[:, 1] < h - 0.5)
    if not inside.any():
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        raise SynthbosError(f"no dot of the prior lies in the {w} x {h} px image (x {lo[0]:.4g} .. {hi[0]:.4g}, "
                            f"y {lo[1]:.4g} .. {hi[1]:.4g} px): wrong units or another image?")
    return int(np.count_nonzero(~inside))
