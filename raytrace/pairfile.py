"""The BOS pair: the in-memory result of a render and its HDF5 file format (reader and writer).

File layout
-----------
``/images/reference``, ``/images/gradient``
    (H, W) float32, noise-free.
``/dots/target_xy_m`` (N, 2)
    Dot centres on the target plane, metres.
``/dots/reference_px``, ``/dots/gradient_px``, ``/dots/displacement_px``, ``/dots/theory_px`` (N, 2)
    Ray-mean image positions without and with the flow, their difference (the exact displacement)
    and Eq. 4's theoretical displacement; x = column, y = row, pixel centres at integer coordinates.
``/dots/theory_cone_px`` (N, 2)
    Eq. 4 averaged over the rays the renderer traced for the dot (its emission points and aperture
    points, each ray taken straight): the displacement the camera's cone of rays sees in the
    weak-deflection limit. In both Eq. 4 truths each depth z counts with its own lever arm z / Z_D and
    the ray's slope u (integrand (grad_xy n - u dn/dz)(1 + |u|^2)), so that they hold for 3-D fields
    too; through a field whose gradient does not vary along the ray this is Eq. 4 as printed.
``/dots/density_cone_kg_m3``, ``/dots/density_chief_kg_m3`` (N,)
    The density averaged over the volume's depth, averaged over the dot's cone of rays, and along its
    chief ray (where a ray passes beside the volume, the volume's edge density continued outwards: the
    renderer sees no gradient there).
``/dots/ray_covariance_px2``, ``/dots/ray_covariance_reference_px2`` (N, 3)
    [var_x, var_y, cov_xy] of the landing positions of the dot's rays about their mean (the ray-mean
    position above), in the gradient image and in the reference image, px^2. The reference's is the
    dot's own disk and any defocus or thick-lens spread (zero for a point dot through a thin lens, up
    to float32 rounding); what the gradient's adds is the spread the flow makes inside the aperture's
    cone (:func:`in_cone_spread_px`).
``/dots/ray_third_moment_px3`` (N, 4)
    [m30, m21, m12, m03], the central third moments E[dx^a dy^b] (a + b = 3, dx, dy about the mean) of
    the gradient image's landing positions, px^3: the skew of the distorted dot.
``/dots/valid`` (N,) bool
    Every ray of the dot reached the sensor in both images.
root attributes
    ``config`` (the full configuration as TOML text), ``magnification``, ``version``, ``device``,
    ``render_seconds``, ``n0``, ``spot_diameter_px``, ``sign_convention``, ``z_d_m``, ``z_stop_m``,
    ``pixel_pitch_m``, ``principal_point_x_px``, ``principal_point_y_px``, ``volume_depth_m``,
    ``volume_centre_x_m``, ``volume_centre_y_m`` (the volume's lateral offset off the optical axis),
    ``gladstone_dale_m3_per_kg``, ``ambient_density_kg_m3`` (all scalars).

``/images/y``, ``/images/x``, ``/dots/dot``, ``/dots/component``, ``/dots/covariance``, ``/dots/moment``
    HDF5 dimension scales (the pixel centres, the dot index, the column labels), attached to the datasets
    above, so that ``xarray.open_dataset(path, engine="h5netcdf", group="dots")`` (or ``group="images"``)
    shows named dimensions ``(dot, component)``, ``(y, x)``.

Every dataset carries ``units`` and ``description`` attributes, from ``PAIR_DATASETS``. Files written
before the cone truth existed read with ``theory_cone_px`` and the two densities set to None; files
written before the ray moments existed read with the three moment fields set to None.

Sign convention: the image is upright (columns grow with target x, rows with target y) and a
displacement is gradient-image position minus reference-image position. A ray bends towards higher
density, so a dot appears shifted *down* the density gradient: Eq. 4 reads
dX = -(M Z_D / n0) * integral of grad n dz with M > 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from synthbos import SynthbosError, atomic_hdf5

__all__ = [
    "PAIR_DATASETS", "SIGN_CONVENTION", "Pair", "describe_datasets", "in_cone_spread_px", "is_scale", "name_dimensions",
    "read_pair", "write_pair",
]

SIGN_CONVENTION = (
    "upright image (x = column grows with target x, y = row grows with target y); "
    "displacement = gradient - reference; dots shift down the density gradient: "
    "dX = -(M Z_D / n0) * integral(grad n) dz"
)

_DOT_SETS = ("target_xy_m", "reference_px", "gradient_px", "displacement_px", "theory_px")
_TRUTH_SETS = ("theory_cone_px", "density_cone_kg_m3", "density_chief_kg_m3")
# Per-dot ray moments: name -> number of columns.
_MOMENT_SETS = {"ray_covariance_px2": 3, "ray_covariance_reference_px2": 3, "ray_third_moment_px3": 4}

@dataclass
class Pair:
    """A rendered BOS image pair with its per-dot ground truth."""

    reference: np.ndarray
    gradient: np.ndarray
    target_xy_m: np.ndarray
    reference_px: np.ndarray
    gradient_px: np.ndarray
    displacement_px: np.ndarray
    theory_px: np.ndarray
    valid: np.ndarray
    theory_cone_px: np.ndarray | None = None
    density_cone_kg_m3: np.ndarray | None = None
    density_chief_kg_m3: np.ndarray | None = None
    ray_covariance_px2: np.ndarray | None = None
    ray_covariance_reference_px2: np.ndarray | None = None
    ray_third_moment_px3: np.ndarray | None = None
    attrs: dict = field(default_factory=dict)

    @property
    def n_dots(self) -> int:
        return len(self.target_xy_m)


# The pair file's datasets: path -> (units, description). The writer attaches both to every dataset as
# attributes; a dataset added to the file gets its row here.
PAIR_DATASETS = {
    "images/reference": ("a.u.", "reference image (no flow), noise-free; a lone point dot peaks at the "
                                 "root attribute peak_intensity; row = y, column = x"),
    "images/gradient": ("a.u.", "gradient image (through the density volume), noise-free, same scale and "
                                "ray set as the reference image"),
    "dots/target_xy_m": ("m", "dot centres on the target plane (x, y), z = 0, optical axis at (0, 0)"),
    "dots/reference_px": ("px", "ray-mean image position (x = column, y = row) of each dot without the flow"),
    "dots/gradient_px": ("px", "ray-mean image position (x = column, y = row) of each dot through the flow"),
    "dots/displacement_px": ("px", "exact dot displacement, gradient_px - reference_px (x, y)"),
    "dots/theory_px": ("px", "Eq. 4's displacement -(M Z_D / n0) * integral(grad n) dz along the chief ray, each "
                             "depth z weighted by its lever arm z / Z_D and the ray's obliquity (x, y)"),
    "dots/theory_cone_px": ("px", "Eq. 4's displacement (as theory_px, depth-weighted) averaged over the rays traced "
                                  "for the dot (its dot and aperture samples, each ray straight): the aperture's "
                                  "cone (x, y)"),
    "dots/density_cone_kg_m3": ("kg/m^3", "density averaged over the volume's depth and over the dot's cone of rays"),
    "dots/density_chief_kg_m3": ("kg/m^3", "density averaged over the volume's depth along the dot's chief ray"),
    "dots/ray_covariance_px2": ("px^2", "covariance [var_x, var_y, cov_xy] of the landing positions of the dot's "
                                        "rays in the gradient image about their mean: the dot's spread"),
    "dots/ray_covariance_reference_px2": ("px^2", "covariance [var_x, var_y, cov_xy] of the landing positions of "
                                                  "the dot's rays in the reference image about their mean (the "
                                                  "dot's disk, defocus and lens spread)"),
    "dots/ray_third_moment_px3": ("px^3", "central third moments [m30, m21, m12, m03] = E[dx^a dy^b] of the landing "
                                          "positions of the dot's rays in the gradient image: the skew"),
    "dots/valid": ("1", "true where every ray of the dot reached the sensor in both images"),
}


def in_cone_spread_px(pair: Pair) -> np.ndarray:
    """RMS spread the flow adds to each dot's image inside the aperture's cone of rays, px.

    ``sqrt(max(0, (var_x + var_y) of the gradient image - (var_x + var_y) of the reference image))``
    from the pair's ray covariances: 0 where every ray of a dot is displaced alike (a linear field, a
    uniform medium), large where the flow varies across the cone (a sharp interface).

    Parameters
    ----------
    pair : Pair
        A rendered pair (``render_pair``) or one read back (``read_pair``).

    Returns
    -------
    (N,) float64
        The spread, px; NaN for every dot where the pair holds no ray covariances (a file written
        before they were recorded) and where a dot's are NaN.

    Examples
    --------
    >>> import numpy as np
    >>> pair = Pair(reference=np.zeros((2, 2)), gradient=np.zeros((2, 2)), target_xy_m=np.zeros((2, 2)),
    ...             reference_px=np.zeros((2, 2)), gradient_px=np.zeros((2, 2)),
    ...             displacement_px=np.zeros((2, 2)), theory_px=np.zeros((2, 2)), valid=np.ones(2, bool),
    ...             ray_covariance_px2=np.array([[0.02, 0.05, 0.01], [0.01, 0.0, 0.0]]),
    ...             ray_covariance_reference_px2=np.array([[0.01, 0.02, 0.0], [0.01, 0.0, 0.0]]))
    >>> in_cone_spread_px(pair)
    array([0.2, 0. ])
    >>> pair.ray_covariance_px2 = None
    >>> in_cone_spread_px(pair)
    array([nan, nan])
    """
    if pair.ray_covariance_px2 is None or pair.ray_covariance_reference_px2 is None:
        return np.full(pair.n_dots, np.nan)
    grad = np.asarray(pair.ray_covariance_px2, dtype=np.float64)
    ref = np.asarray(pair.ray_covariance_reference_px2, dtype=np.float64)
    added = (grad[:, 0] + grad[:, 1]) - (ref[:, 0] + ref[:, 1])
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.maximum(added, 0.0))


def describe_datasets(h5file, schema: dict) -> None:
    """Attach ``units`` and ``description`` from ``schema`` (path -> (units, description)) to the file's datasets."""
    for name, (units, description) in schema.items():
        if name in h5file:
            h5file[name].attrs["units"] = units
            h5file[name].attrs["description"] = description


