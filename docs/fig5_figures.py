"""Draw the figures of ``docs/fig5.md`` from the sweeps and campaigns that page lists (their folders as arguments).

    python docs/fig5_figures.py FNUMBER_SWEEP SCALE_SWEEP DEFAULT_CAMPAIGN NARROW_CAMPAIGN

writes ``docs/fig5_sweep.png`` (p90 of every method against the f-number and the density contrast, at zero
noise and at 5 % above the threshold, with the Cramér-Rao bound) and ``docs/fig5_default.png`` /
``docs/fig5_narrow.png`` (each campaign's ``fig5.png``, reduced to a page's width).
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from PIL import Image
from synthbos.benchmarks.figures import METHODS, method_style
from synthbos.benchmarks.scoring import cramer_rao_displacement

DOCS = Path(__file__).resolve().parent
PANELS = ((0.0, "all", "zero noise, all points"), (5.0, "above", "5 % noise, |ΔX| ≥ threshold"))


def _rows(folder):
    with open(Path(folder) / "sweep.csv", newline="") as f:
        return [r for r in csv.DictReader(f) if r["quantity"] == "displacement"]


def _curve(rows, method, noise, split, *, second=None):
    sel = [r for r in rows if r["method"] == method and float(r["noise_percent"]) == noise and r["split"] == split
           and (second is None or float(r["param2_value"]) == second)]
    sel.sort(key=lambda r: float(r["param_value"]))
    return [float(r["param_value"]) for r in sel], [float(r["p90"]) for r in sel]


def sweep_figure(fnumber_folder, scale_folder, out):
    fn, sc = _rows(fnumber_folder), _rows(scale_folder)
    methods = [m for m in METHODS if any(r["method"] == m for r in fn)]
    fig, axes = plt.subplots(2, 2, figsize=(7.2, 5.4), layout="constrained")
    crlb90 = cramer_rao_displacement(5.0) * np.sqrt(-2.0 * np.log(0.1))  # the magnitude's 90 % quantile (Rayleigh)
    for c, (noise, split, words) in enumerate(PANELS):
        for m in methods:
            style = method_style(m)
            marker = METHODS[m].marker
            axes[0, c].plot(*_curve(fn, m, noise, split), marker=marker, ms=4, **style)
            for f_number, ls in ((11.0, "-"), (32.0, "--")):
                axes[1, c].plot(*_curve(sc, m, noise, split, second=f_number), marker=marker, ms=4,
                                color=style["color"], ls=ls)
        for r in range(2):
            ax = axes[r, c]
            ax.set_yscale("linear" if (r, c) == (0, 1) else "log")  # within a factor 2: linear
            ax.grid(True, which="both", alpha=0.3)
            if noise > 0:
                ax.axhline(crlb90, color="k", ls=":", lw=1.0)
            ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.set_ylabel("p90 error (px)", fontsize=8)
        axes[0, c].set_title(words, fontsize=8)
        axes[0, c].set_xlabel("f-number (density contrast 1.225 kg/m³)", fontsize=8)
        scales = sorted({float(r["param_value"]) for r in sc})
        axes[1, c].set_xscale("log")
        axes[1, c].set_xticks(scales, [f"{v:g}" for v in scales])
        axes[1, c].minorticks_off()
        axes[1, c].set_xlabel("volume.density_scale_kg_m3 (kg/m³)", fontsize=8)
    handles = [plt.Line2D([], [], marker=METHODS[m].marker, ms=4, **method_style(m)) for m in methods]
    handles += [plt.Line2D([], [], color="k", ls="-"), plt.Line2D([], [], color="k", ls="--"),
                plt.Line2D([], [], color="k", ls=":")]
    labels = [method_style(m)["label"] for m in methods] + ["f/11 (lower row)", "f/32 (lower row)",
                                                            "Cramér-Rao bound, p90 at 5 %"]
    fig.legend(handles, labels, loc="outside lower center", ncol=3, frameon=False, fontsize=7)
    fig.suptitle("90th percentile of the displacement error, 256 × 256 px, 500 rays per dot, snapshots 0-4 × 2 pairs",
                 fontsize=8)
    fig.savefig(out, dpi=150)
    plt.close(fig)


def reduced(src, out, *, width=1400):
    im = Image.open(src).convert("RGB")
    im.thumbnail((width, width * 4))
    im.quantize(colors=64, dither=Image.Dither.NONE).save(out, optimize=True)


def main(argv=None):
    fnumber, scale, default, narrow = (Path(a) for a in (argv if argv is not None else sys.argv[1:]))
    sweep_figure(fnumber, scale, DOCS / "fig5_sweep.png")
    reduced(default / "fig5.png", DOCS / "fig5_default.png")
    reduced(narrow / "fig5.png", DOCS / "fig5_narrow.png")
    for name in ("fig5_sweep.png", "fig5_default.png", "fig5_narrow.png"):
        print(f"wrote {DOCS / name}: {(DOCS / name).stat().st_size / 1e3:.0f} kB")


if __name__ == "__main__":
    main()
