"""synthbos: synthetic Background Oriented Schlieren ray tracing and benchmarks.

This small package holds what every part of the project shares: the version, the one
exception type raised for input a user can get wrong, atomic output and the embedded data; and the
Python API, the everyday path of a user, loaded on first use::

    import synthbos
    pair = synthbos.render_pair({"camera": {"pixels": [128, 128]}})
    reference, gradient = synthbos.add_noise(pair, noise_percent=1.0, seed=0)
    table = synthbos.track_pair(reference, gradient, prior_xy=synthbos.nominal_prior(pair))
    synthbos.score(pair, table)  # error percentiles against the ray-traced truth

The algorithms live in the subpackages ``synthbos.raytrace``, ``synthbos.correlation``,
``synthbos.tracking`` and ``synthbos.integration``; the harness and the command line in
``synthbos.benchmarks``. In the repository those folders sit at the root and install under
``synthbos`` through setuptools' package-dir mapping.
"""

from importlib import metadata as _metadata
from importlib import resources as _resources
from pathlib import Path

from .errors import SynthbosError
from .outputs import (
    atomic_hdf5,
    atomic_output,
    check_output_file,
    check_output_folder,
    folder_lock,
    make_folder,
)

# Running from a source checkout (the repository root holds pyproject.toml and raytrace/ beside this
# folder): the subpackages are found in that checkout, so a worktree tests its own code. An installed
# wheel has them inside this folder and skips this.
_root = Path(__file__).resolve().parent.parent
if (_root / "pyproject.toml").is_file() and (_root / "raytrace" / "__init__.py").is_file():
    __path__.append(str(_root))

try:
    __version__ = _metadata.version("synthbos")
except _metadata.PackageNotFoundError:  # running from a source tree without installing
    __version__ = "0.0.0+unknown"


def data_file(*parts):
    """Path of an embedded data file (``data/`` in the repository, ``synthbos.data`` once installed).

    Found through :mod:`importlib.resources`, so an editable install, a wheel or ``pip install .``
    all find the same files from any working folder.
    """
    return Path(str(_resources.files("synthbos.data").joinpath(*parts)))


# The Python API: ``synthbos.render_pair``, ``synthbos.track_pair``, ... Each name maps to its home module
# and is imported from there on first use (PEP 562's module ``__getattr__``, the pattern of scientific
# Python's lazy_loader), so that ``import synthbos`` (which the command line and every worker process run
# first, and every subpackage for SynthbosError) does not pay for Warp, SciPy and h5py.
_API = {
    "render_pair": "synthbos.raytrace",
    "read_pair": "synthbos.raytrace",
    "write_pair": "synthbos.raytrace",
    "add_noise": "synthbos.benchmarks.api",
    "nominal_prior": "synthbos.benchmarks.api",
    "track_pair": "synthbos.tracking",
    "TrackingSettings": "synthbos.tracking",
    "DotStatus": "synthbos.tracking",
    "is_valid": "synthbos.tracking",
    "correlate_pair": "synthbos.correlation",
    "CorrelationSettings": "synthbos.correlation",
    "score": "synthbos.benchmarks.api",
    "displacement_errors": "synthbos.benchmarks.api",
    "integrate": "synthbos.benchmarks.api",
    "density_truth": "synthbos.benchmarks.api",
    "to_dataframe": "synthbos.benchmarks.api",
}


def __getattr__(name):
    home = _API.get(name)
    if home is None:
        raise AttributeError(f"module 'synthbos' has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(home), name)
    globals()[name] = value  # found directly from now on
    return value


def __dir__():
    return sorted(set(globals()) | set(_API))


# With the API's names (_API): tests/test_api.py checks that both list the same ones.
__all__ = [
    "CorrelationSettings",
    "DotStatus",
    "SynthbosError",
    "TrackingSettings",
    "__version__",
    "add_noise",
    "atomic_hdf5",
    "atomic_output",
    "check_output_file",
    "check_output_folder",
    "correlate_pair",
    "data_file",
    "density_truth",
    "displacement_errors",
    "folder_lock",
    "integrate",
    "is_valid",
    "make_folder",
    "nominal_prior",
    "read_pair",
    "render_pair",
    "score",
    "to_dataframe",
    "track_pair",
    "write_pair",
]
