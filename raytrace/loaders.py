"""File readers for density data: JHTDB cutouts, NRRD, NumPy, HDF5, and the embedded snapshot file.

Every reader returns a validated :class:`LoadedDensity` or raises one ``SynthbosError`` naming the
file and the problem (missing file or dataset, truncated/unreadable HDF5, wrong dimensionality,
NaN/inf, zero or negative values), so bad input never reaches the kernels.

Array conventions: a volume is ``(nz, ny, nx)`` (C order, x fastest), a slice ``(ny, nx)``.

What is relied on, per format
-----------------------------
``jhtdb``
    Cutout files of the Johns Hopkins Turbulence Database. The current toolkit (givernylocal) writes
    netCDF4, which is HDF5, so both it and the legacy h5py layout are read with h5py: a variable named
    after the field and time step, ``Density_NNNN``, of shape ``(nz, ny, nx, 1)`` (a trailing component
    axis of length 1; ``(nz, ny, nx)`` is also accepted), and 1-D coordinate variables ``xcoor``,
    ``ycoor``, ``zcoor`` whose uniform step is returned as the spacing (in database units: the "mixing"
    run has a ``2 pi`` box). File attributes (``dataset``, ``x_start``, ``x_step``, ...) are kept in
    ``attrs`` but not needed. Several time steps in one file: pick one with ``dataset``.
``nrrd``
    Read with pynrrd in C index order, so the array is ``(nz, ny, nx)``; the spacing comes from the
    header's ``spacings`` or the norms of ``space directions`` when present (units as in the file).
``npy`` / ``npz``
    A 2-D or 3-D array; for ``npz`` the array is named by ``dataset`` (optional if there is only one).
    No coordinates: the spacing is None.
``hdf5``
    The dataset at path ``dataset`` (optional if the file holds exactly one dataset). A file with
    ``Density_NNNN`` and ``xcoor`` and no ``dataset`` given is read as ``jhtdb``. No coordinates.
"""

from __future__ import annotations

import os
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import nrrd
import numpy as np

from synthbos import SynthbosError, data_file

from .checks import check_density

__all__ = [
    "DEFAULT_SNAPSHOTS",
    "FORMATS",
    "LoadedDensity",
    "infer_format",
    "load_density",
    "read_snapshots",
    "write_snapshots",
]

FORMATS = ("jhtdb", "nrrd", "npy", "npz", "hdf5")
DEFAULT_SNAPSHOTS = data_file("buoyancy_snapshots.h5")
SNAPSHOT_FORMAT = "synthbos-buoyancy-snapshots/1"

_AXES = {"x": 2, "y": 1, "z": 0}
_JHTDB_VAR = re.compile(r"^[A-Za-z]+_\d{4}$")


@dataclass(frozen=True)
class LoadedDensity:
    """Density data read from a file.

    Attributes
    ----------
    data : float64 array, ``(nz, ny, nx)`` or ``(ny, nx)``
        The values as stored (not rescaled), validated finite and > 0.
    spacing : tuple of float or None
        Node spacing ``(dx, dy[, dz])``: the ``spacing_mm`` asked for, else the file's own where the
        format carries coordinates (JHTDB, NRRD), else None. A 2-D result has two entries, ordered like
        its axes reversed (first the in-plane horizontal axis, then the vertical one).
    spacing_units : {"mm", "file", None}
        "mm" when ``spacing_mm`` was given, "file" for the file's own units.
    path : str
        The file.
    dataset : str or None
        The variable or dataset read.
    attrs : dict
        File/dataset metadata kept for the record.
    """

    data: np.ndarray
    spacing: tuple | None
    spacing_units: str | None
    path: str
    dataset: str | None = None
    attrs: dict = field(default_factory=dict)


