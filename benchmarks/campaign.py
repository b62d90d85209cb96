"""Campaigns: render BOS pairs through known density fields, process them with every method, score.

A campaign lives in one folder::

    campaign.json          what the campaign is (its spec); a re-run must match it
    pairs/s{S}_p{P}.h5     one noise-free rendered pair per snapshot S and pair P
    scores/s{S}_p{P}_n{N}_{method}.npz   the errors of one method on one pair at noise level N %
    results.csv, results.json, fig4.png, fig5.png   made from the scores at the end

Each pair and each score is its own file written atomically, so a re-run skips finished work and an
interrupted run loses only the items in progress. Scoring runs in parallel over CPU cores; rendering
runs in parallel worker processes on the CPU, or in this process on a GPU.
"""

from __future__ import annotations

import copy
import json
import os
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from synthbos import SynthbosError, atomic_output

from . import scoring
from .process import METHODS, run_method

__all__ = ["FULL", "QUICK", "REGRESS", "CampaignSpec", "run_campaign", "score_pair", "summarise"]

# The paper's set-up (Rajendran, Bane & Vlachos 2019, section 4).
PAPER_CONFIG = {
    "camera": {"pixels": [512, 512], "pixel_pitch_um": 10.0, "focal_length_mm": 105.0, "f_number": 11.0},
    "target": {"distance_mm": 1000.0, "dots_per_32px": 20.0, "dot_diameter_px": 3.0, "pattern": "random"},
    "volume": {"source": "slice", "distance_from_target_mm": 250.0, "size_mm": [32.0, 32.0, 10.0]},
    "rays": {"per_dot": 10_000},
}


@dataclass(frozen=True)
class CampaignSpec:
    """What a campaign renders, how it processes, and the seeds that make it repeatable."""

    name: str
    snapshots: tuple = (0, 1, 2, 3, 4)
    pairs_per_snapshot: int = 10
    noise_percent: tuple = (0.0, 1.0, 3.0, 5.0)
    methods: tuple = METHODS
    config: dict = field(default_factory=lambda: copy.deepcopy(PAPER_CONFIG))
    seed: int = 2019
    correlation: dict = field(default_factory=dict)  # CorrelationSettings overrides
    tracking: dict = field(default_factory=dict)  # TrackingSettings overrides

    def as_dict(self) -> dict:
        d = asdict(self)
        d["snapshots"], d["noise_percent"], d["methods"] = list(self.snapshots), list(self.noise_percent), list(
            self.methods
        )
        return d

    def with_config(self, overrides: dict) -> CampaignSpec:
        """A copy whose render configuration has ``overrides`` (tables of keys) merged in."""
        cfg = copy.deepcopy(self.config)
        for table, values in overrides.items():
            cfg.setdefault(table, {}).update(values)
        return replace(self, config=cfg)

    def pair_keys(self):
        return [(s, p) for s in self.snapshots for p in range(self.pairs_per_snapshot)]

    def pair_config(self, snapshot: int, pair: int) -> dict:
        cfg = copy.deepcopy(self.config)
        if cfg.get("volume", {}).get("source", "slice") == "slice":
            cfg.setdefault("volume", {})["snapshot"] = snapshot
        cfg.setdefault("target", {})["seed"] = self._seed("pattern", snapshot, pair)
        cfg.setdefault("rays", {})["seed"] = self._seed("rays", snapshot, pair)
        return cfg

    def noise_seed(self, snapshot: int, pair: int, noise: float, frame: str) -> int:
        return self._seed(f"noise-{noise:g}-{frame}", snapshot, pair)

    def _seed(self, what: str, snapshot: int, pair: int) -> int:
        return zlib.crc32(f"{self.seed}/{what}/{snapshot}/{pair}".encode()) & 0x7FFFFFFF


def _quick_config():
    cfg = copy.deepcopy(PAPER_CONFIG)
    cfg["rays"]["per_dot"] = 100
    return cfg


# Reduced: runs on two CPU cores in a few minutes and shows the paper's qualitative result.
QUICK = CampaignSpec(name="quick", pairs_per_snapshot=2, config=_quick_config())
# The paper's size, meant for a GPU.
FULL = CampaignSpec(name="full")


def _regress_config():
    cfg = _quick_config()
    cfg["camera"]["pixels"] = [256, 256]
    cfg["rays"]["per_dot"] = 50
    return cfg


# The CI regression campaign: small and fixed.
REGRESS = CampaignSpec(name="regress", snapshots=(1, 3), pairs_per_snapshot=1, noise_percent=(0.0, 3.0),
                       config=_regress_config())


# ----------------------------------------------------------------------------------------------
# Work items (top-level functions: they run in worker processes)


def _render_item(config: dict, out: str, device):
    from synthbos.raytrace import render_pair, write_pair

    write_pair(out, render_pair(config, device=device))
    return out


