"""Regenerate every figure in ``docs/``, and say what was written.

    python docs/make_figures.py                         # runs 'synthbos paper --quick' itself (about a minute
                                                        # on two CPU cores), then draws the quick_*.png
    python docs/make_figures.py --campaign runs/paper-quick
    python docs/make_figures.py --campaign Q --fig5 FNUMBER_SWEEP SCALE_SWEEP DEFAULT_CAMPAIGN NARROW_CAMPAIGN

Figures and where they come from:

- ``quick_fig4.png``, ``quick_fig5.png``, ``quick_fig_density.png``, ``quick_fig_budget.png`` (README, accuracy):
  the campaign figures of a quick campaign (``--campaign FOLDER``, else one run here into ``--work``).
- ``fig5_sweep.png``, ``fig5_default.png``, ``fig5_narrow.png`` (``docs/fig5.md``): with ``--fig5``, from the two
  sweeps and the two campaigns that page lists (``synthbos sweep --param f_number=...`` and the density-scale
  sweep; ``synthbos paper --quick --methods ...`` of the default and the narrow set-up, every method).

Each is drawn by ``synthbos.benchmarks.figures`` at journal size (7.2 in wide, text >= 7 pt) and stored
as a PNG of ``--width`` pixels (1440: 200 dpi at 7.2 in) in 256 colours, small enough for the repository;
the campaigns' own folders keep the 300 dpi PNG, PDF and SVG. Figures whose source is not given are left as
they are (and listed as such).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import FormatStrFormatter, NullFormatter
from PIL import Image
from synthbos.benchmarks import figures
from synthbos.benchmarks.figures import METHODS, TWO_COLUMNS_IN, journal_style, method_style
from synthbos.benchmarks.scoring import cramer_rao_displacement
from synthbos.benchmarks.spec import CampaignSpec

DOCS = Path(__file__).resolve().parent
QUICK_FIGURES = ("fig4", "fig5", "fig_density", "fig_budget")
FIG5_PANELS = ((0.0, "all", "zero noise, all points"), (5.0, "above", "5 % noise, |ΔX| ≥ threshold"))


def campaign_spec(folder) -> CampaignSpec:
    """The spec of a campaign folder, from its ``campaign.json``."""
    path = Path(folder) / "campaign.json"
    if not path.is_file():
        raise SystemExit(f"make_figures: {folder} is not a campaign folder (no campaign.json)")
    d = json.loads(path.read_text())
    return CampaignSpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def reduced(src, out, *, width):
    """``src`` (a 300 dpi PNG) as ``out``: ``width`` pixels wide, 256 colours, optimised."""
    with Image.open(src) as im:
        im = im.convert("RGB")
        im.thumbnail((width, width * 4), Image.Resampling.LANCZOS)
        im.quantize(colors=256, dither=Image.Dither.NONE).save(out, optimize=True)
    return Path(out)


def campaign_figure(stem, folder, out, *, work, width):
    """A campaign's figure ``stem`` redrawn from its folder (the current code), reduced into ``out``."""
    spec = campaign_spec(folder)
    tmp = Path(work) / f"{Path(folder).name}_{stem}"
    written = figures.CAMPAIGN_FIGURES[stem](spec, folder, tmp, formats=("png",))
    if stem == "fig_budget" and written is None:
        return None  # pairs without the ray covariance: no budget to draw
    return reduced(tmp.with_suffix(".png"), out, width=width)


def run_quick_campaign(work) -> Path:
    """``synthbos paper --quick`` on the CPU into ``work/paper-quick``; its folder."""
    from synthbos.benchmarks.cli import main

    folder = Path(work) / "paper-quick"
    t0 = time.perf_counter()
    if main(["paper", "--quick", "--out", str(folder), "--device", "cpu", "-q"]) != 0:
        raise SystemExit("make_figures: the quick campaign failed")
    print(f"quick campaign: {time.perf_counter() - t0:.0f} s -> {folder}")
    return folder


def _sweep_rows(folder):
    with open(Path(folder) / "sweep.csv", newline="") as f:
        return list(csv.DictReader(f))


def _number(text):
    try:
        return float(text)
    except (TypeError, ValueError):
        return None


def _curve(rows, method, noise, split, *, second=None):
    sel = [r for r in rows if r["quantity"] == "displacement" and r["method"] == method and
           float(r["noise_percent"]) == noise and r["split"] == split and
           (second is None or _number(r["param2_value"]) == second)]
    sel.sort(key=lambda r: float(r["param_value"]))
    return [float(r["param_value"]) for r in sel], [float(r["p90"]) for r in sel]