def infer_format(path):
    """Format from a file's extension: .nc -> jhtdb, .nrrd/.nhdr -> nrrd, .npy, .npz, .h5/.hdf5 -> hdf5."""
    ext = Path(path).suffix.lower()
    table = {
        ".nc": "jhtdb",
        ".nrrd": "nrrd",
        ".nhdr": "nrrd",
        ".npy": "npy",
        ".npz": "npz",
        ".h5": "hdf5",
        ".hdf5": "hdf5",
        ".he5": "hdf5",
        ".hdf": "hdf5",
    }
    if ext not in table:
        raise SynthbosError(
            f"{path}: cannot infer the format from extension {ext!r}; set format to one of {FORMATS}"
        )
    return table[ext]


def _check_declared(shape, path, name, memory_gb):
    """Refuse data whose declared shape would not fit in memory, before reading it."""
    from .checks import BYTES_PER_NODE, check_memory

    nodes = float(np.prod([float(n) for n in shape])) if len(shape) else 1.0
    what = f"{path}: {name + ' ' if name else ''}of shape {tuple(int(n) for n in shape)}"
    check_memory(nodes * BYTES_PER_NODE, what, memory_gb=memory_gb)


def _npy_header(fp, path):
    """(shape, dtype) from the header of an open .npy stream, without reading the data."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fp)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(fp)
        else:
            shape, _, dtype = fmt.read_array_header_2_0(fp)
    except (ValueError, EOFError, OSError) as exc:
        raise SynthbosError(f"{path}: not a readable .npy array ({_short(exc)})") from None
    return shape, dtype


def _h5py_open(path):
    try:
        return h5py.File(path, "r")
    except OSError as exc:  # truncated, not HDF5, permissions
        raise SynthbosError(f"{path}: not a readable HDF5/netCDF4 file ({_short(exc)})") from None


def _short(exc):
    return str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__


def _datasets(h5):
    names = []
    h5.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
    return names


def _read_h5_array(h5, name, path, memory_gb=None):
    obj = h5.get(name)
    if not isinstance(obj, h5py.Dataset):
        avail = _datasets(h5)
        raise SynthbosError(f"{path}: no dataset {name!r} in the file (it has {avail[:8]})")
    _check_declared(obj.shape or (), path, f"dataset {name!r}", memory_gb)
    try:
        return obj[()], {k: _attr(v) for k, v in obj.attrs.items()}
    except (OSError, ValueError, TypeError) as exc:
        raise SynthbosError(
            f"{path}: dataset {name!r} cannot be read ({_short(exc)}); truncated file?"
        ) from None


def _attr(v):
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.ndarray) and v.size == 1:
        v = v.reshape(()).item()
        return v.decode("utf-8", "replace") if isinstance(v, bytes) else v
    if isinstance(v, np.generic):
        return v.item()
    return v


def _uniform_step(coord, name, path):
    c = np.asarray(coord, dtype=np.float64).ravel()
    if c.size < 2:
        return None
    d = np.diff(c)
    step = float(d.mean())
    if not np.all(np.isfinite(c)) or step <= 0 or np.max(np.abs(d - step)) > 1e-6 * abs(step) + 1e-12:
        raise SynthbosError(
            f"{path}: coordinate {name} is not uniformly increasing; a regular grid is needed"
        )
    return step


def _is_jhtdb(h5):
    return "xcoor" in h5 and any(_JHTDB_VAR.match(k) and k.lower().startswith("density") for k in h5)


def _load_jhtdb(path, dataset, memory_gb=None):
    with _h5py_open(path) as h5:
        if dataset is None:
            cands = sorted(k for k in h5 if _JHTDB_VAR.match(k) and k.lower().startswith("density"))
            if not cands:
                raise SynthbosError(f"{path}: no Density_NNNN variable found (variables: {sorted(h5)[:8]})")
            if len(cands) > 1:
                raise SynthbosError(f"{path}: several time steps {cands}; choose one with dataset")
            dataset = cands[0]
        data, dattrs = _read_h5_array(h5, dataset, path, memory_gb)
        spacing = []
        for ax in ("xcoor", "ycoor", "zcoor"):
            if ax not in h5:
                raise SynthbosError(f"{path}: JHTDB coordinate variable {ax!r} is missing")
            c, _ = _read_h5_array(h5, ax, path)
            spacing.append(_uniform_step(c, ax, path))
        attrs = {k: _attr(v) for k, v in h5.attrs.items()}
        attrs.update(dattrs)
    data = np.asarray(data)
    if data.ndim == 4:
        if data.shape[3] != 1:
            raise SynthbosError(
                f"{path}: {dataset} has {data.shape[3]} components (shape {data.shape}); density has one"
            )
        data = data[..., 0]
    if data.ndim != 3:
        raise SynthbosError(
            f"{path}: {dataset} must be (nz, ny, nx, 1) or (nz, ny, nx), got shape {data.shape}"
        )
    for n, ax, s in zip(data.shape[::-1], ("xcoor", "ycoor", "zcoor"), spacing, strict=True):
        if s is None and n > 1:
            raise SynthbosError(f"{path}: coordinate {ax} has fewer points than the data axis ({n})")
    spacing = tuple(s if s is not None else 1.0 for s in spacing)
    return data, spacing, dataset, attrs


def _load_nrrd(path, memory_gb=None):
    try:
        sizes = nrrd.read_header(str(path)).get("sizes", ())
    except Exception as exc:  # pynrrd raises NRRDError, OSError, ValueError on bad files
        raise SynthbosError(f"{path}: not a readable NRRD file ({_short(exc)})") from None
    _check_declared(tuple(sizes), path, "", memory_gb)
    try:
        data, header = nrrd.read(str(path), index_order="C")
    except Exception as exc:  # pynrrd raises NRRDError, OSError, ValueError on bad files
        raise SynthbosError(f"{path}: not a readable NRRD file ({_short(exc)})") from None
    spacing = None
    if "spacings" in header:
        spacing = tuple(float(s) for s in header["spacings"])
    elif header.get("space directions") is not None:
        dirs = np.asarray(header["space directions"], dtype=np.float64)
        if dirs.ndim == 2 and np.all(np.isfinite(dirs)):
            spacing = tuple(float(v) for v in np.linalg.norm(dirs, axis=1))
    # pynrrd lists per-axis fields in the file's (Fortran, x first) order: already (dx, dy, dz).
    if spacing is not None and (len(spacing) != data.ndim or not all(np.isfinite(spacing))):
        spacing = None
    attrs = {k: v for k, v in header.items() if isinstance(v, str | int | float)}
    return data, spacing, None, attrs


def _load_npy(path, memory_gb=None):
    try:
        with open(path, "rb") as fp:
            shape, _ = _npy_header(fp, path)
        _check_declared(shape, path, "", memory_gb)
        return np.load(path, allow_pickle=False), None, None, {}
    except SynthbosError:
        raise
    except (OSError, ValueError, EOFError) as exc:
        raise SynthbosError(f"{path}: not a readable .npy file ({_short(exc)})") from None


def _load_npz(path, dataset, memory_gb=None):
    try:
        with np.load(path, allow_pickle=False) as z:
            names = list(z.files)
            if dataset is None:
                if len(names) != 1:
                    raise SynthbosError(f"{path}: holds arrays {names}; choose one with dataset")
                dataset = names[0]
            if dataset not in names:
                raise SynthbosError(f"{path}: no array {dataset!r} in the file (it has {names})")
            with z.zip.open(f"{dataset}.npy") as fp:
                shape, _ = _npy_header(fp, path)
            _check_declared(shape, path, f"array {dataset!r}", memory_gb)
            return z[dataset], None, dataset, {}
    except SynthbosError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise SynthbosError(f"{path}: not a readable .npz file ({_short(exc)})") from None


def _load_hdf5(path, dataset, memory_gb=None):
    with _h5py_open(path) as h5:
        jhtdb = dataset is None and _is_jhtdb(h5)
        if dataset is None and not jhtdb:
            names = _datasets(h5)
            if len(names) != 1:
                raise SynthbosError(f"{path}: holds datasets {names[:8]}; choose one with dataset")
            dataset = names[0]
        if not jhtdb:
            data, attrs = _read_h5_array(h5, dataset, path, memory_gb)
    if jhtdb:
        return _load_jhtdb(path, None, memory_gb)
    return data, None, dataset, attrs


def load_density(
    path,
    *,
    format=None,
    dataset=None,
    slice_index=None,
    axis=None,
    index_range=None,
    spacing_mm=None,
    axis_order=None,
    memory_gb=None,
):
    """Read density data from a file, optionally one 2-D slice or a sub-volume of it.

    Parameters
    ----------
    path : str or Path
    format : {"jhtdb", "nrrd", "npy", "npz", "hdf5"}, optional
        Inferred from the extension when omitted (see :func:`infer_format`).
    dataset : str, optional
        Variable (JHTDB), array name (npz) or dataset path (hdf5).
    slice_index : int, optional
        Pick the 2-D slice at this (absolute, file) index along ``axis`` of a 3-D array. The slice keeps
        the other two axes in order: ``axis="z"`` -> ``(ny, nx)``, ``"y"`` -> ``(nz, nx)``,
        ``"x"`` -> ``(nz, ny)``. Negative indices count from the end.
    axis : {"x", "y", "z"}, optional
        Axis of ``slice_index``; "z" when omitted.
    index_range : sequence of three [start, stop) pairs or None, optional
        Sub-volume in absolute file indices, ordered ``[[x0, x1], [y0, y1], [z0, z1]]`` (None for a
        whole axis). With ``slice_index`` the pair of the sliced axis is ignored. For 2-D data give
        ``[[x0, x1], [y0, y1]]``.
    spacing_mm : float or sequence of float, optional
        Node spacing of the file's grid in mm, one number or ``[dx, dy]`` / ``[dx, dy, dz]`` along the
        file's axes (before slicing). Replaces the file's own spacing; ``spacing_units`` becomes "mm".
    axis_order : str, optional
        The physical axis of each array axis as stored, first array axis first: "zyx" (3-D) and "yx"
        (2-D) are the conventions above and the default; "xyz" / "xy" read an array stored as
        ``(nx, ny, nz)`` / ``(nx, ny)`` (Fortran-ordered simulation output, which would otherwise
        render transposed); any permutation is accepted. The data are transposed to ``(nz, ny, nx)``
        before ``index_range``, ``slice_index`` and ``axis`` apply, so those always name physical axes;
        a file's own spacing is permuted along.
    memory_gb : float, optional
        Memory limit (``limits.memory_gb``; default ``raytrace.checks.default_memory_gb()``): a file
        whose declared shape would need more is refused before its data are read.

    Returns
    -------
    LoadedDensity
        Values as stored (float64), ``(nz, ny, nx)`` or ``(ny, nx)``; the spacing follows the slice.

    Raises
    ------
    SynthbosError
        Missing file or dataset, unreadable or truncated file, wrong dimensionality, bad slice or range,
        NaN/inf or non-positive values.
    """
    path = str(path)
    if not os.path.isfile(path):
        raise SynthbosError(f"{path}: density file not found")
    fmt = infer_format(path) if format is None else str(format).lower()
    if fmt not in FORMATS:
        raise SynthbosError(f"{path}: unknown format {format!r}; use one of {FORMATS}")
    if fmt in ("npy", "nrrd") and dataset is not None:
        raise SynthbosError(f"{path}: format {fmt!r} holds one array; dataset does not apply")
    if fmt == "jhtdb":
        data, spacing, dataset, attrs = _load_jhtdb(path, dataset, memory_gb)
    elif fmt == "nrrd":
        data, spacing, dataset, attrs = _load_nrrd(path, memory_gb)
    elif fmt == "npy":
        data, spacing, dataset, attrs = _load_npy(path, memory_gb)
    elif fmt == "npz":
        data, spacing, dataset, attrs = _load_npz(path, dataset, memory_gb)
    else:
        data, spacing, dataset, attrs = _load_hdf5(path, dataset, memory_gb)
    data = np.asarray(data)
    what = path if dataset is None else f"{path} [{dataset}]"
    if data.ndim not in (2, 3):
        raise SynthbosError(
            f"{what}: density must be 2-D (ny, nx) or 3-D (nz, ny, nx), got shape {data.shape}"
        )
    spacing = None if spacing is None else tuple(spacing)  # (dx, dy[, dz])
    if axis_order is not None:
        data, spacing = _reorder(data, spacing, axis_order, what)
    units = None if spacing is None else "file"
    if spacing_mm is not None:
        spacing, units = _spacing_arg(spacing_mm, data.ndim, what), "mm"
    if axis is None:
        axis = "z"
    if index_range is not None:
        data, spacing = _crop(
            data, spacing, index_range, slice_axis=axis if slice_index is not None else None, what=what
        )
    if slice_index is not None:
        data, spacing = _slice(data, spacing, slice_index, axis, what=what)
    if min(data.shape) < 2:
        raise SynthbosError(f"{what}: need at least 2 nodes along every axis, got shape {data.shape}")
    data = check_density(data, where=what)
    return LoadedDensity(
        data=np.ascontiguousarray(data),
        spacing=spacing,
        spacing_units=units,
        path=path,
        dataset=dataset,
        attrs=attrs,
    )


def _reorder(data, spacing, axis_order, what):
    """Transpose an array stored with axes ``axis_order`` (e.g. "xyz") to the (z, y, x) convention."""
    canon = "zyx"[3 - data.ndim :]
    order = str(axis_order).lower()
    if sorted(order) != sorted(canon):
        raise SynthbosError(
            f"{what}: axis_order must name each of the {data.ndim} axes {', '.join(sorted(canon))} once "
            f"(e.g. {canon!r} or {canon[::-1]!r}) for data of shape {data.shape}, got {axis_order!r}"
        )
    if spacing is not None:
        # a file's spacing lists the array axes last first (x fastest in the convention)
        by_letter = dict(zip(order[::-1], spacing, strict=True))
        spacing = tuple(by_letter[c] for c in canon[::-1])
    return np.transpose(data, [order.index(c) for c in canon]), spacing


def _spacing_arg(spacing_mm, ndim, what):
    vals = [spacing_mm] * ndim if np.ndim(spacing_mm) == 0 else list(spacing_mm)
    if len(vals) != ndim:
        raise SynthbosError(
            f"{what}: spacing_mm needs 1 or {ndim} values for {ndim}-D data, got {spacing_mm!r}"
        )
    try:
        vals = [float(v) for v in vals]
    except (TypeError, ValueError):
        raise SynthbosError(f"{what}: spacing_mm must be numbers, got {spacing_mm!r}") from None
    if not all(np.isfinite(v) and v > 0 for v in vals):
        raise SynthbosError(f"{what}: spacing_mm must be finite and > 0, got {spacing_mm!r}")
    return tuple(vals)


def _crop(data, spacing, index_range, *, slice_axis, what):
    pairs = list(index_range)
    if len(pairs) != data.ndim:
        raise SynthbosError(
            f"{what}: index_range needs {data.ndim} [start, stop] pairs (x, y{', z' * (data.ndim == 3)})"
        )
    sl = [slice(None)] * data.ndim
    for k, pair in enumerate(pairs):  # k: 0 = x, 1 = y, 2 = z
        ax = data.ndim - 1 - k
        if pair is None or (slice_axis is not None and _AXES[slice_axis] == ax and data.ndim == 3):
            continue
        try:
            a, b = (int(v) for v in pair)
        except (TypeError, ValueError):
            raise SynthbosError(
                f"{what}: index_range entries must be [start, stop] pairs of integers"
            ) from None
        n = data.shape[ax]
        if not 0 <= a < b <= n:
            raise SynthbosError(f"{what}: index_range {[a, b]} outside 0..{n} along {'xyz'[k]}")
        sl[ax] = slice(a, b)
    return data[tuple(sl)], spacing


def _slice(data, spacing, index, axis, *, what):
    if data.ndim != 3:
        raise SynthbosError(f"{what}: slice_index needs 3-D data, got shape {data.shape}")
    if axis not in _AXES:
        raise SynthbosError(f"{what}: axis must be 'x', 'y' or 'z', got {axis!r}")
    ax = _AXES[axis]
    n = data.shape[ax]
    i = int(index)
    if not -n <= i < n:
        raise SynthbosError(f"{what}: slice_index {i} outside 0..{n - 1} along {axis}")
    out = np.take(data, i, axis=ax)
    if spacing is not None:
        dx, dy, dz = spacing
        spacing = {"z": (dx, dy), "y": (dx, dz), "x": (dy, dz)}[axis]
    return out, spacing


# ---------------------------------------------------------------- the embedded snapshot file


def write_snapshots(path, snaps):
    """Write buoyancy snapshots (:class:`raytrace.buoyancy.BuoyancySnapshots`) to HDF5.

    Schema: ``/density`` (m, n, n) float32, each snapshot normalised to mean 1, axes (snapshot, y, x),
    gzip-compressed; ``/time`` (m,) and ``/mixedness`` (m,) float64; the generating parameters, seed
    included, as root attributes, plus ``format``, ``times`` and ``description``. Written to a
    temporary name and renamed.
    """
    path = Path(path)
    dens = np.asarray(snaps.density, dtype=np.float64)
    dens = (dens / dens.mean(axis=(1, 2), keepdims=True)).astype(np.float32)
    tmp = path.with_name(path.name + ".tmp")
    with h5py.File(tmp, "w") as h5:
        h5.attrs["format"] = SNAPSHOT_FORMAT
        h5.attrs["description"] = (
            "2-D Boussinesq buoyancy-driven variable-density mixing from segregated blobs at rest "
            "(raytrace.buoyancy); density rho/<rho>, axes (snapshot, y, x), gravity along -y"
        )
        for k, v in snaps.params.items():
            h5.attrs[k] = v
        h5.attrs["times"] = np.asarray(snaps.times, dtype=np.float64)
        h5.attrs["steps"] = int(snaps.steps)
        d = h5.create_dataset(
            "density",
            data=dens,
            compression="gzip",
            compression_opts=9,
            shuffle=True,
            chunks=(1, *dens.shape[1:]),
        )
        d.attrs["normalisation"] = "each snapshot divided by its mean"
        h5.create_dataset("time", data=np.asarray(snaps.times, dtype=np.float64))
        h5.create_dataset("mixedness", data=np.asarray(snaps.mixedness, dtype=np.float64))
    os.replace(tmp, path)


def read_snapshots(path=None, *, memory_gb=None):
    """Read a snapshot file written by :func:`write_snapshots` (the embedded one by default).

    Returns
    -------
    density : (m, n, n) float64 array
        Normalised density (mean 1), axes (snapshot, y, x), validated finite and > 0.
    times : (m,) float64 array
    attrs : dict
        The root attributes (generating parameters, seed, ...).
    """
    path = str(DEFAULT_SNAPSHOTS if path is None else path)
    if not os.path.isfile(path):
        raise SynthbosError(f"{path}: snapshot file not found")
    with _h5py_open(path) as h5:
        dens, _ = _read_h5_array(h5, "density", path, memory_gb)
        times = (
            _read_h5_array(h5, "time", path)[0] if "time" in h5 else np.arange(len(dens), dtype=np.float64)
        )
        attrs = {k: _attr(v) for k, v in h5.attrs.items()}
    dens = np.asarray(dens)
    if dens.ndim != 3:
        raise SynthbosError(f"{path}: /density must be (snapshots, ny, nx), got shape {dens.shape}")
    return check_density(dens, where=path, ndim=(3,)), np.asarray(times, dtype=np.float64), attrs
