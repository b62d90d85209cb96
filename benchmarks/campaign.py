"""Campaigns: render BOS pairs through known density fields, process them with every method, score.

The runner only orders the work; each job has its own module: the spec and seeds (``spec``), the
work items (``items``), how items run (``scheduling``), the folder and stored scores (``storage``),
the results table (``tables``) and the figures (``figures``). Each pair and each score is its own
file written atomically, so a re-run skips finished work and an interrupted run loses only the items
in progress.
"""

from __future__ import annotations

from pathlib import Path

from synthbos.raytrace import load_config

from .figures import figure4, figure5
from .items import render_item, score_item
from .registry import get_method
from .scheduling import default_workers, run_items
from .spec import CampaignSpec
from .storage import check_folder, pair_path, score_path, write_tables
from .tables import summarise

__all__ = ["run_campaign"]


def run_campaign(spec: CampaignSpec, folder, *, device=None, workers=None, progress=True, figures=True,
                 scheduler=None):
    """Render, process and score a campaign in ``folder``, skipping finished items; return the summary.

    With ``scheduler`` (``"local"``, a Dask scheduler address or file, or an open
    ``distributed.DaskRunner``) the items run on a Dask cluster, one task per pair (``distributed``);
    the files and the summary are the same.

    Returns
    -------
    list of dict
        One row per method, noise level, split and quantity (see ``tables.summarise``).
    """
    folder = Path(folder)
    methods = [get_method(name) for name in spec.methods]  # an unknown method fails before any work
    for s, p in spec.pair_keys()[:1]:  # so does a bad configuration
        load_config(spec.pair_config(s, p))
    check_folder(folder, spec)
    on_gpu = device is not None and str(device).startswith("cuda")
    renders = [
        (spec.pair_config(s, p), str(pair_path(folder, s, p)), device)
        for s, p in spec.pair_keys()
        if not pair_path(folder, s, p).exists()
    ]
    scores = []
    for s, p in spec.pair_keys():
        for noise in spec.noise_percent:
            seeds = (spec.noise_seed(s, p, noise, "reference"), spec.noise_seed(s, p, noise, "gradient"))
            for m in methods:
                out = score_path(folder, s, p, noise, m.name)
                if not out.exists():
                    scores.append((str(pair_path(folder, s, p)), m.name, noise, seeds, str(out),
                                   spec.overrides_for(m)))
    if scheduler is not None:  # Dask: each pair is rendered and scored by one task, on one worker
        from .distributed import run_pairs

        run_pairs(renders, scores, scheduler=scheduler, device=device, workers=workers, progress=progress)
    else:
        workers = workers or default_workers()
        run_items(renders, render_item, workers=1 if on_gpu else workers, desc="render", progress=progress)
        run_items(scores, score_item, workers=workers, desc="process", progress=progress)
    rows = summarise(spec, folder)
    write_tables(rows, folder)
    if figures:
        figure4(spec, folder, folder / "fig4")
        figure5(spec, folder, folder / "fig5")
    return rows
