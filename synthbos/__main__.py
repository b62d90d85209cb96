"""``python -m synthbos``: hands over to the command line."""

import sys

if __name__ == "__main__":
    try:
        from synthbos.benchmarks.cli import main
    except KeyboardInterrupt:  # Ctrl-C while the modules load: one line, as in a command
        print("synthbos: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
    raise SystemExit(main())
