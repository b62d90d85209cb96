"""A campaign's folder: its layout, its spec file, and the stored scores.

::

    campaign.json                          what the campaign is (its spec); a re-run must match it
    pairs/s{S}_p{P}.h5                     one noise-free rendered pair per snapshot S and pair P
    scores/s{S}_p{P}_n{N}_{method}.npz     the errors of one method on one pair at noise level N %, and the
                                           device that processed it (process_device)
    results.csv, results.json              the summary table, made from the scores at the end
    fig4.*, fig5.*, fig_density.*          the figures, made from the pairs and scores

Figures and tables read results through this module, never through the campaign runner.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from synthbos import SynthbosError, atomic_output

__all__ = ["DENSITY_TRUTHS", "SCORE_FIELDS", "check_folder", "load_density_map", "load_scores", "pair_path",
           "save_scores", "score_path", "write_tables"]

DENSITY_TRUTHS = ("cone", "chief")  # the renderer's two density truths: each dot's cone of rays, its chief ray


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


#: What :func:`load_scores` can give: each pooled array or count, by name.
SCORE_FIELDS = ("error", "true_mag", "grad_error", "threshold", "spread", "measured", "expected",
                *(f"density_{t}{rel}" for t in DENSITY_TRUTHS for rel in ("", "_rel")))


def load_scores(spec, folder, method: str, noise: float, fields=None) -> dict:
    """Concatenate the scores of one method and noise level over all pairs of a campaign.

    ``process_device`` is the processing device(s) of those scores, sorted and joined by "+". ``spread``
    (the in-cone spread at each point, px) is NaN for score files written before it was recorded.
    ``fields`` (names of :data:`SCORE_FIELDS`, default all) chooses what is read: a figure that draws
    a few of them reads only those arrays of the 50-600 files (each array of a file costs about as much
    to read as a small file).

    Examples
    --------
    >>> from synthbos.benchmarks.spec import QUICK
    >>> load_scores(QUICK, "no-such-folder", "tracking", 0.0, fields=("errors",))
    Traceback (most recent call last):
    ...
    ValueError: load_scores: unknown fields ['errors']; choose from SCORE_FIELDS
    """
    wanted = set(SCORE_FIELDS if fields is None else fields)
    if wanted - set(SCORE_FIELDS):
        raise ValueError(f"load_scores: unknown fields {sorted(wanted - set(SCORE_FIELDS))}; choose from SCORE_FIELDS")
    parts = {k: (0 if k in ("measured", "expected") else []) for k in SCORE_FIELDS if k in wanted}
    devices = set()
    truths = [t for t in DENSITY_TRUTHS if {f"density_{t}", f"density_{t}_rel"} & wanted]
    for s, p in spec.pair_keys():
        with np.load(score_path(folder, s, p, noise, method)) as z:
            n = len(z["error"]) if {"error", "threshold", "spread"} & wanted else 0
            for truth in truths:  # |error| in kg/m^3 and relative to the pair's truth range
                e = np.abs(z[f"density_error_{truth}"]) if f"density_error_{truth}" in z else np.zeros(0)
                if f"density_{truth}" in parts:
                    parts[f"density_{truth}"].append(e)
                if f"density_{truth}_rel" in parts:
                    rng = float(z[f"density_range_{truth}"]) if f"density_range_{truth}" in z else np.nan
                    parts[f"density_{truth}_rel"].append(e / rng if rng > 0 else np.full(len(e), np.nan))
            for k in ("error", "true_mag", "grad_error"):
                if k in parts:
                    parts[k].append(z[k])
            if "threshold" in parts:
                parts["threshold"].append(np.full(n, float(z["threshold"])))
            if "spread" in parts:
                parts["spread"].append(z["spread"] if "spread" in z else np.full(n, np.nan))  # older scores: none
            for k in ("measured", "expected"):
                if k in parts:
                    parts[k] += int(z[k])
            devices.add(str(z["process_device"]) if "process_device" in z else "unknown")
    out = {k: (np.concatenate(v) if isinstance(v, list) else v) for k, v in parts.items()}
    out["process_device"] = "+".join(sorted(devices))
    return out


def load_density_map(folder, snapshot: int, pair: int, noise: float, method: str) -> dict | None:
    """The density maps one item stored (reconstruction, both truths, grid in mm); None if it has none."""
    path = score_path(folder, snapshot, pair, noise, method)
    if not path.exists():
        return None
    with np.load(path) as z:
        if "density_map" not in z or z["density_map"].size == 0:
            return None
        return {k: z[k] for k in ("density_map", "density_truth_cone", "density_truth_chief", "density_x_mm",
                                  "density_y_mm")}


def write_tables(rows: list[dict], folder, *, stem: str = "results") -> None:
    """``{stem}.csv`` and ``{stem}.json`` in ``folder`` (atomic); a None value is an empty CSV field (JSON null)."""
    folder = Path(folder)
    cols = list(rows[0].keys())
    with atomic_output(folder / f"{stem}.csv") as tmp:
        lines = [",".join(cols)]
        for r in rows:
            lines.append(",".join(f"{r[c]:.6g}" if isinstance(r[c], float) else ("" if r[c] is None else str(r[c]))
                                  for c in cols))
        tmp.write_text("\n".join(lines) + "\n")
    with atomic_output(folder / f"{stem}.json") as tmp:
        tmp.write_text(json.dumps(rows, indent=1))
