"""The results table of a campaign: error percentiles and yield per method, noise, split and quantity.

Columns: ``method, noise_percent, split, quantity, n, yield, p50, p68, p90, p95, p99, rms, process_device``,
then the error budget by in-cone spread (``scoring.SPREAD_BINS``): for each bin ``B`` (``undistorted``,
``mild``, ``distorted``, ``strong``) the points of the row's set in it, ``n_B``, and their error
percentiles ``p50_B``, ``p90_B``, ``p99_B`` (missing where the bin is empty, and in density rows, which
belong to no dot: None in the rows and results.json, an empty field in results.csv). The budget
columns come last, then ``error_units``: the unit of the row's error columns (``p*``, ``rms``), which
depends on its quantity (``ERROR_UNITS``: px, px/px, kg/m^3, or 1 for errors relative to the truth's
range); ``n`` counts points and ``yield`` is a fraction. New columns come last, so readers of the older
table keep working.
"""

from __future__ import annotations

import numpy as np

from . import scoring
from .storage import DENSITY_TRUTHS, load_scores

__all__ = ["BUDGET_PERCENTILES", "DENSITY_QUANTITIES", "ERROR_UNITS", "FLOOR_METHOD", "QUANTITIES", "SPLITS",
           "floor_rows", "format_floor", "format_summary", "split_masks", "summarise", "summary_groups",
           "summary_rows"]

SPLITS = ("all", "below", "above")
QUANTITIES = ("displacement", "gradient")
# Density errors (split "all" only): kg/m^3, and relative to the truth's range (``_rel``).
DENSITY_QUANTITIES = tuple(q for t in DENSITY_TRUTHS for q in (f"density_{t}", f"density_{t}_rel"))
BUDGET_PERCENTILES = (50, 90, 99)  # the error percentiles of each in-cone spread bin
#: The method name of the density floor's rows (``floor.csv``): the pairs' exact per-dot displacements.
FLOOR_METHOD = "exact"
#: The unit of a row's error columns, by its quantity.
ERROR_UNITS = {"displacement": "px", "gradient": "px/px",
               **{q: ("1" if q.endswith("_rel") else "kg/m^3") for q in DENSITY_QUANTITIES}}


def split_masks(scores: dict) -> dict:
    """Masks of the points whose true displacement lies below / above their pair's threshold."""
    below = scores["true_mag"] < scores["threshold"]
    return {"all": np.ones_like(below), "below": below, "above": ~below}


def summarise(spec, folder, *, mapper=map) -> list[dict]:
    """One row per method, noise level, split and quantity: error percentiles and RMS, and yield.

    Displacement errors in px, gradient errors in px/px (three splits each); density errors after
    integration (split ``all``): ``density_cone`` / ``density_chief`` in kg/m^3 against the cone and
    chief-ray truths, ``density_cone_rel`` / ``density_chief_rel`` relative to the truth's range.
    Each (noise level, method) is :func:`summary_rows` of its own score files, mapped by ``mapper``
    (``map`` here; a campaign passes its processes' or cluster's, so that the groups are summarised side
    by side: the rows are the same, in the same order).
    """
    groups = summary_groups(spec)
    parts = mapper(summary_rows, [spec] * len(groups), [str(folder)] * len(groups), *zip(*groups, strict=True))
    return [row for part in parts for row in part]


def summary_groups(spec) -> list[tuple]:
    """The (noise level, method) groups of a campaign's results table, in its row order.

    Examples
    --------
    >>> from synthbos.benchmarks.spec import QUICK
    >>> summary_groups(QUICK)[:2]
    [(0.0, 'correlation'), (0.0, 'tracking')]
    """
    return [(noise, method) for noise in spec.noise_percent for method in spec.methods]


