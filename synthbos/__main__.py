"""``python -m synthbos``: hands over to the command line."""

from synthbos.benchmarks.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
