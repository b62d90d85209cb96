"""The ``synthbos`` command: one entry point, one subcommand per job.

Each subcommand parses its arguments here and calls a library function; user errors
(``synthbos.SynthbosError``) print one line and exit with status 2, bugs keep their traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import synthbos
from synthbos import SynthbosError

__all__ = ["main"]


def _render(args):
    from raytrace import render_pair, write_pair

    out = Path(args.output)
    if not out.parent.is_dir():
        raise SynthbosError(f"output folder {out.parent} does not exist")
    pair = render_pair(args.config, device=args.device, progress=not args.quiet)
    write_pair(out, pair)
    v = pair.valid
    d = pair.displacement_px[v]
    mag = lambda a: (a**2).sum(axis=1) ** 0.5  # noqa: E731
    print(f"wrote {out}: {pair.n_dots} dots ({int(v.sum())} valid), {pair.attrs['rays_per_dot']} rays/dot, "
          f"M = {pair.attrs['magnification']:.4f}, device {pair.attrs['device']}, "
          f"{pair.attrs['render_seconds']:.2f} s")
    if len(d):
        print(f"  |displacement| px: mean {mag(d).mean():.4f}, max {mag(d).max():.4f}; "
              f"|theory (Eq. 4)| max {mag(pair.theory_px[v]).max():.4f}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="synthbos", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"synthbos {synthbos.__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("render", help="ray-trace one BOS image pair into an HDF5 pair file")
    p.add_argument("config", nargs="?", default=None, help="TOML configuration (default: the embedded default)")
    p.add_argument("-o", "--output", required=True, help="pair file to write (HDF5)")
    p.add_argument("--device", default=None, help="Warp device: cpu or cuda:0 (default: Warp's default)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_render)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except SynthbosError as err:
        print(f"synthbos: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("synthbos: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
