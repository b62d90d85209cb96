"""Throughput of a campaign on 1, 2, 4 ... GPUs through ``--scheduler local``: pairs per second and efficiency.

For each GPU count N the benchmark starts a local Dask cluster of ``--per-gpu`` workers per GPU (default
two, as ``--scheduler local`` starts; the first N of ``--gpus``, each worker pinned to its GPU), warms
every worker up (imports, Warp kernels, one tiny pair
rendered and scored), then runs the paper's campaign (five snapshots, every method at every noise
level) in a fresh folder, every pair rendered, processed and scored, exactly as
``synthbos paper --scheduler local`` does. Throughput is pairs per second of that campaign (cluster
start-up and warm-up excluded; the rate with them is reported too). Speed-up is against the first
count; efficiency is speed-up / (N / N_first).

With a GPU, the baseline is the same campaign on one GPU without Dask, and for each N > 1 the host's own
limit: N plain campaigns at once, one per GPU, each with a GPU's share of the cores (the most the host
gives N GPUs with no scheduler between them; ``--no-side-by-side`` skips it). On a host whose cores slow
each other down when all are busy, that limit is below N times one campaign alone.

By default the campaign grows with N (``--pairs-per-gpu``, weak scaling: every count runs as long, so
start-up effects weigh the same); ``--pairs`` fixes it instead (strong scaling). Seeds depend only on
the snapshot and pair index, so the pairs every count has in common must have bit-identical scores:
the benchmark checks it (and the result tables, when the campaigns are the same).

    python -m synthbos.benchmarks.bench_scaling --gpus 0,1,2,3 --counts 1,2,4 --pairs-per-gpu 20 --out scaling
    python -m synthbos.benchmarks.bench_scaling --device cpu --counts 1,2 --pairs-per-gpu 5 --pixels 96 --rays 20

(the second line is a smoke run on CPU workers).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from synthbos import SynthbosError, atomic_output

from .campaign import run_campaign
from .distributed import LOCAL_WORKERS_PER_GPU, DaskRunner, visible_gpus
from .spec import FULL, CampaignSpec

__all__ = ["campaign_spec", "main", "run_scaling", "run_side_by_side"]


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
    from .registry import default_methods

    t0 = time.perf_counter()
    pair = str(Path(folder) / f"warm-{time.monotonic_ns()}.h5")
    render_item({"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 10}}, pair, device)
    for m in default_methods():
        score_item(pair, m, 1.0, (1, 2), pair.replace(".h5", f"-{m}.npz"), {}, device)
    return time.perf_counter() - t0


def _warm_up_pipeline(device: str, folder: str) -> float:
    """On a GPU worker: a tiny campaign through :func:`distributed.pipeline_task`, so the worker's own
    pool of host processes (its fork server, imports, kernels) is started the way the baseline's is."""
    from .distributed import pipeline_task

    t0 = time.perf_counter()
    spec = campaign_spec(1, pixels=96, rays=10)
    out = Path(folder) / f"pipeline-{time.monotonic_ns()}"
    renders = [(spec.pair_config(s, p), str(out / f"{s}-{p}.h5"), device) for s, p in spec.pair_keys()[:1]]
    scores = [(renders[0][1], m, 1.0, (1, 2), str(out / f"{m}.npz"), {}, device) for m in spec.methods]
    out.mkdir(parents=True)
    pipeline_task(renders, scores, f"warm-{out.name}")
    return time.perf_counter() - t0


def _same_scores(first: Path, other: Path) -> bool:
    """Whether every score file of ``first`` has bit-identical arrays in ``other``."""
    for path in sorted((first / "scores").glob("*.npz")):
        with np.load(path) as a, np.load(other / "scores" / path.name) as b:
            if sorted(a.files) != sorted(b.files) or any(a[k].tobytes() != b[k].tobytes() for k in a.files):
                return False
    return True