def fig5_sweep(fnumber_folder, scale_folder, out):
    """``docs/fig5_sweep.png``: the p90 of every method against the f-number (top) and the density contrast
    (bottom, f/11 and f/32), at zero noise over all points and at 5 % noise above the threshold."""
    fn, sc = _sweep_rows(fnumber_folder), _sweep_rows(scale_folder)
    methods = [m for m in METHODS if any(r["method"] == m for r in fn)]
    crlb90 = cramer_rao_displacement(5.0) * np.sqrt(-2.0 * np.log(0.1))  # the magnitude's 90 % quantile (Rayleigh)
    with journal_style():
        fig, axes = plt.subplots(2, 2, figsize=(TWO_COLUMNS_IN, 5.4), layout="constrained")
        for c, (noise, split, words) in enumerate(FIG5_PANELS):
            for m in methods:
                style, marker = method_style(m), METHODS[m].marker
                axes[0, c].plot(*_curve(fn, m, noise, split), marker=marker, **style)
                for f_number, ls in ((11.0, "-"), (32.0, "--")):
                    axes[1, c].plot(*_curve(sc, m, noise, split, second=f_number), marker=marker,
                                    color=style["color"], ls=ls)
            for r in range(2):
                ax = axes[r, c]
                ax.set_yscale("linear" if (r, c) == (0, 1) else "log")  # within a factor 2: linear
                ax.grid(True, which="both", alpha=0.3)
                if noise > 0:
                    ax.axhline(crlb90, color="k", ls=":", lw=1.0)
                ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
                ax.yaxis.set_minor_formatter(NullFormatter())
                ax.set_ylabel("p90 error (px)")
            axes[0, c].set_title(words)
            axes[0, c].set_xlabel("f-number (density contrast 1.225 kg/m³)")
            scales = sorted({float(r["param_value"]) for r in sc})
            axes[1, c].set_xscale("log")
            axes[1, c].set_xticks(scales, [f"{v:g}" for v in scales])
            axes[1, c].minorticks_off()
            axes[1, c].set_xlabel("volume density scale (kg/m³)")
        handles = [plt.Line2D([], [], marker=METHODS[m].marker, **method_style(m)) for m in methods]
        handles += [plt.Line2D([], [], color="k", ls="-"), plt.Line2D([], [], color="k", ls="--"),
                    plt.Line2D([], [], color="k", ls=":")]
        labels = [method_style(m)["label"] for m in methods] + ["f/11 (lower row)", "f/32 (lower row)",
                                                                "Cramér-Rao bound, p90 at 5 %"]
        fig.legend(handles, labels, loc="outside lower center", ncol=3, frameon=False)
        fig.suptitle("90th percentile of the displacement error, 256 × 256 px, 500 rays per dot, "
                     "snapshots 0-4 × 2 pairs")
        return figures.save_figure(fig, out, formats=("png",))[0]


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python docs/make_figures.py", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--campaign", default=None, help="quick campaign folder (default: run one into --work)")
    ap.add_argument("--fig5", nargs=4, default=None, metavar=("FNUMBER_SWEEP", "SCALE_SWEEP", "DEFAULT", "NARROW"),
                    help="the sweeps and campaigns of docs/fig5.md")
    ap.add_argument("--work", default=None, help="folder for the quick campaign and the full-size figures "
                                                 "(default: a temporary one)")
    ap.add_argument("--width", type=int, default=1440, help="pixels across of the PNGs written into docs/")
    ap.add_argument("-o", "--out", default=str(DOCS), help="folder to write the figures into")
    args = ap.parse_args(argv)
    docs = Path(args.out)
    docs.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="synthbos-docs-") as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        written, left = [], []
        campaign = Path(args.campaign) if args.campaign else run_quick_campaign(work)
        for stem in QUICK_FIGURES:
            path = campaign_figure(stem, campaign, docs / f"quick_{stem}.png", work=work, width=args.width)
            if path is None:
                left.append((docs / f"quick_{stem}.png", "the campaign's pairs hold no ray covariance"))
            else:
                written.append(path)
        if args.fig5:
            fn, scale, default, narrow = (Path(a) for a in args.fig5)
            written.append(reduced(fig5_sweep(fn, scale, work / "fig5_sweep.png"), docs / "fig5_sweep.png",
                                   width=args.width))
            for name, folder in (("default", default), ("narrow", narrow)):
                written.append(campaign_figure("fig5", folder, docs / f"fig5_{name}.png", work=work, width=args.width))
        else:
            left += [(docs / n, "no --fig5") for n in ("fig5_sweep.png", "fig5_default.png", "fig5_narrow.png")]
    for path in written:
        with Image.open(path) as im:
            size = im.size
        print(f"wrote {path}: {size[0]} x {size[1]} px, {path.stat().st_size / 1e3:.0f} kB")
    for path, why in left:
        print(f"left {path} as it is ({why})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