def name_dimensions(group, scales: dict, dims: dict) -> None:
    """Name the dimensions of a group's datasets with HDF5 dimension scales, so that netCDF readers
    (h5netcdf, xarray) see named dimensions with coordinates instead of phony ones.

    Parameters
    ----------
    group : h5py.Group
        The group (or file) that holds the datasets; each scale is written in it.
    scales : dict
        Dimension name -> ``(values, units, description)``: a 1-D dataset of that name is written (or,
        when ``values`` is None, the group's existing 1-D dataset of that name is used) and made a scale.
    dims : dict
        Dataset name (relative to ``group``) -> the names of its dimensions, one per axis; a dataset
        that is absent, or whose axis lengths differ from its scales', is left unnamed.
    """
    for name, (values, units, description) in scales.items():
        ds = group[name] if values is None else group.create_dataset(name, data=values)
        ds.attrs["units"] = units
        ds.attrs["description"] = description
        ds.make_scale(name)
    for name, names in dims.items():
        ds = group.get(name)
        if not isinstance(ds, h5py.Dataset) or ds.ndim != len(names):
            continue
        if any(ds.shape[axis] != len(group[d]) for axis, d in enumerate(names)):
            continue
        for axis, d in enumerate(names):
            ds.dims[axis].attach_scale(group[d])