def nominal_positions(pair) -> np.ndarray:
    """The prior a tracking user has: the camera model's image of the known target dot positions."""
    import tomllib

    from synthbos.raytrace.camera import camera_from_config
    from synthbos.raytrace.config import load_config

    cam = camera_from_config(load_config(tomllib.loads(pair.attrs["config"])))
    return cam.target_to_pixel(pair.target_xy_m)


def _settings(method: str, overrides: dict):
    if not overrides:
        return None
    if method == "correlation":
        from synthbos.correlation import CorrelationSettings

        return CorrelationSettings(**overrides)
    from synthbos.tracking import TrackingSettings

    return TrackingSettings(**overrides)


def score_pair(pair, method: str, *, noise_percent: float, seeds=(0, 1), peak=None, settings=None):
    """Process one pair with one method at one noise level and return its error arrays.

    Returns
    -------
    dict of arrays
        ``error`` (displacement error magnitude at each scored point, px), ``true_mag`` (true
        displacement magnitude there, for the threshold split), ``grad_error`` (Frobenius norm of the
        displacement-gradient error), ``threshold`` (half the std of Eq. 4's displacement magnitudes),
        ``measured`` / ``expected`` (for the yield).
    """
    from synthbos.raytrace import add_noise

    peak = float(pair.attrs.get("peak_intensity", 1.0)) if peak is None else peak
    ref = add_noise(pair.reference, percent=noise_percent, seed=seeds[0], peak=peak)
    grad = add_noise(pair.gradient, percent=noise_percent, seed=seeds[1], peak=peak)
    valid = pair.valid & np.all(np.isfinite(pair.displacement_px), axis=1)
    threshold = scoring.split_threshold(pair.theory_px[valid])
    prior = nominal_positions(pair) if method != "correlation" else None
    res = run_method(method, ref, grad, prior_xy=prior, correlation_settings=settings, tracking_settings=settings)
    if method == "correlation":
        truth = scoring.interpolate_truth(pair.reference_px[valid], pair.displacement_px[valid], res.xy)
        scored = np.all(np.isfinite(truth), axis=1)
        outlier = (np.asarray(res.table["flags"]).ravel() & 1) != 0
        measured = scored & np.all(np.isfinite(res.uv), axis=1) & ~outlier
        err = scoring.vector_errors(res.uv, truth)
        ny, nx = res.grid_shape
        g_meas = scoring.grid_gradient(res.uv[:, 0].reshape(ny, nx), res.uv[:, 1].reshape(ny, nx),
                                       res.table["x"], res.table["y"]).reshape(-1, 2, 2)
        g_true = scoring.grid_gradient(truth[:, 0].reshape(ny, nx), truth[:, 1].reshape(ny, nx),
                                       res.table["x"], res.table["y"]).reshape(-1, 2, 2)
        keep = scored
    else:
        truth = pair.displacement_px
        measured = valid & np.all(np.isfinite(res.uv), axis=1)
        err = scoring.vector_errors(res.uv, truth)
        xy = pair.reference_px
        g_meas = scoring.scattered_gradient(np.where(measured[:, None], xy, np.nan), res.uv)
        g_true = scoring.scattered_gradient(np.where(measured[:, None], xy, np.nan), truth)
        keep = valid
    grad_err = np.sqrt(np.sum((g_meas - g_true) ** 2, axis=(1, 2)))
    return {
        "error": np.where(measured, err, np.nan)[keep],
        "true_mag": np.hypot(truth[:, 0], truth[:, 1])[keep],
        "grad_error": np.where(measured, grad_err, np.nan)[keep],
        "threshold": np.float64(threshold),
        "measured": np.int64(measured[keep].sum()),
        "expected": np.int64(keep.sum()),
    }


def _score_item(pair_path: str, method: str, noise: float, seeds, out: str, overrides: dict):
    from synthbos.raytrace import read_pair

    settings = _settings(method, overrides)
    scores = score_pair(read_pair(pair_path), method, noise_percent=noise, seeds=seeds, settings=settings)
    with atomic_output(out) as tmp, open(tmp, "wb") as f:
        np.savez(f, **scores)
    return out


# ----------------------------------------------------------------------------------------------


def _check_folder(folder: Path, spec: CampaignSpec):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "pairs").mkdir(exist_ok=True)
    (folder / "scores").mkdir(exist_ok=True)
    meta = folder / "campaign.json"
    mine = json.loads(json.dumps(spec.as_dict()))
    if meta.exists():
        try:
            theirs = json.loads(meta.read_text())
        except json.JSONDecodeError:
            theirs = None
        if theirs != mine:
            raise SynthbosError(
                f"{folder} holds a different campaign (its campaign.json differs); use another --out folder"
            )
    else:
        with atomic_output(meta) as tmp:
            tmp.write_text(json.dumps(mine, indent=2))


