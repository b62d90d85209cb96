"""A campaign's folder: its layout, its spec file, and the stored scores.

::

    campaign.json                          what the campaign is (its spec); a re-run must match it
    pairs/s{S}_p{P}.h5                     one noise-free rendered pair per snapshot S and pair P
    scores/s{S}_p{P}_n{N}_{method}.npz     the errors of one method on one pair at noise level N %
    results.csv, results.json              the summary table, made from the scores at the end
    fig4.*, fig5.*                         the figures, made from the pairs and scores

Figures and tables read results through this module, never through the campaign runner.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from synthbos import SynthbosError, atomic_output

__all__ = ["check_folder", "load_scores", "pair_path", "save_scores", "score_path", "write_tables"]


def pair_path(folder, snapshot: int, pair: int) -> Path:
    return Path(folder) / "pairs" / f"s{snapshot}_p{pair:02d}.h5"


def score_path(folder, snapshot: int, pair: int, noise: float, method: str) -> Path:
    return Path(folder) / "scores" / f"s{snapshot}_p{pair:02d}_n{noise:g}_{method}.npz"


def check_folder(folder, spec) -> None:
    """Create the campaign folder, or check that it holds this same campaign (its ``campaign.json``)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "pairs").mkdir(exist_ok=True)
    (folder / "scores").mkdir(exist_ok=True)
    meta = folder / "campaign.json"
    mine = json.loads(json.dumps(spec.as_dict()))
    if meta.exists():
        try:
            theirs = json.loads(meta.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            theirs = None
        if theirs != mine:
            raise SynthbosError(
                f"{folder} holds a different campaign (its campaign.json differs); use another --out folder"
            )
    else:
        with atomic_output(meta) as tmp:
            tmp.write_text(json.dumps(mine, indent=2))


def save_scores(path, scores: dict) -> None:
    """One item's score arrays as an ``.npz``, written atomically."""
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **scores)


def load_scores(spec, folder, method: str, noise: float) -> dict:
    """Concatenate the scores of one method and noise level over all pairs of a campaign."""
    parts = {"error": [], "true_mag": [], "grad_error": [], "threshold": [], "measured": 0, "expected": 0}
    for s, p in spec.pair_keys():
        with np.load(score_path(folder, s, p, noise, method)) as z:
            n = len(z["error"])
            parts["error"].append(z["error"])
            parts["true_mag"].append(z["true_mag"])
            parts["grad_error"].append(z["grad_error"])
            parts["threshold"].append(np.full(n, float(z["threshold"])))
            parts["measured"] += int(z["measured"])
            parts["expected"] += int(z["expected"])
    return {k: (np.concatenate(v) if isinstance(v, list) else v) for k, v in parts.items()}


def write_tables(rows: list[dict], folder, *, stem: str = "results") -> None:
    """``{stem}.csv`` and ``{stem}.json`` in ``folder`` (atomic)."""
    folder = Path(folder)
    cols = list(rows[0].keys())
    with atomic_output(folder / f"{stem}.csv") as tmp:
        lines = [",".join(cols)]
        for r in rows:
            lines.append(",".join(f"{r[c]:.6g}" if isinstance(r[c], float) else str(r[c]) for c in cols))
        tmp.write_text("\n".join(lines) + "\n")
    with atomic_output(folder / f"{stem}.json") as tmp:
        tmp.write_text(json.dumps(rows, indent=1))