def is_scale(ds) -> bool:
    """True for a dimension scale written by :func:`name_dimensions` (a coordinate, not data)."""
    return isinstance(ds, h5py.Dataset) and h5py.h5ds.is_scale(ds.id)


#: Labels of the pair file's small dimensions (the columns of the (N, k) dot sets).
PAIR_LABELS = {
    "component": (("x", "y"), "the (x, y) components of the (N, 2) dot sets: x = column, y = row"),
    "covariance": (("var_x", "var_y", "cov_xy"), "the entries [var_x, var_y, cov_xy] of the ray covariances"),
    "moment": (("m30", "m21", "m12", "m03"), "the central third moments [m30, m21, m12, m03] = E[dx^a dy^b]"),
}


def _pair_dimensions(f) -> None:
    """The pair file's named dimensions: (y, x) of the images, (dot, component|covariance|moment) of the dots."""
    h, w = f["images/reference"].shape
    name_dimensions(f["images"], {
        "y": (np.arange(h, dtype=np.float64), "px", "row coordinate y of the image's pixel centres"),
        "x": (np.arange(w, dtype=np.float64), "px", "column coordinate x of the image's pixel centres"),
    }, {"reference": ("y", "x"), "gradient": ("y", "x")})
    dots = f["dots"]
    n = len(dots["valid"])
    scales = {"dot": (np.arange(n, dtype=np.int64), "1", "dot index, the row of every /dots dataset (the "
                                                         "dot_id of a result tracked with this pair's prior)")}
    scales.update({name: (np.array(labels, dtype=h5py.string_dtype()), "1", description)
                   for name, (labels, description) in PAIR_LABELS.items()})
    dims = {name: ("dot", "component") for name in (*_DOT_SETS, "theory_cone_px")}
    dims.update({name: ("dot",) for name in ("density_cone_kg_m3", "density_chief_kg_m3", "valid")})
    dims.update({name: ("dot", "covariance" if columns == 3 else "moment") for name, columns in _MOMENT_SETS.items()})
    name_dimensions(dots, scales, dims)


