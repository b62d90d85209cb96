"""``synthbos show-density``: figures of density, with axes, units and colour bars.

``synthbos show-density -o FIG.png`` draws the embedded density snapshots (or ``--snapshots FILE.h5``): one
column per snapshot, the normalised density on top (diverging colour map centred on the mean), ``|grad
rho|`` underneath on a logarithmic scale, with each snapshot's time and mixedness in the titles and the
gradient flatness in the lower titles. Lengths are in the snapshots' unit L (the periodic box is 2 pi L).

``synthbos show-density DENSITY.h5 -o FIG.png`` (and ``synthbos show-result DENSITY.h5``) draws a density file
of ``synthbos integrate`` (:func:`plot_density_file`): the reconstructed density in kg/m^3 over the volume's
mid-plane in mm and, when the file holds the truth (integrated against its pair), the cone truth on the
same scale and the difference.

Either figure is one file, in the format of its name's suffix (``.png`` at 300 dpi, ``.pdf``, ``.svg``,
``.jpg``), two journal columns wide (``figures.TWO_COLUMNS_IN``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np

from synthbos import SynthbosError

from .figures import TWO_COLUMNS_IN, figure_format, journal_style, save_figure

__all__ = ["main", "plot_density_file", "plot_snapshots", "read_density_file"]


def plot_snapshots(out, *, snapshots_file=None, progress=False):
    """Draw the density and |grad rho| of every snapshot in one figure and save it as ``out``.

    Parameters
    ----------
    out : str or Path
        Figure to write, in the format of its suffix (.png at 300 dpi, .pdf, .svg, .jpg); only this file.
    snapshots_file : str or Path, optional
        A snapshot file (``raytrace.loaders.write_snapshots`` schema); the embedded one by default.
    progress : bool
        Show a progress bar (a snapshot a step, then the file).

    Returns
    -------
    list of dict
        Per snapshot: ``time``, ``min``, ``max``, ``grad_flatness`` (flatness of |grad rho|).
    """
    from synthbos.raytrace.loaders import read_snapshots
    from tqdm import tqdm

    fmt = figure_format(out)
    dens, times, attrs = read_snapshots(snapshots_file)
    with tqdm(total=len(dens) + 1, desc="show-density", unit="step", disable=not progress) as bar, journal_style():
        fig, stats = _snapshot_figure(dens, times, attrs, bar)
        save_figure(fig, Path(out).with_suffix(""), formats=(fmt,))
        bar.update()
    return stats


def _snapshot_figure(dens, times, attrs, bar):
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    from synthbos.raytrace.buoyancy import flatness, gradient_magnitude

    m, ny, nx = dens.shape
    box = float(attrs.get("box", 2.0 * np.pi))
    atwood = float(attrs.get("atwood", np.max(np.abs(dens - 1.0))))
    grads = [gradient_magnitude(d, spacing=box / nx) for d in dens]
    positive = np.concatenate([g[g > 0].ravel() for g in grads])
    gmax = float(positive.max())
    gmin = max(float(np.percentile(positive, 1.0)), gmax * 1e-4)
    mixedness = 1.0 - ((dens - 1.0) ** 2).mean(axis=(1, 2)) / atwood**2 if atwood > 0 else None
    panel = (TWO_COLUMNS_IN - 0.9) / m
    fig, axes = plt.subplots(2, m, figsize=(TWO_COLUMNS_IN, 2 * panel * ny / nx + 1.1), squeeze=False,
                             layout="constrained")
    extent = (0.0, box, 0.0, box * ny / nx)
    ticks = np.linspace(0.0, box, 3)
    labels = ["0", "π", "2π"] if np.isclose(box, 2 * np.pi) else [f"{t:.3g}" for t in ticks]
    stats = []
    for i in range(m):
        top, bot = axes[0, i], axes[1, i]
        im0 = top.imshow(dens[i], origin="lower", cmap="RdBu_r", vmin=1.0 - atwood, vmax=1.0 + atwood, extent=extent,
                         interpolation="nearest")
        words = f"t = {times[i]:.3g}" + (f"\nmixed {mixedness[i]:.2f}" if mixedness is not None else "")
        top.set_title(f"snapshot {i}: {words}")
        im1 = bot.imshow(np.maximum(grads[i], gmin), origin="lower", cmap="magma", norm=LogNorm(gmin, gmax),
                         extent=extent, interpolation="nearest")
        F = flatness(grads[i])
        bot.set_title(f"flatness {F:.1f}")
        for r, ax in enumerate((top, bot)):
            ax.set_xticks(ticks, labels)
            ax.set_yticks(ticks[ticks <= extent[3] + 1e-9], labels[: int((ticks <= extent[3] + 1e-9).sum())])
            ax.tick_params(labelleft=i == 0, labelbottom=r == 1)
        stats.append({"time": float(times[i]), "min": float(dens[i].min()), "max": float(dens[i].max()),
                      "grad_flatness": F})
        bar.update()
    for ax in axes[1]:
        ax.set_xlabel("x / L")
    axes[0, 0].set_ylabel("ρ / ⟨ρ⟩\ny / L")
    axes[1, 0].set_ylabel("|∇ρ|\ny / L")
    fig.colorbar(im0, ax=axes[0, :].tolist(), shrink=0.9, label="ρ / ⟨ρ⟩")
    fig.colorbar(im1, ax=axes[1, :].tolist(), shrink=0.9, label="|∇ρ| (⟨ρ⟩ / L)")
    fig.suptitle(f"Buoyancy-driven variable-density mixing (2-D Boussinesq, A = {atwood:.3g}, gravity along −y; "
                 "box 2π L, periodic)")
    return fig, stats


def read_density_file(path) -> dict:
    """The datasets of a density file of ``synthbos integrate`` (``integrate.write_density``'s layout).

    Returns
    -------
    dict
        ``density`` (kg/m^3, NaN where not reconstructed), ``x_mm``, ``y_mm`` (the nodes), ``measured``,
        ``truth`` (the cone truth, kg/m^3, or None), ``attrs`` (the root attributes).
    """
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"density file {path} does not exist")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise SynthbosError(f"cannot read density file {path}: {err}") from None
    with f:
        missing = [f"/{n}" for n in ("density_kg_m3", "x_mm", "y_mm") if not isinstance(f.get(n), h5py.Dataset)]
        if missing:
            raise SynthbosError(f"{path} is not a density file of 'synthbos integrate': missing {', '.join(missing)}")
        out = {"density": np.asarray(f["density_kg_m3"][()], dtype=np.float64),
               "x_mm": np.asarray(f["x_mm"][()], dtype=np.float64).ravel(),
               "y_mm": np.asarray(f["y_mm"][()], dtype=np.float64).ravel(),
               "measured": f["measured"][()].astype(bool) if "measured" in f else None,
               "truth": np.asarray(f["truth_cone_kg_m3"][()], dtype=np.float64) if "truth_cone_kg_m3" in f else None,
               "attrs": {k: (v.decode("utf-8", "replace") if isinstance(v, bytes) else v) for k, v in f.attrs.items()}}
    if out["density"].shape != (len(out["y_mm"]), len(out["x_mm"])):
        raise SynthbosError(f"{path}: /density_kg_m3 has shape {out['density'].shape}, the nodes "
                            f"{len(out['y_mm'])} x {len(out['x_mm'])}")
    if out["truth"] is not None and out["truth"].shape != out["density"].shape:
        raise SynthbosError(f"{path}: /truth_cone_kg_m3 has shape {out['truth'].shape}, the density "
                            f"{out['density'].shape}")
    return out


def density_summary_line(d) -> str:
    """The reconstructed range (and the error against the truth, when there is one) of a density file, on one line."""
    rho = d["density"]
    ok = np.isfinite(rho)
    if not ok.any():
        return "density: no node reconstructed"
    text = (f"density ({d['attrs'].get('method', '?')}, solver {d['attrs'].get('solver', '?')}): {int(ok.sum())} of "
            f"{rho.size} nodes, {np.nanmin(rho):.6g} to {np.nanmax(rho):.6g} kg/m^3")
    if d["truth"] is not None:
        from .scoring import density_errors

        e = density_errors(rho, d["truth"])
        if e["n"]:
            text += (f"; error against the cone truth: RMS {e['rms_kg_m3']:.3g} kg/m^3 ({100 * e['rms_rel']:.3g} % "
                     f"of its range), p90 {e['p90_kg_m3']:.3g} kg/m^3")
    return text


def plot_density_file(path, out) -> str:
    """Draw a density file of ``synthbos integrate`` as ``out`` (format of its suffix) and return its summary.

    One panel (the reconstructed density, kg/m^3, over x and y in mm) without a truth; with the file's cone
    truth, three: reconstructed and true density on one scale, and their difference (diverging, centred on 0).
    Nodes that were not reconstructed are blank.
    """
    fmt = figure_format(out)
    d = read_density_file(path)
    summary = density_summary_line(d)
    with journal_style():
        fig = _density_figure(d, Path(path).name)
        save_figure(fig, Path(out).with_suffix(""), formats=(fmt,))
    return summary


def _density_figure(d, name):
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    from .figures import ONE_COLUMN_IN, _colorbar, _fitted

    x, y, rho, truth = d["x_mm"], d["y_mm"], d["density"], d["truth"]
    fields = [(rho, "reconstructed density")] + ([(truth, "true (cone) density")] if truth is not None else [])
    n = len(fields) + (truth is not None)
    width = ONE_COLUMN_IN if n == 1 else TWO_COLUMNS_IN
    aspect = (abs(y[-1] - y[0]) or 1.0) / (abs(x[-1] - x[0]) or 1.0)
    fig, axes = plt.subplots(1, n, figsize=(width, (width - 0.6) / n * aspect + 1.3), squeeze=False,
                             layout="constrained")
    axes = axes[0]
    half = 0.5 * ((x[1] - x[0]) if len(x) > 1 else 1.0), 0.5 * ((y[1] - y[0]) if len(y) > 1 else 1.0)
    ext = (x[0] - half[0], x[-1] + half[0], y[-1] + half[1], y[0] - half[1])  # row 0 at the top, as the image
    values = np.concatenate([f[np.isfinite(f)] for f, _ in fields] or [np.zeros(1)])
    lo, hi = (float(values.min()), float(values.max())) if len(values) else (0.0, 1.0)
    for ax, (field, title) in zip(axes, fields, strict=False):
        im = ax.imshow(field, extent=ext, vmin=lo, vmax=hi if hi > lo else lo + 1e-9, cmap="viridis",
                       interpolation="nearest")
        ax.set_title(title)
    _colorbar(fig, im, list(axes[: len(fields)]), location="bottom", shrink=0.8, label="ρ (kg/m³)",
              ticks=MaxNLocator(4))
    if truth is not None:
        diff = rho - truth
        lim = float(np.nanmax(np.abs(diff))) if np.isfinite(diff).any() else 1.0
        im = axes[-1].imshow(diff, extent=ext, vmin=-lim, vmax=lim, cmap="RdBu_r", interpolation="nearest")
        axes[-1].set_title("reconstructed − true")
        _colorbar(fig, im, axes[-1], location="bottom", shrink=0.9, label="Δρ (kg/m³)", ticks=MaxNLocator(3))
    for k, ax in enumerate(axes):
        ax.set_xlabel("x (mm)")
        ax.tick_params(labelleft=k == 0)
        ax.xaxis.set_major_locator(MaxNLocator(4))
    axes[0].set_ylabel("y (mm)")
    a = d["attrs"]
    fig.suptitle(_fitted(f"{name}: depth-averaged density at the volume's mid-plane, from {a.get('method', '?')} "
                         f"(solver {a.get('solver', '?')}, {a.get('reference', 'reference ?')})", width - 0.1))
    return fig


def main(argv=None):
    """Draw the density snapshots: ``python3 -m synthbos.benchmarks.show_density -o FIG.png``."""
    ap = argparse.ArgumentParser(prog="synthbos show-density", description=main.__doc__)
    ap.add_argument("-o", "--output", default="density_snapshots.png", help="figure to write (.png, .pdf, .svg, .jpg)")
    ap.add_argument("--snapshots", default=None, help="snapshot file (default: the embedded one)")
    args = ap.parse_args(argv)
    stats = plot_snapshots(args.output, snapshots_file=args.snapshots)
    print(snapshot_table(stats))
    print(f"wrote {args.output}")
    return 0


def snapshot_table(stats) -> str:
    """The per-snapshot summary of :func:`plot_snapshots` as a small table."""
    lines = [f"{'snapshot':>8} {'time':>8} {'rho min':>9} {'rho max':>9} {'|grad| flatness':>16}"]
    lines += [f"{i:>8d} {s['time']:>8.3g} {s['min']:>9.4f} {s['max']:>9.4f} {s['grad_flatness']:>16.2f}"
              for i, s in enumerate(stats)]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
