"""Figures of a campaign: the flows and displacements (fig4) and the error CDFs (fig5), as in
section 4 of Rajendran, Bane & Vlachos (2019); and the experiment-design plots of a sweep."""

from __future__ import annotations

import tomllib
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from synthbos.raytrace import load_config, read_pair
from synthbos.raytrace.sources import density_from_config

from synthbos import atomic_output

from . import scoring
from .registry import METHODS
from .storage import load_scores, pair_path
from .tables import split_masks

__all__ = ["FORMATS", "figure4", "figure5", "method_style", "save_figure", "sweep_figure"]

FORMATS = ("png", "pdf")  # a 300 dpi PNG to look at, a vector PDF to print


def method_style(name: str) -> dict:
    """Matplotlib keywords (colour, line style, marker, label) of a method, from the registry."""
    m = METHODS.get(name)
    if m is None:
        return {"label": name}
    return {"color": m.color, "ls": m.linestyle, "label": m.label}


def save_figure(fig, path) -> list[Path]:
    """Save ``fig`` as ``path`` with each suffix of ``FORMATS`` (atomically); return the paths written.

    ``path`` may carry a suffix (``fig4.png``) or not (``fig4``); either way every format is written.
    """
    path = Path(path)
    stem = path.with_suffix("") if path.suffix.lower() in {f".{f}" for f in FORMATS} else path
    written = []
    for fmt in FORMATS:
        out = stem.with_name(f"{stem.name}.{fmt}")
        with atomic_output(out) as tmp:
            fig.savefig(tmp, dpi=300, bbox_inches="tight", format=fmt)
        written.append(out)
    plt.close(fig)
    return written


_save = save_figure


