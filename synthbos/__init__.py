"""synthbos: synthetic Background Oriented Schlieren ray tracing and benchmarks.

This small package holds what every part of the project shares: the version, the one
exception type raised for input a user can get wrong, atomic output and the embedded data.
The algorithms live in the subpackages ``synthbos.raytrace``, ``synthbos.correlation``,
``synthbos.tracking`` and ``synthbos.integration``; the harness and the command line in
``synthbos.benchmarks``. In the repository those folders sit at the root and install under
``synthbos`` through setuptools' package-dir mapping.
"""

from importlib import metadata as _metadata
from importlib import resources as _resources
from pathlib import Path

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


class SynthbosError(ValueError):
    """Bad input a user can cause: a configuration key, a missing file, a NaN in a volume.

    The command line prints the message on one line and exits with status 2; bugs raise
    other exceptions and keep their traceback.
    """


from .outputs import (  # noqa: E402  (needs SynthbosError above)
    atomic_hdf5,
    atomic_output,
    check_output_file,
    check_output_folder,
    folder_lock,
    make_folder,
)


def data_file(*parts):
    """Path of an embedded data file (``data/`` in the repository, ``synthbos.data`` once installed).

    Found through :mod:`importlib.resources`, so an editable install, a wheel or ``pip install .``
    all find the same files from any working folder.
    """
    return Path(str(_resources.files("synthbos.data").joinpath(*parts)))


__all__ = [
    "SynthbosError",
    "__version__",
    "atomic_hdf5",
    "atomic_output",
    "check_output_file",
    "check_output_folder",
    "data_file",
    "folder_lock",
    "make_folder",
]
