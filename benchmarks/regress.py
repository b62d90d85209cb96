"""``synthbos regress``: guard every method's accuracy with a small fixed campaign.

The campaign ``REGRESS`` (two snapshots, one 256 x 256 pair each, noise 0 and 3 %, all methods) is
run from scratch and its error percentiles are compared with the baseline in
``data/baselines/regress.json``. A percentile is worse when it exceeds the baseline by more than
``RTOL`` relative plus ``ATOL`` absolute; a yield is worse when it drops by more than
``YIELD_DROP``. Everything is seeded, so an unchanged code base reproduces the baseline exactly;
the tolerances only absorb library round-off across machines. ``--update`` rewrites the baseline on
purpose.
"""

from __future__ import annotations

import json
import math
import tempfile
from dataclasses import replace
from pathlib import Path

from synthbos import SynthbosError, atomic_output, check_output_folder, data_file

from .campaign import run_campaign
from .spec import REGRESS

__all__ = ["ATOL", "BASELINE", "RTOL", "YIELD_DROP", "compare_to_baseline", "run_regress"]

BASELINE = data_file("baselines", "regress.json")
RTOL = 0.05
ATOL = {"displacement": 2e-4, "gradient": 2e-5, "density_cone": 1e-5, "density_chief": 1e-5,
        "density_cone_rel": 2e-4, "density_chief_rel": 2e-4}
YIELD_DROP = 0.005
PCTS = ("p50", "p68", "p90", "p95", "p99")


def _key(row):
    return (row["method"], float(row["noise_percent"]), row["split"], row["quantity"])


def compare_to_baseline(rows, baseline_rows):
    """Every (method, noise, split, quantity, percentile or yield) that got worse, as readable lines."""
    base = {_key(r): r for r in baseline_rows}
    problems = []
    for row in rows:
        key = _key(row)
        if key not in base:
            problems.append(f"{key[0]} noise {key[1]:g}% {key[2]} {key[3]}: not in the baseline (run --update)")
            continue
        b = base[key]
        name = f"{key[0]} noise {key[1]:g}% {key[2]} threshold {key[3]}"
        for p in PCTS:
            new, old = float(row[p]), float(b[p])
            if math.isnan(new) and math.isnan(old):
                continue
            if math.isnan(new) or (not math.isnan(old) and new > old * (1 + RTOL) + ATOL[key[3]]):
                problems.append(f"{name} {p}: {new:.6g} vs baseline {old:.6g}")
        if float(row["yield"]) < float(b["yield"]) - YIELD_DROP:
            problems.append(f"{name} yield: {row['yield']:.4f} vs baseline {b['yield']:.4f}")
    return problems


def run_regress(*, update=False, out=None, baseline=BASELINE, workers=None, progress=True, scheduler=None,
                wait=False, methods=None, stack=None, stacks=None):
    """Run the regression campaign; return (rows, problems). With ``update`` write the baseline instead.

    ``methods`` (names) runs those instead of the default ones and compares only their rows; with
    ``update`` their rows replace theirs in the baseline and the other methods' rows stay (also without
    ``methods``), so a
    plugin's rows enter a baseline only when asked for. ``stack`` > 0 tracks the tracking items in stacks
    of that many pairs (``run_campaign``; on the CPU, as a GPU campaign does), ``stacks`` logs them.
    """
    baseline = Path(baseline)
    if not update and not baseline.is_file():
        raise SynthbosError(f"no regression baseline at {baseline}; create it with 'synthbos regress --update'")
    if isinstance(scheduler, str) and scheduler != "local" and out is None:
        raise SynthbosError("with a joined --scheduler give --out: a folder the workers see at the same path")
    if out is not None:
        check_output_folder(out)
    spec = REGRESS if methods is None else replace(REGRESS, methods=tuple(methods))
    with tempfile.TemporaryDirectory(prefix="synthbos-regress-") as tmp:
        folder = Path(out) if out else Path(tmp)
        rows = run_campaign(spec, folder, device="cpu", workers=workers, progress=progress, figures=False,
                            scheduler=scheduler, wait=wait, stack=stack, stacks=stacks)
    if update:
        kept = []
        if baseline.is_file():
            kept = [r for r in json.loads(baseline.read_text())["rows"] if r["method"] not in spec.methods]
        merged = kept + rows
        names = tuple(dict.fromkeys(r["method"] for r in merged))
        baseline.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(baseline) as tmp_file:
            tmp_file.write_text(json.dumps({"campaign": replace(spec, methods=names).as_dict(), "rows": merged},
                                           indent=1))
        return rows, []
    base = json.loads(baseline.read_text())
    return rows, compare_to_baseline(rows, base["rows"])