def write_pair(path, pair: Pair) -> Path:
    """Write a pair file atomically (built in memory, see ``synthbos.atomic_hdf5``); return its path.

    Every dataset carries ``units`` and ``description`` attributes (``PAIR_DATASETS``); the pair's
    attributes (its configuration, the set-up's numbers) become the file's root attributes.

    Examples
    --------
    >>> import pathlib
    >>> import tempfile
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = synthbos.write_pair(pathlib.Path(folder) / "pair.h5", pair)
    ...     print(path.name, path.stat().st_size > 0)
    pair.h5 True
    """
    path = Path(path)
    with atomic_hdf5(path) as f:
        img = f.create_group("images")
        img.create_dataset("reference", data=np.asarray(pair.reference, np.float32), compression="gzip")
        img.create_dataset("gradient", data=np.asarray(pair.gradient, np.float32), compression="gzip")
        dots = f.create_group("dots")
        for name in (*_DOT_SETS, *_TRUTH_SETS, *_MOMENT_SETS):
            if getattr(pair, name) is not None:
                dots.create_dataset(name, data=np.asarray(getattr(pair, name), np.float64))
        dots.create_dataset("valid", data=np.asarray(pair.valid, bool))
        for key, value in pair.attrs.items():
            f.attrs[key] = value
        f.attrs["sign_convention"] = SIGN_CONVENTION
        describe_datasets(f, PAIR_DATASETS)
        _pair_dimensions(f)
    return path


