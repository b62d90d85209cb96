"""``synthbos show-result RESULT.h5 -o FIG.png``: a figure and a short summary of one result file.

The figure (one file, in the format of its name's suffix: a 300 dpi PNG, a PDF, an SVG) shows the
displacement magnitude (a colour map of the vector grid, or coloured dots), the vectors as arrows,
and marks the points that were replaced (orange circles), failed (vermillion crosses) or masked
(grey); the title states the counts. The summary (returned and printed) gives the counts and the
median and largest displacement of the measured points.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from synthbos import SynthbosError
from synthbos.values import shorten

from .figures import save_figure
from .process import check_result_file
from .registry import DENSE, GRID

__all__ = ["plot_result", "read_result"]

REPLACED_COLOR = "#E69F00"  # Okabe-Ito orange
FAILED_COLOR = "#D55E00"  # Okabe-Ito vermillion
MASKED_COLOR = "0.6"


def read_result(path) -> dict:
    """The points of a result file of ``synthbos process`` and what became of each.

    Returns
    -------
    dict
        ``method``, ``kind``, ``x``, ``y``, ``u``, ``v`` (1-D, px), ``grid_shape`` (or None),
        boolean ``measured``, ``replaced``, ``failed``, ``masked`` (one of them true per point), and
        ``settings`` (dict).
    """
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"result file {path} does not exist")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise SynthbosError(f"cannot read result file {path}: {err}") from None
    with f:
        method, kind = check_result_file(f, path)
        method = method.name
        try:
            settings = json.loads(f.attrs.get("settings", "{}"))
        except (json.JSONDecodeError, TypeError, UnicodeDecodeError):
            raise SynthbosError(f"{path}: its settings attribute is not JSON text") from None
        if kind in (GRID, DENSE) and method != "correlation":  # another method's own valid vectors
            x, y, u, v = (f[k][()] for k in ("x", "y", "u", "v"))
            grid_shape = u.shape
            ok = f["valid"][()].astype(bool) if "valid" in f else np.isfinite(u) & np.isfinite(v)
            replaced = ~ok & (f["replaced"][()].astype(bool) if "replaced" in f else False)
            failed, masked = ~ok & ~replaced, np.zeros(u.shape, bool)
        elif kind == GRID:
            if "flags" not in f:
                raise SynthbosError(f"{path} is not a correlation result file: missing /flags")
            x, y, u, v = (f[k][()] for k in ("x", "y", "u", "v"))
            flags = f["flags"][()].astype(np.int64)
            if flags.shape != u.shape:
                raise SynthbosError(f"{path}: /flags has shape {flags.shape}, /u {u.shape}")
            grid_shape = u.shape
            from synthbos.correlation.multigrid import FAILED_BITS, FLAG_MASKED

            masked = (flags & FLAG_MASKED) != 0
            failed = ~masked & ((flags & int(FAILED_BITS)) != 0)
            replaced = ~masked & ~failed & (flags != 0)
        else:
            g = f["dots"]
            x, y, u, v = (g[k][()] for k in ("x", "y", "u", "v"))
            from synthbos.tracking import is_valid

            masked = g["masked"][()].astype(bool).ravel() if "masked" in g else np.zeros(len(x), bool)
            if "status" in g:
                ok = is_valid(g["status"][()]).ravel() & np.isfinite(u) & np.isfinite(v)
            else:  # an older or foreign table: valid where the file says so, else where finite
                ok = (g["valid"][()].astype(bool).ravel() if "valid" in g else True) & np.isfinite(u) & np.isfinite(v)
            if ok.shape != x.shape or masked.shape != x.shape:
                raise SynthbosError(f"{path}: the columns under /dots differ in length")
            failed = ~ok & ~masked
            replaced = np.zeros(len(x), bool)
            grid_shape = None
    measured = ~(masked | failed | replaced)
    return {"method": method, "kind": kind, "settings": settings, "grid_shape": grid_shape,
            **{k: np.ravel(a) for k, a in (("x", x), ("y", y), ("u", u), ("v", v), ("measured", measured),
                                           ("replaced", replaced), ("failed", failed), ("masked", masked))}}


def summary_line(res) -> str:
    """Counts and the measured displacement of a :func:`read_result` dict, on one line."""
    n = {k: int(res[k].sum()) for k in ("measured", "replaced", "failed", "masked")}
    mag = np.hypot(res["u"], res["v"])[res["measured"]]
    noun = {GRID: "vectors", DENSE: "pixels"}.get(res["kind"], "dots")
    text = (f"{res['method']}: {len(res['x'])} {noun}: {n['measured']} measured, {n['replaced']} replaced, "
            f"{n['failed']} failed, {n['masked']} masked")
    if len(mag):
        text += f"; |displacement| of the measured: median {np.median(mag):.3f} px, max {mag.max():.3f} px"
    return text


def plot_result(path, out, *, max_arrows=40) -> str:
    """Draw a result file (module docstring) and return the summary.

    Parameters
    ----------
    path : str or Path
        Result file of ``synthbos process``.
    out : str or Path
        Figure to write, atomically, in the format of its suffix (.png at 300 dpi, .pdf, .svg, ...
        whatever matplotlib writes); only this file is written.
    max_arrows : int
        At most this many arrows along each axis (a regular subset of the points).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fmt = figure_format(out)
    res = read_result(path)
    summary = summary_line(res)
    x, y, u, v = res["x"], res["y"], res["u"], res["v"]
    mag = np.hypot(u, v)
    shown = res["measured"] | res["replaced"] | res["failed"]
    vmax = float(np.nanmax(mag[res["measured"]])) if res["measured"].any() else 1.0
    fig, ax = plt.subplots(figsize=(7.0, 6.0), layout="constrained")
    if res["kind"] in (GRID, DENSE):
        ny, nx = res["grid_shape"]
        gx, gy = x.reshape(ny, nx), y.reshape(ny, nx)
        m = np.where(res["masked"], np.nan, mag).reshape(ny, nx)
        im = ax.pcolormesh(gx, gy, m, shading="nearest", cmap="viridis", vmin=0.0, vmax=vmax)
        step = max(1, int(np.ceil(max(ny, nx) / max_arrows)))
        sub = np.zeros((ny, nx), bool)
        sub[::step, ::step] = True
        sub = sub.ravel() & shown
        if res["masked"].any():
            ax.scatter(x[res["masked"]], y[res["masked"]], s=6, marker="s", color=MASKED_COLOR,
                       label=f"masked ({int(res['masked'].sum())})")
    else:
        im = ax.scatter(x[shown], y[shown], c=np.where(res["failed"][shown], np.nan, mag[shown]), s=8,
                        cmap="viridis", vmin=0.0, vmax=vmax)
        span = max(np.ptp(x), np.ptp(y), 1.0)
        keep = np.zeros(len(x), bool)
        cell = span / max_arrows
        _, first = np.unique(np.stack([np.floor(x / cell), np.floor(y / cell)], 1), axis=0, return_index=True)
        keep[first] = True
        sub = keep & res["measured"]
        if res["masked"].any():
            ax.scatter(x[res["masked"]], y[res["masked"]], s=6, color=MASKED_COLOR,
                       label=f"masked ({int(res['masked'].sum())})")
    arrows = sub & np.isfinite(u) & np.isfinite(v)
    still = not np.any(mag[arrows] > 0)  # nothing moved: matplotlib cannot scale zero-length arrows
    ax.quiver(x[arrows], y[arrows], u[arrows], v[arrows], angles="xy", color="white", edgecolor="black",
              linewidth=0.3, width=0.003, scale=1.0 if still else None)
    if res["replaced"].any():
        ax.scatter(x[res["replaced"]], y[res["replaced"]], s=30, facecolors="none", edgecolors=REPLACED_COLOR,
                   linewidths=1.2, label=f"replaced ({int(res['replaced'].sum())})")
    if res["failed"].any():
        ax.scatter(x[res["failed"]], y[res["failed"]], s=24, marker="x", color=FAILED_COLOR, linewidths=1.2,
                   label=f"failed ({int(res['failed'].sum())})")
    ax.set_aspect("equal")
    ax.invert_yaxis()  # image coordinates: row 0 at the top
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px]")
    n = {k: int(res[k].sum()) for k in ("measured", "replaced", "failed", "masked")}
    ax.set_title(f"{res['method']}: {n['measured']} of {len(x)} measured, {n['replaced']} replaced, "
                 f"{n['failed']} failed, {n['masked']} masked", fontsize=10)
    fig.colorbar(im, ax=ax, label="|displacement| [px]", shrink=0.85)
    if ax.get_legend_handles_labels()[0]:
        fig.legend(loc="outside lower center", ncols=3, fontsize=8, frameon=False)
    save_figure(fig, Path(out).with_suffix(""), formats=(fmt,))
    return summary


def figure_format(out) -> str:
    """The image format of a figure path, from its suffix; refused unless matplotlib writes it."""
    from matplotlib.figure import Figure

    kinds = Figure().canvas.get_supported_filetypes()
    kind = Path(out).suffix[1:]  # as written: the file gets exactly the name asked for
    if kind.lower() not in kinds:
        raise SynthbosError(f"-o {shorten(str(out))}: name a figure file ending in one of "
                            f"{', '.join('.' + k for k in sorted(kinds))}")
    return kind