def run_scaling(counts, *, device: str, pairs=None, pairs_per_gpu=20, gpus=None, per_gpu: int = LOCAL_WORKERS_PER_GPU,
                folder=None, progress=False, **spec_options) -> list[dict]:
    """Time the campaign on each count of ``counts`` (GPUs, or CPU workers); return one row per count."""
    rows, outs = [], []
    on_gpu = device.startswith("cuda")
    with tempfile.TemporaryDirectory(prefix="synthbos-scaling-") as tmp:
        base = Path(folder or tmp)
        base.mkdir(parents=True, exist_ok=True)
        for n in counts:
            spec = campaign_spec(pairs or pairs_per_gpu * n, **spec_options)
            t0 = time.perf_counter()
            workers = n * per_gpu if on_gpu else n
            runner = DaskRunner("local", device=device, gpus=gpus[:n] if on_gpu else None, workers=workers,
                                progress=progress)
            with runner:
                client = runner.client
                client.wait_for_workers(workers)
                warm = Path(tmp) / f"warm-{n}"
                warm.mkdir()
                # By reference, even when this file runs as __main__: the workers import it.
                from synthbos.benchmarks.bench_scaling import _warm_up, _warm_up_pipeline

                warm_up = _warm_up_pipeline if runner.pipeline else _warm_up
                client.gather([client.submit(warm_up, device, str(warm), workers=[a], pure=False)
                               for a in client.nthreads()])
                t1 = time.perf_counter()
                out = base / f"{n}-{'gpu' if on_gpu else 'cpu'}"
                run_campaign(spec, out, device=device, scheduler=runner, progress=progress, figures=False)
                t2 = time.perf_counter()
            outs.append(out)
            n_pairs = len(spec.pair_keys())
            rows.append({"units": n, "workers": workers, "pairs": n_pairs, "startup_s": t1 - t0,
                         "campaign_s": t2 - t1, "pairs_per_s": n_pairs / (t2 - t1),
                         "pairs_per_s_with_startup": n_pairs / (t2 - t0)})
        small = min(range(len(rows)), key=lambda i: rows[i]["pairs"])  # its pairs are in every campaign
        for r, out in zip(rows, outs, strict=True):
            r["speedup"] = r["pairs_per_s"] / rows[0]["pairs_per_s"]
            r["efficiency"] = r["speedup"] / (r["units"] / rows[0]["units"])
            same = _same_scores(outs[small], out)
            if r["pairs"] == rows[0]["pairs"]:
                same = same and (out / "results.json").read_bytes() == (outs[0] / "results.json").read_bytes()
            r["identical_results"] = same
    return rows


def run_plain(*, device: str, pairs: int, workers=None, folder, before=None, **spec_options) -> dict:
    """Time the same campaign without Dask (``scheduling.run_pipeline`` in this process, ``workers``
    processes, default every core) on one GPU, after a warm-up here: the baseline of the efficiency.
    ``before``, when given, is called between the warm-up and the timed campaign (:func:`run_side_by_side`'s
    campaigns wait there for each other)."""
    from .scheduling import default_workers

    spec = campaign_spec(pairs, **spec_options)
    folder = Path(folder)
    # warm-up: a tiny campaign the same way (kernels, imports, the worker pool's fork server)
    tiny = campaign_spec(1, pixels=96, rays=10, noise=spec_options.get("noise", (0.0,)))
    run_campaign(tiny, folder / f"warm-{workers or 'all'}", device=device, workers=workers, progress=False,
                 figures=False)
    if before is not None:
        before()
    out = folder / f"plain-{workers or 'all'}"
    t0 = time.perf_counter()
    run_campaign(spec, out, device=device, workers=workers, progress=False, figures=False)
    seconds = time.perf_counter() - t0
    n_pairs = len(spec.pair_keys())
    return {"workers": workers or default_workers(), "pairs": n_pairs, "campaign_s": seconds,
            "pairs_per_s": n_pairs / seconds, "folder": out}


def run_side_by_side(units, *, device: str, pairs: int, workers: int, folder, **spec_options) -> dict:
    """Time ``len(units)`` plain campaigns at once without Dask, one per GPU of ``units`` (``device`` "cuda:0":
    each in its own process that sees only its GPU; "cpu": CPU campaigns), each of ``pairs`` pairs with
    ``workers`` processes, every timed campaign started at one moment after all their warm-ups: the most
    this host gives that many GPUs with no scheduler between them, against which a Dask run is read.

    Returns ``campaigns`` (each one's ``campaign_s`` and ``pairs_per_s``), ``pairs_per_s`` (their sum),
    ``units`` and ``identical_results`` (their ``results.json`` the same bytes)."""
    folder = Path(folder)
    procs = []
    try:
        for i, unit in enumerate(units):
            env = dict(os.environ)
            if device.startswith("cuda"):
                env["CUDA_VISIBLE_DEVICES"] = str(unit)
            job = {"device": device, "pairs": pairs, "workers": workers, "folder": str(folder / f"side-{i}"),
                   "spec": spec_options}
            procs.append(subprocess.Popen(
                [sys.executable, "-c", "from synthbos.benchmarks.bench_scaling import _side_child; _side_child()",
                 json.dumps(job)], env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True))
        for proc in procs:  # each has warmed up
            _child_line(proc, lambda line: line == "ready", "its warm-up")
        for proc in procs:
            proc.stdin.write("go\n")
            proc.stdin.flush()
        campaigns = [json.loads(_child_line(proc, lambda line: line.startswith("{"), "its campaign")) for proc in procs]
        for proc in procs:
            if proc.wait() != 0:
                raise SynthbosError(f"a side-by-side campaign ended with exit status {proc.returncode}")
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    results = {(Path(c["folder"]) / "results.json").read_bytes() for c in campaigns}
    return {"units": len(units), "campaigns": campaigns, "pairs_per_s": sum(c["pairs_per_s"] for c in campaigns),
            "identical_results": len(results) == 1}