def summary_rows(spec, folder, noise, method) -> list[dict]:
    """The rows of one noise level and method (:func:`summarise`), from its score files over all pairs."""
    sc = load_scores(spec, folder, method, noise)
    masks = split_masks(sc)
    yield_ = sc["measured"] / sc["expected"] if sc["expected"] else float("nan")
    rows = []
    for quantity in QUANTITIES:
        errors = sc["error"] if quantity == "displacement" else sc["grad_error"]
        for split in SPLITS:
            rows.append(_row(method, noise, split, quantity, errors[masks[split]], yield_, sc["process_device"],
                             spread=sc["spread"][masks[split]]))
    for quantity in DENSITY_QUANTITIES:
        rows.append(_row(method, noise, "all", quantity, sc[quantity], yield_, sc["process_device"]))
    return rows


def floor_rows(parts) -> list[dict]:
    """The density floor's rows (``floor.csv`` beside ``results.csv``): one per density quantity, method
    ``FLOOR_METHOD``, noise 0, split ``all``, from each pair's :func:`benchmarks.integrate.density_floor_errors`
    pooled over the pairs as a method's rows are. A method's zero-noise density rows read against them."""
    parts = list(parts)
    return [_row(FLOOR_METHOD, 0.0, "all", q, np.concatenate([p[q] for p in parts]) if parts else np.zeros(0), 1.0,
                 "cpu") for q in DENSITY_QUANTITIES]  # fmt: skip


def format_floor(rows: list[dict]) -> str:
    """One line: the floor's density RMS against both truths, % of the range.

    Examples
    --------
    >>> print(format_floor([{"quantity": "density_cone_rel", "rms": 0.0348},
    ...                     {"quantity": "density_chief_rel", "rms": 0.1}]))
    density floor (the pairs' exact displacements, floor.csv): rho rms 3.48 % cone, 10.00 % chief
    """
    by = {r["quantity"]: r["rms"] for r in rows}
    return (f"density floor (the pairs' exact displacements, floor.csv): rho rms {100 * by['density_cone_rel']:.2f} % "
            f"cone, {100 * by['density_chief_rel']:.2f} % chief")


def _row(method, noise, split, quantity, e, yield_, device, *, spread=None):
    e = np.asarray(e, dtype=np.float64)
    fin = e[np.isfinite(e)]
    row = {"method": method, "noise_percent": noise, "split": split, "quantity": quantity,
           "n": len(fin), "yield": float(yield_)}
    row.update({f"p{k}": v for k, v in scoring.error_percentiles(e).items()})
    row["rms"] = float(np.sqrt(np.mean(fin**2))) if len(fin) else float("nan")
    row["process_device"] = device
    bins = scoring.spread_bin_masks(np.full(len(e), np.nan) if spread is None else spread)
    for name, _, _ in scoring.SPREAD_BINS:
        sel = e[bins[name]]
        row[f"n_{name}"] = int(np.isfinite(sel).sum())
        pct = scoring.error_percentiles(sel, BUDGET_PERCENTILES)
        row.update({f"p{k}_{name}": (v if row[f"n_{name}"] else None) for k, v in pct.items()})
    row["error_units"] = ERROR_UNITS[quantity]
    return row


def format_summary(rows: list[dict]) -> str:
    """Short terminal table: displacement error p50 / p90 over all points, and yield."""
    lines = [f"{'method':<17} {'noise %':>7} {'p50 px':>9} {'p90 px':>9} {'p90 below':>10} {'p90 above':>10} "
             f"{'yield':>7} {'rho rms % cone':>14} {'rho rms % chief':>15}"]
    by = {(r["method"], r["noise_percent"], r["split"], r["quantity"]): r for r in rows}
    for (method, noise, split, quantity), r in by.items():
        if split != "all" or quantity != "displacement":
            continue
        lo = by[(method, noise, "below", "displacement")]["p90"]
        hi = by[(method, noise, "above", "displacement")]["p90"]
        rc = by.get((method, noise, "all", "density_cone_rel"), {}).get("rms", float("nan"))
        rh = by.get((method, noise, "all", "density_chief_rel"), {}).get("rms", float("nan"))
        lines.append(f"{method:<17} {noise:>7g} {r['p50']:>9.4f} {r['p90']:>9.4f} {lo:>10.4f} {hi:>10.4f} "
                     f"{r['yield']:>7.3f} {100 * rc:>14.2f} {100 * rh:>15.2f}")
    return "\n".join(lines)
