"""Figure of the embedded density snapshots: density and density-gradient magnitude.

``python3 -m synthbos.benchmarks.show_density -o density.png [--snapshots FILE.h5]`` (to be wired as
``synthbos show-density``) draws one column per snapshot: the normalised density on top (diverging
colour map centred on the mean), ``|grad rho|`` underneath on a logarithmic scale, with each
snapshot's time and mixedness in the titles and the gradient flatness in the lower titles.
"""

from __future__ import annotations

import argparse

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LogNorm
from synthbos.raytrace.buoyancy import flatness, gradient_magnitude
from synthbos.raytrace.loaders import read_snapshots

from .figures import save_figure

__all__ = ["main", "plot_snapshots"]


def plot_snapshots(path_png, *, snapshots_file=None):
    """Draw the density and |grad rho| of every snapshot in one figure and save it.

    Parameters
    ----------
    path_png : str or Path
        Output image: a 300 dpi PNG, with a PDF of the same name beside it (``figures.save_figure``).
    snapshots_file : str or Path, optional
        A snapshot file (``raytrace.loaders.write_snapshots`` schema); the embedded one by default.

    Returns
    -------
    list of dict
        Per snapshot: ``time``, ``min``, ``max``, ``grad_flatness`` (flatness of |grad rho|).
    """
    dens, times, attrs = read_snapshots(snapshots_file)
    m, ny, nx = dens.shape
    box = float(attrs.get("box", 2.0 * np.pi))
    spacing = box / nx
    atwood = float(attrs.get("atwood", np.max(np.abs(dens - 1.0))))
    grads = [gradient_magnitude(d, spacing=spacing) for d in dens]
    positive = np.concatenate([g[g > 0].ravel() for g in grads])
    gmax = float(positive.max())
    gmin = max(float(np.percentile(positive, 1.0)), gmax * 1e-4)
    mixedness = 1.0 - ((dens - 1.0) ** 2).mean(axis=(1, 2)) / atwood**2 if atwood > 0 else None

    fig, axes = plt.subplots(2, m, figsize=(3.0 * m + 1.2, 6.4), squeeze=False, constrained_layout=True)
    extent = (0.0, box, 0.0, box * ny / nx)
    stats = []
    for i in range(m):
        top, bot = axes[0, i], axes[1, i]
        im0 = top.imshow(
            dens[i],
            origin="lower",
            cmap="RdBu_r",
            vmin=1.0 - atwood,
            vmax=1.0 + atwood,
            extent=extent,
            interpolation="nearest",
        )
        label = f"t = {times[i]:.3g}"
        if mixedness is not None:
            label += f"  (mixed {mixedness[i]:.2f})"
        top.set_title(f"snapshot {i}: {label}", fontsize=9)
        im1 = bot.imshow(
            np.maximum(grads[i], gmin),
            origin="lower",
            cmap="magma",
            norm=LogNorm(gmin, gmax),
            extent=extent,
            interpolation="nearest",
        )
        F = flatness(grads[i])
        bot.set_title(f"|grad rho|, flatness {F:.1f}", fontsize=9)
        for ax in (top, bot):
            ax.set_xticks([])
            ax.set_yticks([])
        stats.append(
            {
                "time": float(times[i]),
                "min": float(dens[i].min()),
                "max": float(dens[i].max()),
                "grad_flatness": F,
            }
        )
    fig.colorbar(im0, ax=axes[0, :].tolist(), shrink=0.9, label="rho / <rho>")
    fig.colorbar(im1, ax=axes[1, :].tolist(), shrink=0.9, label="|grad rho| (per unit length, box 2 pi)")
    fig.suptitle(
        f"Buoyancy-driven variable-density mixing (2-D Boussinesq, A = {atwood:.3g}, gravity down)",
        fontsize=11,
    )
    save_figure(fig, path_png)
    return stats


def main(argv=None):
    """Draw the density snapshots: ``python3 -m synthbos.benchmarks.show_density -o FIG.png``."""
    ap = argparse.ArgumentParser(prog="synthbos show-density", description=main.__doc__)
    ap.add_argument("-o", "--output", default="density_snapshots.png", help="image to write (PNG)")
    ap.add_argument("--snapshots", default=None, help="snapshot file (default: the embedded one)")
    args = ap.parse_args(argv)
    stats = plot_snapshots(args.output, snapshots_file=args.snapshots)
    print(f"{'snapshot':>8} {'time':>8} {'rho min':>9} {'rho max':>9} {'|grad| flatness':>16}")
    for i, s in enumerate(stats):
        print(f"{i:>8d} {s['time']:>8.3g} {s['min']:>9.4f} {s['max']:>9.4f} {s['grad_flatness']:>16.2f}")
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
