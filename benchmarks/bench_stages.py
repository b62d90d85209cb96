"""Per-stage times of one campaign pair on each device: render, noise, each method, scoring; and ``paper --full``.

The paper configuration (``raytrace/default.toml``: 512 x 512 px, 20 dots per 32 x 32 px, 3 px dots)
is rendered and processed in this one process on every device given, stage by stage, as a campaign
item does it (``benchmarks.items``):

- ``render``: ``render_pair`` (reference and gradient images, the chief-ray truth and the pair's
  density truths), on the device;
- ``pair file``: writing the pair file and reading it back (host);
- ``noise``: seeded sensor noise on both images (host, NumPy; the campaign adds it per noise level);
- ``<method>``: each of the registry's campaign methods (``registry.default_methods``), with its
  default settings, run on the device (its run function takes the device), each on its own;
- ``methods in turn``: all of them one after another on the same images, as a campaign runs a pair's
  items (``tracking-cc`` then reuses the ``track_pair`` table of ``tracking``, ``registry``);
- ``score <method>``: scoring that method's result, density integration included (host).

The noise and the scoring remember work between the items of a pair (``synthbos.memo``: a seed's
draws, the pair's triangulation, repeated least-squares factors); their stages are timed cold, with
that memory forgotten before every call, as the first item of a pair in a process pays them, an upper
bound for the later items.

Each stage runs once untimed first (kernel compilation and loading, FFT plans, caches), then
``--repeats`` times; the best time is kept, with ``wp.synchronize_device`` before and after every
timed call. ``pair total`` adds up what one pair costs a campaign with the paper's four noise levels:
render + file + 4 x (noise + methods in turn + every scoring); all in one thread, whereas the
campaign's pipeline overlaps the render, the device work and the scoring (``scheduling.run_pipeline``).

Rays per dot: ``--rays`` (default 10,000, the paper's) on CUDA devices, ``--cpu-rays`` (default 100) on
the CPU, whose render at 10,000 rays would take many minutes. The CPU's render time is then SCALED to
``--rays`` rays per dot, proportionally (the trace is linear in the rays; the render's fixed cost,
timed at 2 rays per dot, is not scaled); the table marks a scaled time with ``*`` and the JSON keeps
the measured one beside it. No other stage depends on the rays per dot (the images have the same size
and dots).

``--paper-full`` then runs ``synthbos paper --full --device DEV`` (DEV: the first CUDA device given)
in a temporary folder, in a subprocess, and prints its wall time; ``--also-cpu-processing`` runs it
again with ``--process-device cpu`` (rendering on the GPU, processing in CPU worker processes).

    python -m synthbos.benchmarks.bench_stages --devices cpu cuda:0 --paper-full --json stages.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp
from synthbos.raytrace import read_pair, render_pair, write_pair

from synthbos.device import check_device, describe_device, init_warp
from synthbos.memo import forget_all

from .items import noisy_pair, nominal_positions, score_result
from .registry import default_methods, forget_shared_results, get_method
from .spec import FULL

__all__ = ["main", "paper_full_wall_time", "time_stages"]

PAPER_RAYS = 10_000
NOISE_LEVELS = len(FULL.noise_percent)  # a campaign processes each pair at each of these


def _config(rays_per_dot: int, base=None) -> dict:
    """The paper's set-up (``raytrace/default.toml``, its one home; ``base`` tables over it) with ``rays_per_dot``."""
    return {**(base or {}), "rays": {**(base or {}).get("rays", {}), "per_dot": int(rays_per_dot)}}


def _best(fn, repeats: int, device: str, *, before=None):
    """Best wall time of ``repeats`` calls of ``fn`` (after one untimed call), synchronising ``device``.

    ``before`` runs untimed before every call.
    """
    if before:
        before()
    out = fn()  # warm-up: compilation, module loading, plans
    best = float("inf")
    for _ in range(repeats):
        if before:
            before()
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        out = fn()
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - t0)
    return best, out


