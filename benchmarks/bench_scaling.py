"""Throughput of a campaign on 1, 2, 4 ... GPUs through ``--scheduler local``: pairs per second and efficiency.

For each GPU count N the benchmark starts a local Dask cluster of one worker per GPU (the first N of
``--gpus``, each pinned to its GPU), warms every worker up (imports, Warp kernels, one tiny pair
rendered and scored), then runs the same campaign, every pair rendered, processed by every method at
every noise level and scored, in a fresh folder, exactly as ``synthbos paper --scheduler local`` does.
Throughput is pairs per second of that campaign (cluster start-up and warm-up excluded; the rate with
them is reported too). Speed-up is against the first count; efficiency is speed-up / (N / N_first).
Every count runs the same campaign (a strong-scaling test), so the result tables of all counts must be
byte-identical: the benchmark checks it.

    python -m synthbos.benchmarks.bench_scaling --gpus 0,1,2,3 --counts 1,2,4 --pairs 48 --out scaling
    python -m synthbos.benchmarks.bench_scaling --device cpu --counts 1,2 --pairs 4 --pixels 96 --rays 20

(the second line is a smoke run on CPU workers).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from synthbos import atomic_output

from .campaign import run_campaign
from .distributed import DaskRunner, visible_gpus
from .spec import FULL, CampaignSpec

__all__ = ["campaign_spec", "main", "run_scaling"]


def campaign_spec(pairs: int, *, pixels: int = 512, rays: int = 1000, noise=(0.0, 1.0, 3.0, 5.0)) -> CampaignSpec:
    """The paper's campaign (five snapshots, every method) with ``pairs`` pairs in all (rounded up to 5)."""
    config = {"rays": {"per_dot": rays}}
    if pixels != 512:
        config["camera"] = {"pixels": [pixels, pixels]}
    return replace(FULL, name=f"scaling-{pairs}", pairs_per_snapshot=max(1, math.ceil(pairs / len(FULL.snapshots))),
                   noise_percent=tuple(noise), config=config)