def _child_line(proc, wanted, what: str) -> str:
    """The first line of ``proc``'s output that ``wanted`` accepts (others, such as notes, are passed over)."""
    for line in proc.stdout:
        if wanted(line.strip()):
            return line.strip()
    raise SynthbosError(f"a side-by-side campaign failed in {what} (exit status {proc.wait()})")


def _side_child() -> None:
    """One campaign of :func:`run_side_by_side`: warm up, print ``ready``, wait for a line on stdin, run the
    timed campaign and print its time as one line of JSON."""
    job = json.loads(sys.argv[1])
    try:
        _side_campaign(job)
    except SynthbosError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)


def _side_campaign(job: dict) -> None:
    def ready():  # warmed up: say so, and wait for the others
        print("ready", flush=True)
        sys.stdin.readline()

    r = run_plain(device=job["device"], pairs=job["pairs"], workers=job["workers"], folder=job["folder"],
                  before=ready, **job["spec"])
    print(json.dumps({"folder": str(r["folder"]), "campaign_s": r["campaign_s"], "pairs_per_s": r["pairs_per_s"]}),
          flush=True)


def format_table(rows, unit: str) -> str:
    lines = [f"| {unit}s | workers | pairs | start-up + warm-up s | campaign s | pairs/s | pairs/s with start-up "
             f"| speed-up | efficiency | common pairs bit-identical |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['units']} | {r['workers']} | {r['pairs']} | {r['startup_s']:.1f} | {r['campaign_s']:.1f} "
                     f"| {r['pairs_per_s']:.3f} | {r['pairs_per_s_with_startup']:.3f} | {r['speedup']:.2f} "
                     f"| {r['efficiency']:.2f} | {'yes' if r['identical_results'] else 'NO'} |")
    return "\n".join(lines)