def time_stages(device: str, *, rays_per_dot: int, scale_to: int, repeats: int = 3, noise_percent: float = 3.0,
                methods=None, folder=None, base_config=None, batch: int = 0) -> dict:
    """Time every stage of one pair on ``device``; return ``{"stages": {name: seconds}, ...}``.

    ``base_config`` (tables over the default, e.g. a smaller camera for a test) is None for the paper's set-up.

    The render is timed at ``rays_per_dot``; when that differs from ``scale_to`` its time is also given
    scaled: fixed part (the render at 2 rays per dot) + (measured - fixed) x (scale_to - 2) / (rays - 2).

    ``batch`` > 0 also times ``tracking.stack.track_pairs`` on ``batch`` noisy copies of the pair (each its
    own noise seed), images on the device in and host tables out, as the stage ``tracking, batched``: the
    time per pair (the batch's time / ``batch``); ``tracking_batch`` in the result gives the batch's time
    and dots/s, also from NumPy images (their upload included).
    """
    init_warp()
    device = check_device(device)
    methods = list(methods or default_methods())
    stages: dict[str, float] = {}
    measured: dict[str, float] = {}
    config = _config(rays_per_dot, base_config)

    t_render, pair = _best(lambda: render_pair(config, device=device), repeats, device)
    measured["render"] = t_render
    if rays_per_dot != scale_to:
        t_fixed, _ = _best(lambda: render_pair(_config(2, base_config), device=device), repeats, device)
        t_fixed = min(t_fixed, t_render)
        measured["render fixed (2 rays/dot)"] = t_fixed
        stages["render"] = t_fixed + (t_render - t_fixed) * (scale_to - 2) / max(1, rays_per_dot - 2)
    else:
        stages["render"] = t_render

    with tempfile.TemporaryDirectory(prefix="synthbos-stages-", dir=folder) as tmp:
        path = Path(tmp) / "pair.h5"

        def file_round_trip():
            path.unlink(missing_ok=True)
            write_pair(path, pair)
            return read_pair(path)

        stages["pair file"], pair = _best(file_round_trip, repeats, "cpu")

    seeds = (11, 12)
    stages["noise"], (ref, grad) = _best(
        lambda: noisy_pair(pair, noise_percent=noise_percent, seeds=seeds), repeats, "cpu", before=forget_all)
    prior = nominal_positions(pair)
    results = {}

    def run(name):
        m = get_method(name)
        return m.run(ref, grad, prior_xy=prior if m.uses_prior else None, settings=m.settings(), device=device)

    for name in methods:  # each on its own: no result shared with the method before
        stages[name], results[name] = _best(lambda name=name: run(name), repeats, device, before=forget_shared_results)
    # as a campaign runs them, one after another on the same images (tracking-cc reuses tracking's track_pair)
    stages["methods in turn"], _ = _best(lambda: [run(name) for name in methods], repeats, device,
                                         before=forget_shared_results)
    for name in methods:
        stages[f"score {name}"], _ = _best(lambda name=name: score_result(pair, name, results[name]), repeats, "cpu",
                                           before=forget_all)
    batch_info = None
    if batch > 0:
        batch_info = _time_batch(pair, prior, device, batch=batch, repeats=repeats, noise_percent=noise_percent)
        stages["tracking, batched"] = batch_info["seconds"] / batch
    per_noise = stages["noise"] + stages["methods in turn"] + sum(stages[f"score {n}"] for n in methods)
    stages["pair total"] = stages["render"] + stages["pair file"] + NOISE_LEVELS * per_noise
    measured.update({k: v for k, v in stages.items() if k not in ("render", "pair total")})
    measured["pair total"] = stages["pair total"] - stages["render"] + measured["render"]
    return {
        "device": device,
        "device_name": str(wp.get_device(device).name),
        "rays_per_dot": int(rays_per_dot),
        "render_scaled_to_rays_per_dot": int(scale_to) if rays_per_dot != scale_to else None,
        "dots": int(pair.n_dots),
        "image": list(np.shape(pair.reference)),
        "noise_percent": float(noise_percent),
        "methods": methods,
        "stages": stages,
        "measured": measured,
        "measured_counts": {n: (results[n].counts or {}) for n in methods},
        "tracking_batch": batch_info,
    }


