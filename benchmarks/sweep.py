"""``synthbos sweep``: experiment design by sweeping one or two set-up parameters.

At every point of the sweep the campaign machinery renders, processes and scores a campaign (by
default the small ``REGRESS`` size; ``--size quick`` or ``full`` for more), in its own resumable
folder; the results are gathered into ``sweep.csv`` / ``sweep.json`` and plotted in ``sweep.png``
(error percentiles and yield against the parameter, for every method), so a researcher can choose a
set-up before building it; ``sweep_budget.png`` draws each point's error budget (median error against
the dots' in-cone spread) when the pairs record their rays' covariance.

Parameters are named by a configuration key, ``table.key`` (e.g. ``target.dots_per_32px``,
``camera.f_number``, ``volume.distance_from_target_mm``, ``rays.per_dot``), or by one of these:
``density`` (dots per 32x32 px), ``diameter`` (dot diameter, px), ``noise`` (percent of the peak),
``f_number``, ``z_d`` (mm), ``magnification`` (sets the target distance f (1 + 1/M)), ``rays``
(per dot) and ``window`` (the final correlation window, px; the first pass is twice as large).
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
from concurrent.futures import FIRST_EXCEPTION, CancelledError, ThreadPoolExecutor
from concurrent.futures import wait as wait_for
from dataclasses import replace
from pathlib import Path

from synthbos.raytrace import DEFAULT_CONFIG, load_config

from synthbos import SynthbosError, atomic_output, check_output_folder, folder_lock, make_folder

from .campaign import check_campaign_stack, check_drivers, check_spec, resolve_process_device, run_campaign
from .figures import sweep_budget_figure, sweep_figure
from .registry import get_method
from .spec import FULL, QUICK, REGRESS, CampaignSpec
from .storage import write_tables

__all__ = ["ALIASES", "LABELS", "apply_parameter", "parameter_label", "parse_parameter", "run_sweep"]

ALIASES = {
    "density": "target.dots_per_32px",
    "diameter": "target.dot_diameter_px",
    "f_number": "camera.f_number",
    "z_d": "volume.distance_from_target_mm",
    "rays": "rays.per_dot",
}
SPECIAL = ("noise", "magnification", "window")

# How a figure names a parameter: words and units. Other configuration keys are worded from the key.
LABELS = {
    "target.dots_per_32px": "dot density (dots per 32 × 32 px)",
    "target.dot_diameter_px": "dot diameter (px)",
    "target.distance_mm": "target distance from the lens (mm)",
    "camera.f_number": "f-number",
    "camera.focal_length_mm": "focal length (mm)",
    "camera.pixel_pitch_um": "pixel pitch (µm)",
    "volume.distance_from_target_mm": "volume distance from the target, Z_D (mm)",
    "rays.per_dot": "rays per dot",
    "noise": "noise (% of the dot peak)",
    "magnification": "magnification M",
    "window": "final correlation window (px)",
}
_UNIT_SUFFIXES = {"mm": "mm", "um": "µm", "nm": "nm", "px": "px", "m": "m", "kg_m3": "kg/m³", "kg_m4": "kg/m⁴",
                  "m3_per_kg": "m³/kg", "deg": "°", "s": "s"}


def parameter_label(name: str) -> str:
    """Words and units for a sweep parameter: ``camera.f_number`` -> ``f-number``,
    ``volume.density_scale_kg_m3`` -> ``volume density scale (kg/m³)``."""
    if name in LABELS:
        return LABELS[name]
    table, _, key = name.rpartition(".")
    for suffix in sorted(_UNIT_SUFFIXES, key=len, reverse=True):
        if key.endswith(f"_{suffix}"):
            words = key[: -len(suffix) - 1].replace("_", " ")
            return f"{table} {words} ({_UNIT_SUFFIXES[suffix]})".strip()
    return f"{table} {key.replace('_', ' ')}".strip()
SIZES = {"regress": REGRESS, "quick": QUICK, "full": FULL}


def parse_parameter(text: str):
    """``name=v1,v2,...`` -> (canonical name, [values]); raises SynthbosError on a malformed one."""
    if "=" not in text:
        raise SynthbosError(f"sweep parameter {text!r} must look like name=v1,v2,...")
    name, _, values = text.partition("=")
    name = ALIASES.get(name.strip(), name.strip())
    if name not in SPECIAL and (name.count(".") != 1):
        raise SynthbosError(f"unknown sweep parameter {name!r}: use table.key or one of "
                            f"{sorted(ALIASES) + list(SPECIAL)}")
    if name in ("rays.seed", "target.seed"):
        raise SynthbosError(f"sweep parameter {name}: the campaign sets the seeds of every pair from its own "
                            "seed, so sweeping it would change nothing")
    try:
        vals = [float(v) for v in values.split(",") if v.strip()]
    except ValueError:
        raise SynthbosError(f"sweep parameter {name}: values must be numbers, got {values!r}") from None
    bad = [v for v in vals if not math.isfinite(v)]
    if bad:
        raise SynthbosError(f"sweep parameter {name}: values must be finite numbers, got {bad[0]!r}")
    if not vals:
        raise SynthbosError(f"sweep parameter {name} has no values")
    return name, vals


def apply_parameter(spec: CampaignSpec, name: str, value: float) -> CampaignSpec:
    """The campaign spec with one parameter set to ``value``."""
    if name == "noise":
        return replace(spec, noise_percent=(value,))
    if name == "window":
        w = int(value)
        if w != value:
            raise SynthbosError(f"sweep parameter window: a window is a whole number of pixels, got {value:g}")
        return replace(spec, correlation={**spec.correlation, "window_sizes": (2 * w, w)})
    if name == "magnification":
        if value <= 0:
            raise SynthbosError(f"magnification must be > 0, got {value:g}")
        f = spec.config.get("camera", {}).get("focal_length_mm", DEFAULT_CONFIG["camera"]["focal_length_mm"])
        return spec.with_config({"target": {"distance_mm": f * (1.0 + 1.0 / value)}})
    table, key = name.split(".")
    integer_keys = {"rays.per_dot", "target.seed", "rays.seed", "limits.steps_per_ray"}
    if name in integer_keys and value != int(value):
        raise SynthbosError(f"sweep parameter {name}: values must be whole numbers, got {value:g}")
    return spec.with_config({table: {key: int(value) if name in integer_keys else value}})


def _slug(name, value):
    return f"{name.replace('.', '-')}={value:g}"


def run_sweep(base_config: dict, params, folder, *, size="regress", device=None, workers=None, progress=True,
              scheduler=None, wait=False, process_device=None, worker_device=None, methods=None, stack=None,
              stacks=None, drivers=None):
    """Run the sweep; write sweep.csv, sweep.json, sweep.png and sweep_budget.png in ``folder``; return the rows.

    ``sweep_budget.png`` (``figures.sweep_budget_figure``) is left out when the pairs hold no ray covariance.

    ``device`` renders and ``process_device`` processes (default: ``device``; see ``run_campaign``).
    Every point is checked (configuration, settings, resource limits) before the first is run; the
    sweep folder is locked for the sweep's life (``wait``: wait for another sweep into it to finish).
    ``methods`` (names) replaces the campaign size's default methods at every point.
    With ``scheduler`` (see ``run_campaign``) one Dask client serves the whole sweep and all its points
    run together, so every worker stays busy however few pairs a point has.
    ``stack`` (pairs per stack of tracking items), ``stacks`` (the log of ``track_pairs`` calls) and
    ``drivers`` (processes that drive the GPU) are those of ``run_campaign``, for every point.
    """
    if not 1 <= len(params) <= 2:
        raise SynthbosError("give one or two --param options")
    if size not in SIZES:
        raise SynthbosError(f"sweep size must be one of {sorted(SIZES)}, got {size!r}")
    load_config(base_config)  # the base configuration alone, before any point
    if isinstance(scheduler, str):
        from .distributed import check_scheduler

        check_scheduler(scheduler)
    process_device = resolve_process_device(device, process_device)
    folder = Path(folder)
    check_output_folder(folder)
    spec0 = SIZES[size].with_config(copy.deepcopy(base_config))
    if methods is not None:
        spec0 = replace(spec0, methods=tuple(methods))
    check_campaign_stack(stack, spec0, device=device, scheduler=scheduler)
    check_drivers(drivers)
    if any(name == "window" for name, _ in params) and not any(
            get_method(m).settings_key == "correlation" for m in spec0.methods):
        raise SynthbosError(f"sweep parameter window sets the correlation windows; none of the methods "
                            f"({', '.join(spec0.methods)}) reads them")
    (name1, vals1), *rest = params
    name2, vals2 = rest[0] if rest else (None, [None])
    points = []
    for v2 in vals2:
        for v1 in vals1:
            spec = apply_parameter(spec0, name1, v1)
            label = _slug(name1, v1)
            if name2 is not None:
                spec = apply_parameter(spec, name2, v2)
                label += "_" + _slug(name2, v2)
            spec = replace(spec, name=f"{spec0.name}-sweep-{label}")
            try:
                check_spec(spec, device, process_device)  # every point fails before any work
            except SynthbosError as err:
                raise SynthbosError(f"sweep point {label}: {err}") from None
            points.append((v1, v2, label, spec))

    def run_point(point, runner=None):
        v1, v2, label, spec = point
        if progress and runner is None:
            print(f"sweep point {label}")
        point_rows = run_campaign(spec, folder / "points" / label, device=device, process_device=process_device,
                                  worker_device=worker_device, stack=stack, stacks=stacks, drivers=drivers,
                                  workers=workers, progress=progress, figures=False, scheduler=runner, wait=wait)
        return [{"param": name1, "param_value": v1, "param2": name2, "param2_value": v2, **r} for r in point_rows]

    make_folder(folder)
    with folder_lock(folder, wait=wait, what="sweep folder"):
        per_point = _run_points(points, run_point, scheduler=scheduler, device=device, workers=workers,
                                progress=progress, process_device=process_device)
        rows = [r for point_rows in per_point for r in point_rows]
        write_tables(rows, folder, stem="sweep")
        with atomic_output(folder / "sweep_params.json") as tmp:
            tmp.write_text(json.dumps({"params": [list(p) for p in params], "size": size, "base": base_config}))
        sweep_figure(rows, folder / "sweep.png", param=name1, param2=name2, param_label=parameter_label(name1),
                     param2_label=parameter_label(name2) if name2 else None)
        budget = [(f"{v1:g}" if name2 is None else f"{v1:g}, {v2:g}", spec, folder / "points" / label)
                  for v1, v2, label, spec in points]
        words = parameter_label(name1) if name2 is None else f"{parameter_label(name1)}, {parameter_label(name2)}"
        sweep_budget_figure(budget, folder / "sweep_budget", param_label=words)
    return rows


def _run_points(points, run_point, *, scheduler, device, workers, progress, process_device=None):
    """Every point's rows, one point after another, or all together on one Dask client."""
    if scheduler is None:
        return [run_point(point) for point in points]
    from .distributed import DaskRunner  # dask only when a scheduler is asked for

    owned = not isinstance(scheduler, DaskRunner)
    runner = (DaskRunner(scheduler, device=device, workers=workers, progress=progress, process_device=process_device)
              if owned else scheduler)
    # One thread per point submits its pair tasks and waits for them; the cluster runs them all together.
    threads = min(len(points), 64)
    with (runner if owned else contextlib.nullcontext()), ThreadPoolExecutor(threads, "sweep-point") as pool:
        futures = [pool.submit(run_point, point, runner) for point in points]
        try:
            wait_for(futures, return_when=FIRST_EXCEPTION)
        except BaseException:  # Ctrl-C
            runner.abort()
            raise
        if any(f.exception() for f in futures if f.done()):
            runner.abort()  # the other points' tasks too; then report the error that came first
            wait_for(futures)
            errors = [f.exception() for f in futures if f.exception() is not None]
            raise next((e for e in errors if not isinstance(e, CancelledError)), errors[0])
        return [f.result() for f in futures]
