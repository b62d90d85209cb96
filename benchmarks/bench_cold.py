"""A first run against a warm one: ``synthbos paper --quick`` with an empty Warp kernel cache, then again.

Each repeat makes a fresh kernel cache in a temporary folder (``WARP_CACHE_PATH``: the user's own cache
is neither read nor touched) and runs the command twice in a subprocess, each time into a fresh output
folder: first cold (the CPU kernels shipped with the package are copied into the empty cache,
:mod:`synthbos.shipped_kernels`; every other kernel it launches is compiled), then warm (every kernel
found in that cache). Then, in another fresh cache, once more cold with nothing shipped copied
(``SYNTHBOS_SHIPPED_KERNELS=0``: every kernel compiled, the first run of a machine the shipped objects
do not fit; ``--no-compiled`` leaves it out). The runs start alike (a new interpreter, the same
arguments and environment), so the differences are what a first run costs. Each run's wall time is kept
with the 1-minute load average before and after it (the cores may be shared) and the md5 of its
``results.csv``: a first run must give the same results as a warm one.

    python -m synthbos.benchmarks.bench_cold --repeats 2 [--json cold.json] [-- --device cuda:0]

Arguments after ``--`` are added to ``synthbos paper --quick -q -o OUT``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from synthbos import SynthbosError
from synthbos.shipped_kernels import DISABLE_ENV

__all__ = ["cold_and_warm", "main", "time_run"]

#: The command timed by default; ``{out}`` stands for the run's fresh output folder.
PAPER_QUICK = (sys.executable, "-m", "synthbos", "paper", "--quick", "-q", "-o", "{out}")


def time_run(command, *, cache, out, results="results.csv", env=None) -> dict:
    """Run ``command`` (a sequence; ``"{out}"`` in an argument stands for ``out``) with the Warp kernel
    cache ``cache`` (and the variables ``env`` added to the environment); return its wall time ``wall_s``,
    the load averages ``load_before``/``load_after`` and the md5 of ``out/results`` (``results_md5``). A
    failing command raises ``SynthbosError``."""
    argv = [str(a).replace("{out}", str(out)) for a in command]
    env = {**os.environ, **(env or {}), "WARP_CACHE_PATH": str(cache)}
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run(argv, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise SynthbosError(f"{' '.join(argv)} failed with exit status {proc.returncode}: {last}")
    digest = hashlib.md5(Path(out, results).read_bytes()).hexdigest()
    return {"wall_s": wall, "load_before": load_before, "load_after": os.getloadavg()[0], "results_md5": digest}


def cold_and_warm(command=PAPER_QUICK, *, repeats=2, workdir, results="results.csv", compiled=False) -> list[dict]:
    """Time ``command`` ``repeats`` times cold then warm (see the module's notes), under ``workdir``; with
    ``compiled``, each time also cold with no shipped kernel copied (in a cache of its own).

    Returns one dict per run: ``repeat``, ``run`` ("cold", "warm" or "compiled"), ``cache`` (the kernel
    cache it used) and the entries of :func:`time_run`.

    Examples
    --------
    >>> import sys, tempfile
    >>> script = "import os, sys; open(os.path.join(sys.argv[1], 'results.csv'), 'w').write('a,b')"
    >>> with tempfile.TemporaryDirectory() as d:
    ...     rows = cold_and_warm([sys.executable, "-c", script, "{out}"], repeats=1, workdir=d)
    >>> [row["run"] for row in rows], rows[0]["results_md5"] == rows[1]["results_md5"]
    (['cold', 'warm'], True)
    """
    rows = []
    runs = [("cold", "", None), ("warm", "", None)]  # (run, the cache's suffix, variables added)
    if compiled:
        runs.append(("compiled", "-compiled", {DISABLE_ENV: "0"}))
    for r in range(repeats):
        for run, cache_name, env in runs:
            cache = Path(workdir, f"kernel-cache-{r}{cache_name}")
            cache.mkdir(parents=True, exist_ok=True)
            out = Path(workdir, f"{run}-{r}")
            out.mkdir(parents=True)
            rows.append({"repeat": r, "run": run, "cache": str(cache),
                         **time_run(command, cache=cache, out=out, results=results, env=env)})
    return rows


def _report(rows) -> str:
    lines = ["repeat  run       wall s  load before  load after  results.csv md5"]
    lines += [f"{row['repeat']:>6}  {row['run']:<8}  {row['wall_s']:6.1f}  {row['load_before']:11.2f}  "
              f"{row['load_after']:10.2f}  {row['results_md5']}" for row in rows]
    warm = {row["repeat"]: row["wall_s"] for row in rows if row["run"] == "warm"}
    same = len({row["results_md5"] for row in rows}) == 1
    for run, words in (("cold", "first run (shipped CPU kernels) / warm run"),
                       ("compiled", "first run, every kernel compiled / warm run")):
        ratios = [row["wall_s"] / warm[row["repeat"]] for row in rows if row["run"] == run]
        if ratios:
            lines.append(f"{words}: " + ", ".join(f"{q:.2f}" for q in ratios))
    lines.append(f"results.csv identical in every run: {'yes' if same else 'NO'}")
    return "\n".join(lines)


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2, help="cold + warm pairs of runs (default 2)")
    parser.add_argument("--json", help="also write the runs here as JSON")
    parser.add_argument("--no-compiled", action="store_true",
                        help="leave out the first run with every kernel compiled (no shipped kernel copied)")
    args = parser.parse_args(own)
    if args.repeats < 1:
        raise SystemExit("--repeats must be at least 1")
    with tempfile.TemporaryDirectory(prefix="synthbos-cold-") as workdir:
        rows = cold_and_warm([*PAPER_QUICK, *extra], repeats=args.repeats, workdir=workdir,
                             compiled=not args.no_compiled)
    print(f"command: synthbos paper --quick -q -o OUT {' '.join(extra)}".rstrip())
    print(_report(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