def _time_batch(pair, prior, device, *, batch, repeats, noise_percent):
    """Best time of ``track_pairs`` on ``batch`` noisy copies of ``pair``: from images already on the device
    (``seconds``, as a pipeline that keeps them there) and from NumPy stacks (``seconds_host``, the upload
    included), host tables out both times, and without the first-moment step (``seconds_symmetric``, from
    images on the device); dots per second, the largest difference from ``track_pair`` on the first and
    the last copy (and whether their status bits are the same), and whether every call from images on the
    device gave the same bytes (``calls_identical``)."""
    from synthbos.tracking import TrackingSettings, track_pair
    from synthbos.tracking.stack import track_pairs

    noisy = [noisy_pair(pair, noise_percent=noise_percent, seeds=(100 + 2 * k, 101 + 2 * k)) for k in range(batch)]
    refs = np.stack([np.asarray(r, dtype=np.float64) for r, _ in noisy])
    grads = np.stack([np.asarray(g, dtype=np.float64) for _, g in noisy])
    on_device = [wp.array(a, dtype=wp.float64, device=device) for a in (refs, grads)]
    made, digests = [], []  # every call's table, hashed between the timed calls: the same bytes each time?

    def run():
        made.append(track_pairs(*on_device, prior_xy=prior, device=device))
        return made[-1]

    def hash_made():
        while made:
            digests.append(hashlib.md5(made.pop().tobytes()).hexdigest())

    seconds, tables = _best(run, repeats, device, before=hash_made)
    hash_made()
    seconds_host, _ = _best(lambda: track_pairs(refs, grads, prior_xy=prior, device=device), repeats, device)
    symmetric = TrackingSettings(distortion="none")  # the same without the first-moment step, for its cost
    seconds_symmetric, _ = _best(
        lambda: track_pairs(*on_device, prior_xy=prior, settings=symmetric, device=device), repeats, device
    )
    diff, same_status = 0.0, True
    for k in sorted({0, batch - 1}):  # the first pair and the last (its rows far into the stack's)
        single = track_pair(refs[k], grads[k], prior_xy=prior, device=device)
        for name in ("u", "v", "u_cc", "v_cc"):
            a, b = tables[k][name], single[name]
            both = np.isfinite(a) & np.isfinite(b)
            diff = max(diff, float(np.abs(a[both] - b[both]).max(initial=0.0)))
        same_status = same_status and bool(np.array_equal(tables[k]["status"], single["status"]))
    dots = int(np.prod(tables.shape))
    return {"pairs": batch, "dots": dots, "seconds": seconds, "dots_per_second": dots / seconds,
            "seconds_host": seconds_host, "dots_per_second_host": dots / seconds_host,
            "seconds_symmetric": seconds_symmetric, "dots_per_second_symmetric": dots / seconds_symmetric,
            "max_difference_px": diff, "status_equal": same_status, "calls": len(digests),
            "calls_identical": len(set(digests)) == 1}


def paper_full_wall_time(device: str, *, process_device=None, workers=None, folder=None) -> dict:
    """Run ``synthbos paper --full --device DEVICE`` in a temporary folder (a subprocess); return its wall time."""
    with tempfile.TemporaryDirectory(prefix="synthbos-paper-full-", dir=folder) as tmp:
        cmd = [sys.executable, "-m", "synthbos", "paper", "--full", "--device", device, "--out",
               str(Path(tmp) / "paper-full"), "-q"]
        if process_device:
            cmd += ["--process-device", process_device]
        if workers:
            cmd += ["--workers", str(workers)]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return {"command": " ".join(cmd[1:]), "wall_seconds": wall, "stdout_tail": proc.stdout[-3000:]}