def figure4(spec, folder, path):
    """For each snapshot: density, density-gradient magnitude, theoretical (Eq. 4) and ray-traced
    displacement magnitude (contours), from the first pair of the snapshot."""
    folder = Path(folder)
    snaps = list(spec.snapshots)
    fig, axes = plt.subplots(len(snaps), 4, figsize=(13, 3.0 * len(snaps)), squeeze=False)
    for row, s in enumerate(snaps):
        pair = read_pair(pair_path(folder, s, 0))
        cfg = load_config(tomllib.loads(pair.attrs["config"]))
        vol = {k: v for k, v in cfg["volume"].items() if k != "offset_mm"}
        dens = density_from_config(vol)
        rho = dens.rho[dens.rho.shape[0] // 2]
        lx, ly = dens.size_m[0] * 1e3, dens.size_m[1] * 1e3
        extent = (-lx / 2, lx / 2, ly / 2, -ly / 2)
        gy, gx = np.gradient(rho, ly * 1e-3 / (rho.shape[0] - 1), lx * 1e-3 / (rho.shape[1] - 1))
        ax = axes[row]
        im = ax[0].imshow(rho, extent=extent, cmap="viridis")
        fig.colorbar(im, ax=ax[0], label="ρ (kg/m³)")
        im = ax[1].imshow(np.hypot(gx, gy), extent=extent, cmap="magma")
        fig.colorbar(im, ax=ax[1], label="|∇ρ| (kg/m⁴)")
        ok = pair.valid
        xy = pair.reference_px[ok]
        th = np.hypot(*pair.theory_px[ok].T)
        rt = np.hypot(*pair.displacement_px[ok].T)
        levels = np.linspace(0, max(th.max(), rt.max(), 1e-9), 12)
        for k, (vals, title) in enumerate(((th, "theory, Eq. 4"), (rt, "ray-traced")), start=2):
            cs = ax[k].tricontourf(xy[:, 0], xy[:, 1], vals, levels=levels, cmap="cividis")
            ax[k].set_xlim(0, pair.reference.shape[1])
            ax[k].set_ylim(pair.reference.shape[0], 0)
            ax[k].set_aspect("equal")
            fig.colorbar(cs, ax=ax[k], label="|ΔX| (px)")
            ax[k].set_title(f"snapshot {s}: {title}", fontsize=9)
        ax[0].set_title(f"snapshot {s}: density", fontsize=9)
        ax[1].set_title(f"snapshot {s}: density gradient", fontsize=9)
        for a in ax[:2]:
            a.set_xlabel("x (mm)")
            a.set_ylabel("y (mm)")
        for a in ax[2:]:
            a.set_xlabel("x (px)")
            a.set_ylabel("y (px)")
    fig.suptitle(f"Campaign '{spec.name}': density fields and dot displacements", y=1.0)
    fig.tight_layout()
    _save(fig, path)


def figure5(spec, folder, path):
    """Error CDFs on a log error axis: one row per noise level; columns: displacement below and above
    the threshold, displacement gradient below and above; all methods; the Cramér-Rao bound of the
    displacement as a dashed line."""
    noises = list(spec.noise_percent)
    cols = [("displacement", "below"), ("displacement", "above"), ("gradient", "below"), ("gradient", "above")]
    fig, axes = plt.subplots(len(noises), 4, figsize=(15, 2.9 * len(noises)), squeeze=False, sharey=True)
    for r, noise in enumerate(noises):
        for method in spec.methods:
            sc = load_scores(spec, folder, method, noise)
            masks = split_masks(sc)
            for c, (quantity, split) in enumerate(cols):
                e = (sc["error"] if quantity == "displacement" else sc["grad_error"])[masks[split]]
                x, y = scoring.empirical_cdf(e)
                x = np.maximum(x, 1e-6)
                style = method_style(method)
                axes[r, c].step(x, y, where="post", **style)
        for c, (quantity, split) in enumerate(cols):
            ax = axes[r, c]
            ax.set_xscale("log")
            ax.set_xlim(1e-5 if quantity == "displacement" else 1e-6, 10 if quantity == "displacement" else 1)
            ax.grid(True, which="both", alpha=0.3)
            unit = "px" if quantity == "displacement" else "px/px"
            ax.set_title(f"noise {noise:g}%: {quantity} error, {split} threshold", fontsize=9)
            ax.set_xlabel(f"error ({unit})")
            if quantity == "displacement" and noise > 0:
                crb = scoring.cramer_rao_displacement(noise)
                ax.axvline(crb, color="k", ls="--", lw=1, label=f"Cramér-Rao bound {crb:.3g} px")
        axes[r, 0].set_ylabel("CDF")
    handles, labels = [], []
    for ax in axes.ravel():
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in labels and not lab.startswith("Cramér"):
                handles.append(h)
                labels.append(lab)
    handles.append(plt.Line2D([], [], color="k", ls="--", lw=1))
    labels.append("Cramér-Rao bound (displacement)")
    fig.legend(handles, labels, loc="upper center", ncol=len(labels), bbox_to_anchor=(0.5, 1.02))
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    _save(fig, path)


def sweep_figure(rows, path, *, param, param2=None, percentiles=(50, 90)):
    """Error percentiles (displacement, all points) and yield against the swept parameter."""
    order = list(METHODS)
    methods = sorted({r["method"] for r in rows},
                     key=lambda m: (m not in order, order.index(m) if m in order else 0, m))
    noises = sorted({r["noise_percent"] for r in rows})
    second = sorted({r.get("param2_value") for r in rows}, key=lambda v: (v is None, v))
    fig, axes = plt.subplots(len(noises), len(percentiles) + 1, figsize=(4.3 * (len(percentiles) + 1),
                             3.0 * len(noises)), squeeze=False)
    linestyles = ["-", "--", ":", "-."]
    for r, noise in enumerate(noises):
        for method in methods:
            style = method_style(method)
            for k, val2 in enumerate(second):
                sel = [x for x in rows if x["method"] == method and x["noise_percent"] == noise
                       and x.get("param2_value") == val2 and x["split"] == "all" and x["quantity"] == "displacement"]
                sel.sort(key=lambda x: x["param_value"])
                xs = [x["param_value"] for x in sel]
                lab = style["label"] + (f", {param2} = {val2:g}" if val2 is not None else "")
                ls = linestyles[k % 4] if val2 is not None else style.get("ls", "-")
                kw = {"color": style.get("color"), "ls": ls,
                      "marker": METHODS[method].marker if method in METHODS else "o", "label": lab}
                for c, p in enumerate(percentiles):
                    axes[r, c].plot(xs, [x[f"p{p}"] for x in sel], **kw)
                axes[r, -1].plot(xs, [x["yield"] for x in sel], **kw)
        for c, p in enumerate(percentiles):
            axes[r, c].set_yscale("log")
            axes[r, c].set_ylabel(f"{p}th percentile error (px)")
            axes[r, c].set_title(f"noise {noise:g}%", fontsize=9)
        axes[r, -1].set_ylabel("yield")
        axes[r, -1].set_title(f"noise {noise:g}%", fontsize=9)
        for ax in axes[r]:
            ax.set_xlabel(param)
            ax.grid(True, alpha=0.3)
    h, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, lab, loc="upper center", ncol=min(len(lab), 3), bbox_to_anchor=(0.5, 1.04))
    fig.tight_layout()
    _save(fig, path)