def _pool(workers: int):
    return ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"))


def _run_items(items, fn, *, workers: int, desc: str, progress: bool):
    """Run (args) items through ``fn``, in a process pool when workers > 1; returns nothing."""
    if not items:
        return
    bar = tqdm(total=len(items), desc=desc, unit="item", disable=not progress)
    with bar:
        if workers <= 1:
            for args in items:
                fn(*args)
                bar.update(1)
            return
        with _pool(workers) as pool:
            futures = [pool.submit(fn, *args) for args in items]
            try:
                for fut in as_completed(futures):
                    fut.result()
                    bar.update(1)
            except BaseException:
                for fut in futures:
                    fut.cancel()
                raise


def default_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def run_campaign(spec: CampaignSpec, folder, *, device=None, workers=None, progress=True, figures=True):
    """Render, process and score a campaign in ``folder``, skipping finished items; return the summary.

    Returns
    -------
    list of dict
        One row per method, noise level, split and quantity (see ``summarise``).
    """
    from synthbos.raytrace import load_config

    folder = Path(folder)
    workers = workers or default_workers()
    for s, p in spec.pair_keys():  # reject a bad configuration before any work starts
        load_config(spec.pair_config(s, p))
        break
    _check_folder(folder, spec)
    on_gpu = device is not None and str(device).startswith("cuda")
    renders = [
        (spec.pair_config(s, p), str(folder / "pairs" / f"s{s}_p{p:02d}.h5"), device)
        for s, p in spec.pair_keys()
        if not (folder / "pairs" / f"s{s}_p{p:02d}.h5").exists()
    ]
    _run_items(renders, _render_item, workers=1 if on_gpu else workers, desc="render", progress=progress)
    scores = []
    for s, p in spec.pair_keys():
        pair_path = folder / "pairs" / f"s{s}_p{p:02d}.h5"
        for noise in spec.noise_percent:
            seeds = (spec.noise_seed(s, p, noise, "reference"), spec.noise_seed(s, p, noise, "gradient"))
            for method in spec.methods:
                out = folder / "scores" / f"s{s}_p{p:02d}_n{noise:g}_{method}.npz"
                if not out.exists():
                    overrides = spec.correlation if method == "correlation" else spec.tracking
                    scores.append((str(pair_path), method, noise, seeds, str(out), overrides))
    _run_items(scores, _score_item, workers=workers, desc="process", progress=progress)
    rows = summarise(spec, folder)
    write_tables(rows, folder)
    if figures:
        from .figures import figure4, figure5

        figure4(spec, folder, folder / "fig4.png")
        figure5(spec, folder, folder / "fig5.png")
    return rows


def load_scores(spec: CampaignSpec, folder, method: str, noise: float) -> dict:
    """Concatenate the scores of one method and noise level over all pairs of a campaign."""
    folder = Path(folder)
    parts = {"error": [], "true_mag": [], "grad_error": [], "threshold": [], "measured": 0, "expected": 0}
    for s, p in spec.pair_keys():
        with np.load(folder / "scores" / f"s{s}_p{p:02d}_n{noise:g}_{method}.npz") as z:
            n = len(z["error"])
            parts["error"].append(z["error"])
            parts["true_mag"].append(z["true_mag"])
            parts["grad_error"].append(z["grad_error"])
            parts["threshold"].append(np.full(n, float(z["threshold"])))
            parts["measured"] += int(z["measured"])
            parts["expected"] += int(z["expected"])
    out = {k: (np.concatenate(v) if isinstance(v, list) else v) for k, v in parts.items()}
    return out


SPLITS = ("all", "below", "above")
QUANTITIES = ("displacement", "gradient")


def split_masks(scores: dict) -> dict:
    """Masks of the points whose true displacement lies below / above their pair's threshold."""
    below = scores["true_mag"] < scores["threshold"]
    return {"all": np.ones_like(below), "below": below, "above": ~below}


def summarise(spec: CampaignSpec, folder) -> list[dict]:
    """The results table: error percentiles and yield per method, noise level, split and quantity."""
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


def write_tables(rows: list[dict], folder) -> None:
    """results.csv and results.json in the campaign folder (atomic)."""
    folder = Path(folder)
    cols = list(rows[0].keys())
    with atomic_output(folder / "results.csv") as tmp:
        lines = [",".join(cols)]
        for r in rows:
            lines.append(",".join(f"{r[c]:.6g}" if isinstance(r[c], float) else str(r[c]) for c in cols))
        tmp.write_text("\n".join(lines) + "\n")
    with atomic_output(folder / "results.json") as tmp:
        tmp.write_text(json.dumps(rows, indent=1))


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