def format_table(runs: list[dict]) -> str:
    """Stage, seconds per device, and each device's speed-up over the first (first / device)."""
    names = list(runs[0]["stages"])
    head = f"{'stage':<22}" + "".join(f" {r['device'] + ' s':>12}" for r in runs)
    head += "".join(f" {runs[0]['device'] + '/' + r['device']:>14}" for r in runs[1:])
    lines = [head]
    for name in names:
        line = f"{name:<22}"
        for r in runs:
            t = r["stages"].get(name, float("nan"))
            mark = "*" if name in ("render", "pair total") and r["render_scaled_to_rays_per_dot"] else " "
            line += f" {t:>11.4f}{mark}"
        for r in runs[1:]:
            line += f" {runs[0]['stages'][name] / r['stages'][name]:>14.1f}"
        lines.append(line)
    notes = [f"{r['device']}: {r['device_name']}, {r['rays_per_dot']} rays/dot rendered"
             + (f", * render scaled to {r['render_scaled_to_rays_per_dot']} rays/dot (measured "
                f"{r['measured']['render']:.3f} s)" if r["render_scaled_to_rays_per_dot"] else "")
             for r in runs]
    lines.append(f"pair total = render + pair file + {NOISE_LEVELS} noise levels x (noise + methods in turn + "
                 "each scoring), in one thread")
    return "\n".join(lines + notes)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", nargs="+", default=["cpu"], help="Warp devices, e.g. cpu cuda:0")
    parser.add_argument("--rays", type=int, default=PAPER_RAYS, help="rays per dot on CUDA devices (default 10000)")
    parser.add_argument("--cpu-rays", type=int, default=100,
                        help="rays per dot rendered on the CPU; its render time is scaled to --rays (default 100)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats per stage after a warm-up (best kept)")
    parser.add_argument("--noise", type=float, default=3.0, help="noise level of the timed processing, %% of the peak")
    parser.add_argument("--methods", default=None, help="comma-separated methods (default: the campaign's)")
    parser.add_argument("--paper-full", action="store_true",
                        help="also time 'synthbos paper --full' on the first CUDA device given")
    parser.add_argument("--also-cpu-processing", action="store_true",
                        help="with --paper-full, also time it with --process-device cpu (render on the GPU, process "
                             "in CPU worker processes: the scheduling before the GPU pipeline)")
    parser.add_argument("--workers", type=int, default=None, help="--workers of the paper --full runs")
    parser.add_argument("--batch", type=int, default=0,
                        help="also time tracking.stack.track_pairs on this many noisy copies of the pair on CUDA "
                             "devices (dots/s)")
    parser.add_argument("--cpu-batch", type=int, default=4, help="pairs of the batched tracking on the CPU")
    parser.add_argument("--json", help="write the table (and the paper --full time) here as JSON")
    args = parser.parse_args(argv)
    init_warp()
    methods = [n.strip() for n in args.methods.split(",")] if args.methods else list(default_methods())
    for n in methods:
        get_method(n)
    runs = []
    for dev in args.devices:
        print(describe_device(check_device(dev)), flush=True)
        rays = args.cpu_rays if dev == "cpu" else args.rays
        batch = (args.cpu_batch if dev == "cpu" else args.batch) if args.batch else 0
        runs.append(time_stages(dev, rays_per_dot=rays, scale_to=args.rays, repeats=args.repeats,
                                noise_percent=args.noise, methods=methods, batch=batch))
    date = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    print(f"\nper-stage times of one pair, paper configuration ({runs[0]['dots']} dots, "
          f"{runs[0]['image'][1]} x {runs[0]['image'][0]} px, noise {args.noise:g} %), best of {args.repeats}, "
          f"{date}, {platform.node()} ({os.cpu_count()} CPU cores)")
    print(format_table(runs))
    for r in runs:
        tb = r.get("tracking_batch")
        if tb:
            print(f"tracking, batched on {r['device']}: {tb['pairs']} pairs ({tb['dots']} dots) in "
                  f"{tb['seconds']:.4f} s = {tb['dots_per_second']:.3g} dots/s from images on the device "
                  f"({tb['seconds_host']:.4f} s = {tb['dots_per_second_host']:.3g} dots/s from NumPy images; "
                  f"without the first-moment step {tb['dots_per_second_symmetric']:.3g} dots/s); "
                  f"largest difference from track_pair on the first and last pairs {tb['max_difference_px']:.2e} px, "
                  f"status equal: {tb['status_equal']}; the {tb['calls']} calls' tables "
                  f"{'the same bytes' if tb['calls_identical'] else 'NOT the same bytes'}")
    paper = None
    if args.paper_full:
        cuda = [d for d in args.devices if d.startswith("cuda")]
        if not cuda:
            parser.error("--paper-full needs a CUDA device in --devices")
        paper = [paper_full_wall_time(cuda[0], workers=args.workers)]
        if args.also_cpu_processing:
            paper.append(paper_full_wall_time(cuda[0], process_device="cpu", workers=args.workers))
        for run in paper:
            print(f"\n{run['command']}\n" + "\n".join(run["stdout_tail"].strip().splitlines()[-16:]))
        print()
        for run in paper:
            print(f"{run['command']}: {run['wall_seconds']:.1f} s wall")
    if args.json:
        out = {"date": date, "host": platform.node(), "cpu_cores": os.cpu_count(), "warp": wp.config.version,
               "repeats": args.repeats, "noise_levels_per_pair": NOISE_LEVELS, "runs": runs, "paper_full": paper}
        Path(args.json).write_text(json.dumps(out, indent=1))
    return runs, paper


if __name__ == "__main__":
    main()