def _plain_table(rows, gpus, args) -> str:
    """The baseline without Dask on one GPU, and each row's efficiency against N times it."""
    from .scheduling import default_workers

    first = min(rows, key=lambda r: r["units"])
    with tempfile.TemporaryDirectory(prefix="synthbos-plain-") as tmp:
        spec_options = {"pixels": args.pixels, "rays": args.rays, "noise": [float(v) for v in args.noise.split(",")]}
        share = max(1, default_workers() // max(1, len(gpus)))
        # every core, and a GPU worker's share (once where they are the same: a second campaign into the same
        # folder would find its work done)
        plain = [run_plain(device=args.device, pairs=first["pairs"], workers=w, folder=tmp, **spec_options)
                 for w in sorted({default_workers(), share}, reverse=True)]
    best = max(plain, key=lambda p: p["pairs_per_s"])  # like with like: the faster of the two
    lines = [f"Without Dask on one GPU ({first['pairs']} pairs): "
             + "; ".join(f"{p['workers']} processes {p['pairs_per_s']:.3f} pairs/s ({p['campaign_s']:.1f} s)"
                         for p in plain),
             "", f"| GPUs | pairs/s through Dask | N x plain ({best['workers']} processes, the faster) "
                 "| efficiency vs plain |",
             "| --- | --- | --- | --- |"]
    for r in rows:
        ideal = r["units"] * best["pairs_per_s"]
        r["efficiency_vs_plain"] = r["pairs_per_s"] / ideal
        lines.append(f"| {r['units']} | {r['pairs_per_s']:.3f} | {ideal:.3f} | {r['efficiency_vs_plain']:.2f} |")
    if args.side_by_side:
        alone = next(p for p in plain if p["workers"] == share)
        lines += ["", f"The host's own limit: N plain campaigns at once, one per GPU, {share} processes each, "
                      f"against one alone ({alone['pairs_per_s']:.3f} pairs/s):", "",
                  "| GPUs | pairs/s through Dask | N plain campaigns at once, pairs/s | each against one alone "
                  "| Dask against them | their results the same |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for r in rows:
            if r["units"] < 2:
                continue
            with tempfile.TemporaryDirectory(prefix="synthbos-side-") as tmp:
                side = run_side_by_side(gpus[: r["units"]], device=args.device, workers=share, folder=tmp,
                                        pairs=math.ceil(r["pairs"] / r["units"]), **spec_options)
            r["side_by_side_pairs_per_s"] = side["pairs_per_s"]
            r["efficiency_vs_side_by_side"] = r["pairs_per_s"] / side["pairs_per_s"]
            each = side["pairs_per_s"] / (r["units"] * alone["pairs_per_s"])
            lines.append(f"| {r['units']} | {r['pairs_per_s']:.3f} | {side['pairs_per_s']:.3f} | {each:.2f} "
                         f"| {r['efficiency_vs_side_by_side']:.2f} | {'yes' if side['identical_results'] else 'NO'} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda:0", help="cuda:0 (each worker's own GPU) or cpu (CPU workers)")
    parser.add_argument("--gpus", default=None, help="GPUs to pin workers to, e.g. 0,1,2,3 (default: all visible)")
    parser.add_argument("--counts", default="1,2,4", help="GPU (or CPU worker) counts to time, e.g. 1,2,4")
    parser.add_argument("--per-gpu", type=int, default=LOCAL_WORKERS_PER_GPU,
                        help=f"workers per GPU (default: {LOCAL_WORKERS_PER_GPU}, as --scheduler local starts)")
    parser.add_argument("--pairs-per-gpu", type=int, default=20, help="pairs per GPU (or CPU worker): weak scaling")
    parser.add_argument("--pairs", type=int, default=None, help="pairs in every campaign instead: strong scaling")
    parser.add_argument("--pixels", type=int, default=512)
    parser.add_argument("--rays", type=int, default=1000, help="rays per dot")
    parser.add_argument("--noise", default="0,1,3,5", help="noise levels, percent of the dot peak")
    parser.add_argument("--out", default=None, help="write scaling.json and scaling.md here")
    parser.add_argument("--keep", default=None, help="keep the campaign folders here (default: a temporary folder)")
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--no-plain", dest="plain", action="store_false",
                        help="skip the baseline: the same campaign on one GPU without Dask (every core, and the "
                             "cores a Dask GPU worker gets)")
    parser.add_argument("--no-side-by-side", dest="side_by_side", action="store_false",
                        help="skip the host's own limit: for each count N > 1, N plain campaigns at once, one per "
                             "GPU, each with a GPU's share of the cores (needs the baseline)")
    args = parser.parse_args(argv)
    counts = [int(c) for c in args.counts.split(",")]
    on_gpu = args.device.startswith("cuda")
    gpus = (args.gpus.split(",") if args.gpus else visible_gpus()) if on_gpu else None
    if on_gpu and max(counts) > len(gpus):
        parser.error(f"--counts asks for {max(counts)} GPUs but only {len(gpus)} are available: {gpus}")
    noise = [float(v) for v in args.noise.split(",")]
    name = "cpu"
    if on_gpu:
        import warp as wp

        name = wp.get_device("cuda:0").name
    size = f"{args.pairs} pairs" if args.pairs else f"{args.pairs_per_gpu} pairs per {'GPU' if on_gpu else 'worker'}"
    print(f"scaling: {size} of {args.pixels} x {args.pixels} px, {args.rays} rays/dot, noise {args.noise} %, "
          f"every method; {name}; counts {counts}", flush=True)
    rows = run_scaling(counts, device=args.device, pairs=args.pairs, pairs_per_gpu=args.pairs_per_gpu, gpus=gpus,
                       per_gpu=args.per_gpu, folder=args.keep, progress=args.progress, pixels=args.pixels,
                       rays=args.rays, noise=noise)
    table = format_table(rows, "GPU" if on_gpu else "CPU worker")
    print(table, flush=True)
    if on_gpu and args.plain:
        table += "\n\n" + _plain_table(rows, gpus, args)
    date = time.strftime("%Y-%m-%d", time.gmtime())
    print(f"\n{date}, {name}\n{table}")
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        meta = {"date": date, "device": name, "args": vars(args), "rows": rows}
        with atomic_output(out / "scaling.json") as tmp:
            tmp.write_text(json.dumps(meta, indent=1))
        with atomic_output(out / "scaling.md") as tmp:
            tmp.write_text(f"{date}, {name}\n\n{table}\n")
    return rows


if __name__ == "__main__":
    main()
