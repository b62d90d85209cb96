"""``python -m synthbos`` and the ``synthbos`` command: hand over to the command line.

The command's entry point is :func:`main` here rather than the command line's own, so that a Ctrl-C
while the command line's modules load (a second or more on a loaded machine) ends in one line too; and
the worker processes a local Dask cluster spawns, which import the command's main module again, import
only this small one. A command interrupted while a worker thread of its own still runs (a render's Warp
launch, which a Ctrl-C cannot stop) leaves at once, without waiting for that thread.
"""

import os
import sys


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


if __name__ == "__main__":
    raise SystemExit(main())
