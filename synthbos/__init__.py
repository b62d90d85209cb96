"""synthbos: synthetic Background Oriented Schlieren ray tracing and benchmarks.

This small package holds what every part of the project shares: the version and the one
exception type raised for input a user can get wrong. The algorithms live in the sibling
packages ``raytrace``, ``correlation``, ``tracking`` and the harness in ``benchmarks``.
"""

from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("synthbos")
except _metadata.PackageNotFoundError:  # running from a source tree without installing
    __version__ = "0.0.0+unknown"


class SynthbosError(ValueError):
    """Bad input a user can cause: a configuration key, a missing file, a NaN in a volume.

    The command line prints the message on one line and exits with status 2; bugs raise
    other exceptions and keep their traceback.
    """


__all__ = ["SynthbosError", "__version__"]
