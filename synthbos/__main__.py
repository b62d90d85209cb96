"""``python -m synthbos`` and the ``synthbos`` command: hand over to the command line.

The command's entry point is :func:`main` here rather than the command line's own, so that a Ctrl-C
while the command line's modules load (a second or more on a loaded machine) ends in one line too; and
the worker processes a local Dask cluster spawns, which import the command's main module again, import
only this small one. A command interrupted while a worker thread of its own still runs (a render's Warp
launch, which a Ctrl-C cannot stop) leaves at once, without waiting for that thread.
"""

import atexit
import os
import sys

_STATUS: list[int] = []  # the command's exit status, once it has returned


def _leave() -> None:
    """The last exit handler (registered before the command line's modules register theirs): once a
    command has returned, every other handler has run (its worker processes joined, its threads ended);
    flush and leave without the interpreter's teardown of its thousand modules and objects, which took
    1-1.6 s at the end of every command (measured on the 2-core machine)."""
    if not _STATUS:
        return
    if "logging" in sys.modules:  # its handler was registered before this one, so it would run after it
        sys.modules["logging"].shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(_STATUS[0])


atexit.register(_leave)


def main(argv=None) -> int:
    """Load the command line and run it; a Ctrl-C while it loads ends in one line and status 130."""
    try:
        from synthbos.benchmarks.cli import main as cli_main
        from synthbos.benchmarks.cli import work_abandoned
    except KeyboardInterrupt:  # Ctrl-C while the modules load: one line, as in a command
        print("synthbos: interrupted", file=sys.stderr)
        return 130
    status = cli_main(argv)
    if work_abandoned():
        # A thread abandoned inside a long C call: the interpreter's exit would wait for it (measured 5-6 s
        # of a render's Warp launch); its result is not wanted, so leave now.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    return status


def command() -> int:
    """The ``synthbos`` command and ``python -m synthbos``: :func:`main`, whose status the last exit
    handler then leaves with (:func:`_leave`). Called in a process of its own only: :func:`main` is the
    one to call from Python."""
    try:
        status = main()
    except SystemExit as done:  # argparse's --help and usage errors
        code = done.code
        _STATUS.append(code if isinstance(code, int) else int(code is not None))
        raise
    _STATUS.append(int(status))
    return status


if __name__ == "__main__":
    raise SystemExit(command())