def read_pair(path) -> Pair:
    """Read a pair file written by ``write_pair``; a missing or malformed file raises SynthbosError.

    Examples
    --------
    >>> import pathlib
    >>> import tempfile
    >>> import numpy as np
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     back = synthbos.read_pair(synthbos.write_pair(pathlib.Path(folder) / "pair.h5", pair))
    >>> bool(np.array_equal(back.gradient, pair.gradient)), back.n_dots == pair.n_dots
    (True, True)
    """
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"pair file {path} does not exist")
    try:
        with h5py.File(path, "r") as f:
            missing = [f"/images/{n}" for n in ("reference", "gradient") if f"images/{n}" not in f]
            missing += [f"/dots/{n}" for n in (*_DOT_SETS, "valid") if f"dots/{n}" not in f]
            if missing:
                raise SynthbosError(f"{path} is not a synthbos pair file: missing {', '.join(missing)}")
            _check_layout(f, path)
            kwargs = {n: f[f"dots/{n}"][()] for n in _DOT_SETS}
            optional = (*_TRUTH_SETS, *_MOMENT_SETS)
            kwargs.update({n: (f[f"dots/{n}"][()] if f"dots/{n}" in f else None) for n in optional})
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            return Pair(
                reference=f["images/reference"][()], gradient=f["images/gradient"][()],
                valid=f["dots/valid"][()].astype(bool), attrs=attrs, **kwargs,
            )
    except OSError as err:
        raise SynthbosError(f"cannot read pair file {path}: {err}") from None


def _check_layout(f, path):
    """Shapes, types and the ``config`` attribute of an open pair file, before anything is read."""
    import tomllib

    def dataset(name):
        obj = f[name]
        if not isinstance(obj, h5py.Dataset):
            raise SynthbosError(f"{path} is not a synthbos pair file: /{name} is a group, not a dataset")
        if obj.dtype.kind not in "fiub":
            raise SynthbosError(f"{path}: /{name} holds {obj.dtype}, not numbers")
        return obj

    ref, grad = dataset("images/reference"), dataset("images/gradient")
    if ref.ndim != 2 or ref.shape != grad.shape or min(ref.shape) < 2:
        raise SynthbosError(
            f"{path}: /images/reference and /images/gradient must be 2-D images of one shape, "
            f"got {ref.shape} and {grad.shape}"
        )
    n = None
    for name in _DOT_SETS:
        obj = dataset(f"dots/{name}")
        if obj.ndim != 2 or obj.shape[1] != 2 or (n is not None and obj.shape[0] != n):
            raise SynthbosError(f"{path}: /dots/{name} must be (N, 2) like the other dot sets, got shape {obj.shape}")
        n = obj.shape[0]
    for name, columns in _MOMENT_SETS.items():
        if f"dots/{name}" in f and dataset(f"dots/{name}").shape != (n, columns):
            raise SynthbosError(f"{path}: /dots/{name} must be ({n}, {columns}), got shape {f['dots/' + name].shape}")
    if dataset("dots/valid").shape != (n,):
        raise SynthbosError(f"{path}: /dots/valid must be ({n},), got shape {f['dots/valid'].shape}")
    config = f.attrs.get("config")
    if isinstance(config, bytes):
        config = config.decode("utf-8", "replace")
    if not isinstance(config, str):
        raise SynthbosError(f"{path} is not a synthbos pair file: its 'config' attribute is missing or not text")
    try:
        limits = tomllib.loads(config).get("limits")
    except tomllib.TOMLDecodeError as err:
        raise SynthbosError(f"{path}: its 'config' attribute is not valid TOML ({err})") from None
    _check_memory(f, path, limits)


def _check_memory(f, path, limits):
    """The declared sizes of the datasets ``read_pair`` reads, against the file's ``limits.memory_gb``."""
    from .checks import check_file_memory

    memory = limits.get("memory_gb") if isinstance(limits, dict) else None
    if isinstance(memory, bool) or not isinstance(memory, int | float) or not 0 < memory < float("inf"):
        memory = None
    names = ["images/reference", "images/gradient", *(f"dots/{n}" for n in (*_DOT_SETS, *_TRUTH_SETS, "valid"))]
    check_file_memory([f[n] for n in names if n in f and isinstance(f[n], h5py.Dataset)], f"pair file {path}",
                      memory_gb=memory)
