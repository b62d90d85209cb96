"""Campaigns: render BOS pairs through known density fields, process them with every method, score.

The runner only orders the work; each job has its own module: the spec and seeds (``spec``), the
work items (``items``), how items run (``scheduling``), the folder and stored scores (``storage``),
the results table (``tables``) and the figures (``figures``). Each pair and each score is its own
file written atomically, so a re-run skips finished work and an interrupted run loses only the items
in progress.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

from synthbos.raytrace import checks, plan_render

from synthbos import SynthbosError, folder_lock, make_folder
from synthbos.device import check_device

from .campaign_figures import CAMPAIGN_FIGURES, FIRST_PAIR_FIGURES, FORMATS
from .integrate import floor_current, pair_floor
from .items import by_pair_and_noise, render_item, score_items
from .registry import check_available, get_method
from .scheduling import (
    PIPELINE_DRIVERS,
    PIPELINE_WORKER_DEVICE,
    default_workers,
    pipeline_workers,
    render_kernels,
    run_items,
    run_pipeline,
    score_kernels,
    worker_pool,
)
from .spec import CampaignSpec
from .stacks import check_stack
from .storage import check_folder, pair_path, score_path, write_tables
from .tables import floor_rows, summarise, summary_groups, summary_rows

__all__ = ["PIPELINE_DRIVERS", "PIPELINE_WORKER_DEVICE", "campaign_order", "check_campaign_stack", "check_drivers",
           "check_spec", "draw_figure", "resolve_process_device", "run_campaign", "write_summary"]



def run_campaign(spec: CampaignSpec, folder, *, device=None, workers=None, progress=True, figures=True,
                 scheduler=None, wait=False, process_device=None, pipeline=None, worker_device=None, timings=None,
                 stack=None, stacks=None, drivers=None, drivers_log=None):
    """Render, process and score a campaign in ``folder``, skipping finished items; return the summary.

    ``device`` renders; ``process_device`` runs the methods (default: ``device``, and the CPU when
    neither is given). Every score file, and the results table's column ``process_device``, records it.

    Without a scheduler, a campaign that processes on the CPU runs its renders and then its score
    items in a pool of ``workers`` processes; one that processes on a GPU runs as a pipeline
    (``scheduling.run_pipeline``): this process does the device work of pair after pair while
    ``workers - 1`` processes score the results. ``pipeline`` (True or False) chooses either way
    whatever the device; the files are byte-identical. In the pipeline the methods that are not
    device resident (tracking, unless tracked in stacks: ``stack`` below) run in the worker
    processes, on ``worker_device``: by default the CPU
    (``PIPELINE_WORKER_DEVICE``), since their host work between kernels dominates and a dozen processes
    sharing one GPU by time slices were measured slower than on their own cores; pass the GPU to run
    them there. Each score file records the device that processed it.

    ``stack``: pairs per stack of tracking items (``stacks``; ``scheduling.run_pipeline``): the
    pipeline tracks the noisy images of every noise level of up to ``stack`` pairs with one
    ``tracking.stack.track_pairs`` call, in the process that drives the device. None: stacks of
    ``stacks.DEFAULT_STACK`` pairs when processing on a GPU, and item by item in the worker processes on
    the CPU, where they spread the pairs over the cores; 0: item by item. A ``stack`` > 0 on the CPU
    runs the pipeline (unless ``pipeline`` is False, which is refused), so the CPU runs the same
    orchestration as a GPU; the results equal the item-by-item ones to floating-point rounding.
    ``stacks`` (a list, optional) receives one entry per ``track_pairs`` call (``stacks.Stacks``).

    ``drivers``: processes that drive the GPU in the pipeline, this one included, each taking the next
    pair no one has taken (``benchmarks.drivers``); None: :data:`PIPELINE_DRIVERS` when processing on a
    GPU, else 1. The files are the same whatever the count. ``drivers_log`` (a list, optional) receives
    the pairs each of them took.

    Everything a user can get wrong (the configuration, the methods and their settings, the folder) is
    checked before any work starts. The folder is locked (``folder/.lock``) for the campaign's life: a
    second campaign into it is refused at once, or waits for the first with ``wait=True``.

    With ``scheduler`` (``"local"``, a Dask scheduler address or file, or an open
    ``distributed.DaskRunner``) the items run on a Dask cluster, one task per pair (``distributed``);
    the files and the summary are the same.

    ``timings`` (a dict, optional) receives the wall seconds of the phases: ``"render and process"``,
    ``"tables"`` and ``"figures"``; in the pipeline, where fig4 is drawn during the rendering and the
    tables beside the other figures, ``"render and process"`` and ``"tables and figures, after the last
    item"``.

    Returns
    -------
    list of dict
        One row per method, noise level, split and quantity (see ``tables.summarise``).
    """
    folder = Path(folder)
    process_device = resolve_process_device(device, process_device)
    check_spec(spec, device, process_device)  # a bad method, setting, device or configuration fails before any work
    if isinstance(scheduler, str):
        from .distributed import check_scheduler

        check_scheduler(scheduler)  # so does a bad --scheduler, even for a finished campaign
    methods = [get_method(name) for name in spec.methods]
    check_campaign_stack(stack, spec, device=device, scheduler=scheduler, pipeline=pipeline)
    check_drivers(drivers)
    if pipeline is None:
        pipeline = process_device.startswith("cuda") or bool(stack)
    make_folder(folder)
    with folder_lock(folder, wait=wait):
        return _run_locked(spec, folder, methods, device=device, workers=workers, progress=progress,
                           figures=figures, scheduler=scheduler, process_device=process_device, pipeline=pipeline,
                           worker_device=worker_device, timings={} if timings is None else timings, stack=stack,
                           stacks=stacks, drivers=drivers, drivers_log=drivers_log)


def check_campaign_stack(stack, spec: CampaignSpec, *, device=None, scheduler=None, pipeline=None) -> None:
    """Refuse, in one line, a ``stack`` (pairs per stack) that a campaign cannot honour: not a count, no method
    tracked in stacks (``stacks.check_stack``), the pipeline turned off, or Dask workers that run one task
    per pair (a cluster that renders on the CPU) instead of the pipeline."""
    check_stack(stack, spec.methods, lambda name: spec.overrides_for(get_method(name)))
    if not stack:
        return
    if scheduler is None and pipeline is False:
        raise SynthbosError(f"stack {stack}: stacks are tracked by the pipeline, which pipeline=False turns off")
    on_pipeline = getattr(scheduler, "pipeline", str(device or "").startswith("cuda"))
    if scheduler is not None and not on_pipeline:
        raise SynthbosError(f"--stack {stack}: with --scheduler on CPU workers each pair is a task of its own; "
                            "stacks are tracked by GPU workers (--device cuda), which run the pipeline")


def check_drivers(drivers) -> None:
    """Refuse, in one line, a count of processes driving the GPU (``drivers``) that is not a whole number >= 1."""
    if drivers is None:
        return
    if isinstance(drivers, bool) or not isinstance(drivers, int) or drivers < 1:
        raise SynthbosError(f"--drivers must be a whole number of processes, 1 or more, got {drivers!r}")


def resolve_process_device(device=None, process_device=None) -> str:
    """The processing device of a campaign: ``process_device``, else the render ``device``, else ``"cpu"``."""
    chosen = process_device if process_device is not None else device
    return "cpu" if chosen is None else str(chosen)


def check_spec(spec: CampaignSpec, device=None, process_device=None) -> None:
    """Check a campaign spec without rendering: its methods, their settings, noise levels, devices and render plan."""
    if process_device is not None:
        check_device(process_device)
    for noise in spec.noise_percent:
        if not (isinstance(noise, int | float) and math.isfinite(noise) and 0 <= noise <= 100):
            raise SynthbosError(f"noise level must be a percentage in 0..100, got {noise!r}")
    for name in spec.methods:
        m = get_method(name)
        check_available(m)
        overrides = spec.overrides_for(m)
        if overrides:
            m.settings(overrides)
    for s, p in spec.pair_keys()[:1]:
        checks.check_ray_steps(plan_render(spec.pair_config(s, p)), device)  # configuration, limits, view


def _run_locked(spec, folder, methods, *, device, workers, progress, figures, scheduler, process_device, pipeline,
                worker_device=None, timings, stack=None, stacks=None, drivers=None, drivers_log=None):
    t0 = time.perf_counter()
    check_folder(folder, spec)
    # Temporary files of a run killed while writing (SIGKILL): no one else writes here while we hold the lock.
    for sub in (folder, folder / "pairs", folder / "scores", folder / "floors"):
        for stale in sub.glob(".*.tmp"):
            stale.unlink(missing_ok=True)
    on_gpu = device is not None and str(device).startswith("cuda")
    keys = campaign_order(spec)
    renders = [
        (spec.pair_config(s, p), str(pair_path(folder, s, p)), device)
        for s, p in keys
        if not pair_path(folder, s, p).exists()
    ]
    scores = []
    for s, p in keys:
        for noise in spec.noise_percent:
            seeds = (spec.noise_seed(s, p, noise, "reference"), spec.noise_seed(s, p, noise, "gradient"))
            for m in methods:
                out = score_path(folder, s, p, noise, m.name)
                if not out.exists():
                    scores.append((str(pair_path(folder, s, p)), m.name, noise, seeds, str(out),
                                   spec.overrides_for(m), process_device))
    if progress:
        _resume_note(folder, n_pairs=len(keys), n_scores=len(keys) * len(spec.noise_percent) * len(methods),
                     renders=len(renders), scores=len(scores))
    # host processes here: one GPU's pipeline at most PIPELINE_MAX_WORKERS of them, else every core (Dask
    # workers size their own)
    host = workers or (pipeline_workers() if pipeline and scheduler is None else default_workers())
    figure_jobs = _figure_jobs(spec, folder, workers=host) if figures else []
    if pipeline and scheduler is None:
        # The device work here; scoring, the tables and the figures in worker processes. A figure that
        # reads pair files only (fig4) is drawn as soon as they are rendered; the rest after the last item.
        # The table's (noise level, method) groups are summarised side by side, one job each. After the last
        # item the late figures start first: they take longest, and the summaries fill the other workers.
        groups = summary_groups(spec)
        floors = _pair_paths(spec, folder)
        jobs = [(pair_floor, (path,), {path}) for path in floors]  # each as soon as its pair is there
        jobs += [(draw_figure, args, _figure_pairs(args[0], spec, folder)) for args in figure_jobs]
        jobs += [(summary_rows, (spec, str(folder), noise, m), None) for noise, m in groups]
        t_items = []
        there = PIPELINE_WORKER_DEVICE if worker_device is None else worker_device
        if drivers is None:
            drivers = PIPELINE_DRIVERS if process_device.startswith("cuda") else 1
        parts = run_pipeline(renders, scores, workers=host, progress=progress,
                             worker_device=there, jobs=jobs, stack=stack, stacks_log=stacks, drivers=drivers,
                             drivers_log=drivers_log, on_items_done=lambda: t_items.append(time.perf_counter()))
        rows = [row for part in parts[len(floors) + len(figure_jobs) :] for row in part]
        write_tables(rows, folder)
        # a pair another driver took: its floor is in its file (``pair_floor`` reads it)
        made = [pair_floor(path) if part is None else part for path, part in zip(floors, parts, strict=False)]
        write_tables(floor_rows(made), folder, stem="floor")
        timings["render and process"] = t_items[0] - t0
        timings["tables and figures, after the last item"] = time.perf_counter() - t_items[0]
        return rows
    if scheduler is not None:  # Dask: each pair is rendered and scored by one task, on one worker
        from .distributed import campaign_runner

        with campaign_runner(scheduler, needed=bool(renders or scores), device=device, workers=workers,
                             progress=progress, process_device=process_device) as runner:
            if runner is not None:
                runner.run_pairs(renders, scores, stack=stack)
            t1 = time.perf_counter()
            rows = write_summary(spec, folder, mapper=map if runner is None else runner.map)  # on the cluster
    else:
        processing = score_kernels(scores)
        with worker_pool(host) as pool:  # the same processes render and then score: kernels built once
            run_items(renders, render_item, workers=1 if on_gpu else host, desc="render", progress=progress,
                      kernels=render_kernels(renders), pool=None if on_gpu else pool, build_after=processing)
            # a pair's items of one noise level in one task: tracking and tracking-cc share one tracker run
            run_items(by_pair_and_noise(scores), score_items, workers=host, desc="process", progress=progress,
                      kernels=processing, pool=pool)
            t1 = time.perf_counter()
            rows = write_summary(spec, folder, mapper=map if pool is None else pool.map)
    t2 = time.perf_counter()
    timings["render and process"] = t1 - t0
    timings["tables"] = t2 - t1
    if figure_jobs:  # side by side in worker processes: matplotlib draws on one core
        run_items(figure_jobs, draw_figure, workers=min(len(figure_jobs), host),
                  desc="figures", progress=progress)
        timings["figures"] = time.perf_counter() - t2
    return rows


def _resume_note(folder, *, n_pairs: int, n_scores: int, renders: int, scores: int) -> None:
    """One line when a campaign resumes: how many of its items (pairs to render, scores to make) a former run
    finished, and how many are left to run."""
    total, left = n_pairs + n_scores, renders + scores
    if left == total:
        return
    print(f"resumed {folder}: {total - left} of {total} items already done ({n_pairs - renders} of {n_pairs} pairs "
          f"rendered, {n_scores - scores} of {n_scores} scores made), {left} to run")


def campaign_order(spec: CampaignSpec) -> list:
    """The campaign's pairs in the order they are rendered and processed: the first pair of every
    snapshot, then the others (pair after pair within a snapshot), so that what is drawn from first
    pairs (``campaign_figures.FIRST_PAIR_FIGURES``) can start early. Every item depends only on its own key."""
    return sorted(spec.pair_keys(), key=lambda key: key[1] > 0)


def _figure_jobs(spec: CampaignSpec, folder, *, workers: int) -> list[tuple]:
    """:func:`draw_figure` arguments: one job per figure drawn early (``FIRST_PAIR_FIGURES``); for those
    drawn from the scores at the end, one per figure and format where ``workers`` processes can draw them all
    side by side (they finish sooner), else one per figure, drawn once and saved in every format (on two
    cores, the quick campaign's figures 9.5 -> 6 s: a figure's layout is most of its cost).

    Examples
    --------
    >>> from synthbos.benchmarks.spec import QUICK
    >>> len(_figure_jobs(QUICK, "out", workers=2)), len(_figure_jobs(QUICK, "out", workers=14))
    (4, 10)
    """
    late = [stem for stem in CAMPAIGN_FIGURES if stem not in FIRST_PAIR_FIGURES]
    split = workers >= len(CAMPAIGN_FIGURES) - len(late) + len(late) * len(FORMATS)
    jobs = []
    for stem in CAMPAIGN_FIGURES:
        formats = [(fmt,) for fmt in FORMATS] if split and stem in late else [None]
        jobs += [(stem, spec, str(folder), fmts) for fmts in formats]
    return jobs


def draw_figure(stem: str, spec: CampaignSpec, folder, formats=None) -> str:
    """Draw the campaign figure ``stem`` into ``folder`` (``figures.campaign_figure``); return its stem path.
    A campaign's worker processes run it: matplotlib is imported where a figure is drawn, not in the
    campaign's process, and ahead of the first job (``preload``: the module a worker imports before its
    first job, ``scheduling.run_pipeline``).

    Examples
    --------
    >>> draw_figure.preload
    'synthbos.benchmarks.figures'
    """
    from .figures import campaign_figure

    return campaign_figure(stem, spec, folder, formats)


draw_figure.preload = "synthbos.benchmarks.figures"


def _figure_pairs(stem: str, spec: CampaignSpec, folder):
    """The pair files a campaign figure reads, when it reads nothing else (None: it reads scores too)."""
    if stem not in FIRST_PAIR_FIGURES:
        return None
    return {str(pair_path(folder, s, 0)) for s in spec.snapshots}


def write_summary(spec: CampaignSpec, folder, *, mapper=map) -> list[dict]:
    """The campaign's results table: summarise its score files, write ``results.csv`` and ``.json``, return the rows.
    Beside it the density floor (``floor.csv`` and ``.json``, ``tables.floor_rows``): its pairs' exact
    displacements integrated and scored alike.

    ``mapper`` maps the table's groups (``tables.summarise``) and the floors the workers did not already
    keep (``integrate.pair_floor``): a pool's or a Dask cluster's ``map`` does them side by side."""
    rows = summarise(spec, folder, mapper=mapper)
    write_tables(rows, folder)
    paths = _pair_paths(spec, folder)
    missing = [p for p in paths if not floor_current(p)]
    made = dict(zip(missing, mapper(pair_floor, missing), strict=True))
    write_tables(floor_rows([made[p] if p in made else pair_floor(p) for p in paths]), folder, stem="floor")
    return rows


def _pair_paths(spec: CampaignSpec, folder) -> list[str]:
    """Every pair file of the campaign (the density floor's inputs), in its pairs' order."""
    return [str(pair_path(folder, s, p)) for s, p in spec.pair_keys()]