def _warm_up(device: str, folder: str) -> float:
    """On a worker: render and score one tiny pair, so imports and kernels are loaded before timing."""
    from .items import render_item, score_item
    from .registry import method_names

    t0 = time.perf_counter()
    pair = str(Path(folder) / f"warm-{time.monotonic_ns()}.h5")
    render_item({"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 10}}, pair, device)
    for m in method_names():
        score_item(pair, m, 1.0, (1, 2), pair.replace(".h5", f"-{m}.npz"), {})
    return time.perf_counter() - t0


def run_scaling(spec: CampaignSpec, counts, *, device: str, gpus=None, per_gpu: int = 1, folder=None,
                progress=False) -> list[dict]:
    """Time ``spec`` on each worker count of ``counts``; return one row per count."""
    rows, tables = [], []
    with tempfile.TemporaryDirectory(prefix="synthbos-scaling-") as tmp:
        base = Path(folder or tmp)
        base.mkdir(parents=True, exist_ok=True)
        for n in counts:
            t0 = time.perf_counter()
            on_gpu = device.startswith("cuda")
            if on_gpu:
                runner = DaskRunner("local", device=device, gpus=gpus[:n], workers=n * per_gpu, progress=progress)
            else:
                runner = DaskRunner("local", device=device, workers=n, progress=progress)
            with runner:
                client = runner.client
                workers = n * per_gpu if on_gpu else n
                client.wait_for_workers(workers)
                warm = Path(tmp) / f"warm-{n}"
                warm.mkdir()
                addresses = list(client.nthreads())
                # By reference, even when this file runs as __main__: the workers import it.
                from synthbos.benchmarks.bench_scaling import _warm_up

                client.gather([client.submit(_warm_up, device, str(warm), workers=[a], pure=False)
                               for a in addresses])
                t1 = time.perf_counter()
                out = base / f"{n}-{'gpu' if on_gpu else 'cpu'}"
                run_campaign(spec, out, device=device, scheduler=runner, progress=progress, figures=False)
                t2 = time.perf_counter()
            pairs = len(spec.pair_keys())
            tables.append((out / "results.json").read_bytes())
            rows.append({"units": n, "workers": workers, "pairs": pairs, "startup_s": t1 - t0,
                         "campaign_s": t2 - t1, "pairs_per_s": pairs / (t2 - t1),
                         "pairs_per_s_with_startup": pairs / (t2 - t0)})
    for r in rows:
        r["speedup"] = r["pairs_per_s"] / rows[0]["pairs_per_s"]
        r["efficiency"] = r["speedup"] / (r["units"] / rows[0]["units"])
        r["identical_results"] = tables[rows.index(r)] == tables[0]
    return rows


def format_table(rows, unit: str) -> str:
    lines = [f"| {unit}s | workers | pairs | start-up + warm-up s | campaign s | pairs/s | pairs/s with start-up "
             f"| speed-up | efficiency | results identical to the first |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['units']} | {r['workers']} | {r['pairs']} | {r['startup_s']:.1f} | {r['campaign_s']:.1f} "
                     f"| {r['pairs_per_s']:.3f} | {r['pairs_per_s_with_startup']:.3f} | {r['speedup']:.2f} "
                     f"| {r['efficiency']:.2f} | {'yes' if r['identical_results'] else 'NO'} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda:0", help="cuda:0 (each worker's own GPU) or cpu (CPU workers)")
    parser.add_argument("--gpus", default=None, help="GPUs to pin workers to, e.g. 0,1,2,3 (default: all visible)")
    parser.add_argument("--counts", default="1,2,4", help="GPU (or CPU worker) counts to time, e.g. 1,2,4")
    parser.add_argument("--per-gpu", type=int, default=1, help="workers per GPU")
    parser.add_argument("--pairs", type=int, default=40, help="pairs in the campaign (a multiple of 5)")
    parser.add_argument("--pixels", type=int, default=512)
    parser.add_argument("--rays", type=int, default=1000, help="rays per dot")
    parser.add_argument("--noise", default="0,1,3,5", help="noise levels, percent of the dot peak")
    parser.add_argument("--out", default=None, help="write scaling.json and scaling.md here (and keep the campaigns)")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    counts = [int(c) for c in args.counts.split(",")]
    on_gpu = args.device.startswith("cuda")
    gpus = (args.gpus.split(",") if args.gpus else visible_gpus()) if on_gpu else None
    if on_gpu and max(counts) > len(gpus):
        parser.error(f"--counts asks for {max(counts)} GPUs but only {len(gpus)} are available: {gpus}")
    spec = campaign_spec(args.pairs, pixels=args.pixels, rays=args.rays,
                         noise=[float(v) for v in args.noise.split(",")])
    name = "cpu"
    if on_gpu:
        import warp as wp

        name = wp.get_device("cuda:0").name
    print(f"scaling: {len(spec.pair_keys())} pairs of {args.pixels} x {args.pixels} px, {args.rays} rays/dot, "
          f"noise {args.noise} %, methods {', '.join(spec.methods)}; {name}; counts {counts}", flush=True)
    folder = Path(args.out) / "campaigns" if args.out else None
    rows = run_scaling(spec, counts, device=args.device, gpus=gpus, per_gpu=args.per_gpu, folder=folder,
                       progress=args.progress)
    table = format_table(rows, "GPU" if on_gpu else "CPU worker")
    date = time.strftime("%Y-%m-%d", time.gmtime())
    print(f"\n{date}, {name}\n{table}")
    if args.out:
        out = Path(args.out)
        meta = {"date": date, "device": name, "spec": spec.as_dict(), "per_gpu": args.per_gpu, "rows": rows}
        with atomic_output(out / "scaling.json") as tmp:
            tmp.write_text(json.dumps(meta, indent=1))
        with atomic_output(out / "scaling.md") as tmp:
            tmp.write_text(f"{date}, {name}\n\n{table}\n")
    return rows


if __name__ == "__main__":
    main()
