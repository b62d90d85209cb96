"""Figures of a campaign: the flows and displacements (fig4) and the error CDFs (fig5), as in
section 4 of Rajendran, Bane & Vlachos (2019); and the experiment-design plots of a sweep."""

from __future__ import annotations

import tomllib
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import LogLocator, MaxNLocator, NullFormatter
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


def _nice_levels(vmax: float, n: int = 12) -> np.ndarray:
    """Contour levels from 0 to at least ``vmax`` at round steps (0.05, 0.1, 0.2, ...)."""
    return MaxNLocator(nbins=n, steps=[1, 2, 2.5, 5, 10]).tick_values(0.0, max(float(vmax), 1e-9))


def figure4(spec, folder, path):
    """For each snapshot: density, density-gradient magnitude, theoretical (Eq. 4) and ray-traced
    displacement magnitude (filled contours), from the first pair of the snapshot.

    Each displacement panel has its own colour scale: the ray-traced displacement is the aperture's
    average of Eq. 4's and several times weaker, so a shared scale would leave it dark.
    """
    folder = Path(folder)
    snaps = list(spec.snapshots)
    fig, axes = plt.subplots(len(snaps), 4, figsize=(14.0, 2.9 * len(snaps) + 0.9), squeeze=False,
                             layout="constrained")
    titles = ("density ρ", "density gradient |∇ρ|", "|ΔX|, theory (Eq. 4)", "|ΔX|, ray-traced")
    for c, title in enumerate(titles):
        axes[0, c].set_title(title, fontsize=11)
    counts = []
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
        fig.colorbar(im, ax=ax[0], label="ρ (kg/m³)", ticks=MaxNLocator(5))
        im = ax[1].imshow(np.hypot(gx, gy), extent=extent, cmap="magma")
        fig.colorbar(im, ax=ax[1], label="|∇ρ| (kg/m⁴)", ticks=MaxNLocator(5))
        ok = pair.valid
        counts.append((int(ok.sum()), pair.n_dots))
        xy = pair.reference_px[ok]
        for k, vals in ((2, np.hypot(*pair.theory_px[ok].T)), (3, np.hypot(*pair.displacement_px[ok].T))):
            levels = _nice_levels(vals.max())
            cs = ax[k].tricontourf(xy[:, 0], xy[:, 1], vals, levels=levels, cmap="cividis")
            ax[k].set_xlim(0, pair.reference.shape[1])
            ax[k].set_ylim(pair.reference.shape[0], 0)
            ax[k].set_aspect("equal")
            fig.colorbar(cs, ax=ax[k], label="|ΔX| (px)", ticks=levels[:: max(1, (len(levels) + 4) // 5)])
            ax[k].set_xlabel("x (px)")
            ax[k].set_ylabel("y (px)")
        for a in ax[:2]:
            a.set_xlabel("x (mm)")
            a.set_ylabel("y (mm)")
        ax[0].set_ylabel(f"snapshot {s}\ny (mm)")
    used = sum(c[0] for c in counts)
    total = sum(c[1] for c in counts)
    fig.suptitle(f"Campaign '{spec.name}', first pair of each snapshot: density at the volume's mid-plane and "
                 f"dot displacement magnitude\n({used:,} of {total:,} dots valid, "
                 f"{pair.attrs.get('rays_per_dot', '?')} rays per dot; each |ΔX| panel on its own scale)",
                 fontsize=10)
    _save(fig, path)


def _threshold_text(thresholds: np.ndarray) -> str:
    t = np.unique(thresholds[np.isfinite(thresholds)])
    if len(t) == 0:
        return "no threshold"
    if np.ptp(t) < 5e-4:
        return f"{t[0]:.3f} px"
    return f"{t.min():.3f} to {t.max():.3f} px"


def _log_limits(arrays, *, low_quantile=0.005, margin=1.25):
    """Log-axis limits that fit the data: from the ``low_quantile`` of the positive values to their maximum."""
    e = np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in arrays] or [np.zeros(0)])
    e = e[np.isfinite(e) & (e > 0)]
    if len(e) == 0:
        return 1e-3, 1.0
    return float(np.quantile(e, low_quantile)) / margin, float(e.max()) * margin


def _log_axis(axis, lo, hi):
    """A log axis with labelled ticks at 1, 2, 5 x 10^k when it spans less than two decades, else decades."""
    axis.axes.set_xscale("log") if axis.axis_name == "x" else axis.axes.set_yscale("log")
    axis.set_major_locator(LogLocator(base=10, subs=(1.0,) if hi / lo >= 100 else (1.0, 2.0, 5.0)))
    axis.set_minor_formatter(NullFormatter())


def figure5(spec, folder, path):
    """Error CDFs on a log error axis: one row per noise level; columns: displacement error below and
    above the threshold, displacement-gradient error below and above; all methods; the Cramér-Rao bound
    of the displacement as a dashed line.

    The threshold (half the standard deviation of Eq. 4's displacement magnitudes, per pair) is stated in
    the title, the number of points of each method in each panel; each panel's error axis spans its data
    (the smallest 0.5 % of the errors sit at its left edge).
    """
    noises = list(spec.noise_percent)
    cols = [("displacement", "below"), ("displacement", "above"), ("gradient", "below"), ("gradient", "above")]
    fig, axes = plt.subplots(len(noises), 4, figsize=(15, 2.7 * len(noises) + 1.0), squeeze=False, sharey=True,
                             layout="constrained")
    thresholds = None
    for r, noise in enumerate(noises):
        curves = {c: [] for c in range(len(cols))}
        for method in spec.methods:
            sc = load_scores(spec, folder, method, noise)
            thresholds = sc["threshold"] if thresholds is None else thresholds
            masks = split_masks(sc)
            for c, (quantity, split) in enumerate(cols):
                e = (sc["error"] if quantity == "displacement" else sc["grad_error"])[masks[split]]
                curves[c].append((method, e))
        for c, (quantity, split) in enumerate(cols):
            ax = axes[r, c]
            lo, hi = _log_limits([e for _, e in curves[c]])
            crb = scoring.cramer_rao_displacement(noise) if quantity == "displacement" and noise > 0 else None
            if crb is not None:
                lo, hi = min(lo, crb / 1.25), max(hi, crb * 1.25)
            counts = []
            for method, e in curves[c]:
                x, y = scoring.empirical_cdf(e)
                if len(x):  # start each curve at zero on the left edge
                    x, y = np.concatenate([[lo], np.maximum(x, lo)]), np.concatenate([[0.0], y])
                ax.step(x, y, where="post", **method_style(method))
                counts.append((method, int(np.isfinite(e).sum())))
            if crb is not None:
                ax.axvline(crb, color="k", ls=":", lw=1.2)
            _log_axis(ax.xaxis, lo, hi)
            ax.set_xlim(lo, hi)
            ax.set_ylim(0, 1.02)
            ax.grid(True, which="major", alpha=0.3)
            for k, (method, n) in enumerate(reversed(counts)):  # listed top to bottom as in the legend
                ax.text(0.97, 0.05 + 0.1 * k, f"n = {n:,}", transform=ax.transAxes, ha="right", va="bottom",
                        fontsize=8, color=method_style(method).get("color", "k"))
            unit = "px" if quantity == "displacement" else "px/px"
            ax.set_xlabel(f"{quantity} error ({unit})")
            if r == 0:
                what = "displacement" if quantity == "displacement" else "displacement gradient"
                ax.set_title(f"{what},\n|ΔX| {'<' if split == 'below' else '≥'} threshold", fontsize=10)
        axes[r, 0].set_ylabel(f"noise {noise:g} %\nCDF")
    handles = [plt.Line2D([], [], **method_style(m)) for m in spec.methods]
    labels = [method_style(m)["label"] for m in spec.methods]
    handles.append(plt.Line2D([], [], color="k", ls=":", lw=1.2))
    labels.append("Cramér-Rao bound (displacement)")
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), frameon=False)
    fig.suptitle(f"Error CDFs, campaign '{spec.name}' ({len(spec.pair_keys())} pairs). Threshold: half the standard "
                 f"deviation of Eq. 4's |ΔX| in each pair, {_threshold_text(thresholds)}; "
                 "n: points scored per method", fontsize=10)
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
