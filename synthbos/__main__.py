"""``python -m synthbos`` and the ``synthbos`` command: hand over to the command line.

The command's entry point is :func:`main` here rather than the command line's own, so that a Ctrl-C
while the command line's modules load (a second or more on a loaded machine) ends in one line too; and
the worker processes a local Dask cluster spawns, which import the command's main module again, import
only this small one.
"""

import sys


def main(argv=None) -> int:
    """Load the command line and run it; a Ctrl-C while it loads ends in one line and status 130."""
    try:
        from synthbos.benchmarks.cli import main as cli_main
    except KeyboardInterrupt:  # Ctrl-C while the modules load: one line, as in a command
        print("synthbos: interrupted", file=sys.stderr)
        return 130
    return cli_main(argv)


if __name__ == "__main__":
    raise SystemExit(main())
