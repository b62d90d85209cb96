"""The one exception type of the project, in the lowest module of the base so that every module can
import it (``synthbos`` re-exports it as :class:`synthbos.SynthbosError`)."""

__all__ = ["SynthbosError"]


class SynthbosError(ValueError):
    """Bad input a user can cause: a configuration key, a missing file, a NaN in a volume.

    The command line prints the message on one line and exits with status 2; bugs raise
    other exceptions and keep their traceback.
    """

    __module__ = "synthbos"  # its public name, ``synthbos.SynthbosError`` (which pickling also finds)
