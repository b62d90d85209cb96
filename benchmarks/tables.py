"""The results table of a campaign: error percentiles and yield per method, noise, split and quantity."""

from __future__ import annotations

import numpy as np

from . import scoring
from .storage import load_scores

__all__ = ["QUANTITIES", "SPLITS", "format_summary", "split_masks", "summarise"]

SPLITS = ("all", "below", "above")
QUANTITIES = ("displacement", "gradient")


def split_masks(scores: dict) -> dict:
    """Masks of the points whose true displacement lies below / above their pair's threshold."""
    below = scores["true_mag"] < scores["threshold"]
    return {"all": np.ones_like(below), "below": below, "above": ~below}


def summarise(spec, folder) -> list[dict]:
    """One row per method, noise level, split and quantity: error percentiles (px) and yield."""
    rows = []
    for noise in spec.noise_percent:
        for method in spec.methods:
            sc = load_scores(spec, folder, method, noise)
            masks = split_masks(sc)
            yield_ = sc["measured"] / sc["expected"] if sc["expected"] else float("nan")
            for quantity in QUANTITIES:
                errors = sc["error"] if quantity == "displacement" else sc["grad_error"]
                for split in SPLITS:
                    e = errors[masks[split]]
                    row = {"method": method, "noise_percent": noise, "split": split, "quantity": quantity,
                           "n": int(np.isfinite(e).sum()), "yield": float(yield_)}
                    row.update({f"p{k}": v for k, v in scoring.error_percentiles(e).items()})
                    rows.append(row)
    return rows


def format_summary(rows: list[dict]) -> str:
    """Short terminal table: displacement error p50 / p90 over all points, and yield."""
    lines = [f"{'method':<13} {'noise %':>7} {'p50 px':>9} {'p90 px':>9} {'p90 below':>10} {'p90 above':>10} "
             f"{'yield':>7}"]
    by = {(r["method"], r["noise_percent"], r["split"], r["quantity"]): r for r in rows}
    for (method, noise, split, quantity), r in by.items():
        if split != "all" or quantity != "displacement":
            continue
        lo = by[(method, noise, "below", "displacement")]["p90"]
        hi = by[(method, noise, "above", "displacement")]["p90"]
        lines.append(f"{method:<13} {noise:>7g} {r['p50']:>9.4f} {r['p90']:>9.4f} {lo:>10.4f} {hi:>10.4f} "
                     f"{r['yield']:>7.3f}")
    return "\n".join(lines)
