"""``synthbos show-result FILE.h5 -o FIG.png``: a figure and a short summary of any synthbos file.

A result file of ``synthbos process`` (correlation, tracking, any registered method): the displacement
magnitude of the measured points (a colour map of the vector grid, coloured dots, or, past
``DOT_MARKERS_MAX`` dots, their median in cells), the vectors as arrows with a quiver key above the image,
the points that were replaced (orange circles), failed (vermillion crosses) or masked (grey); past
``FAILED_MARKERS_MAX`` failures the failures are drawn as their density instead (the failed fraction in
cells, a panel of its own), so that a field of tens of thousands of dots stays readable. When the pair
file is known (``--pair``, or the pair file the result was processed from), a panel of the error against
the pair's truth (its displacement interpolated to the measured points). The title states the counts.

A density file of ``synthbos integrate``: drawn by ``show_density.plot_density_file``.

The figure is one file, in the format of its name's suffix (``.png`` at 300 dpi, ``.pdf``, ``.svg``,
``.jpg``), one journal column wide (3.5 in) with one panel, two (7.2 in) with more. The summary (returned
and printed) gives the counts, the median and largest displacement of the measured points and, with a
pair, their error.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from synthbos import SynthbosError

from .figures import ONE_COLUMN_IN, TWO_COLUMNS_IN, _fitted, figure_format, journal_style, save_figure
from .process import check_result_file
from .registry import DENSE, GRID

__all__ = ["DOT_MARKERS_MAX", "FAILED_MARKERS_MAX", "plot_result", "read_result", "result_truth"]

REPLACED_COLOR = "#E69F00"  # Okabe-Ito orange
FAILED_COLOR = "#D55E00"  # Okabe-Ito vermillion
MASKED_COLOR = "0.6"
#: Dots drawn as coloured markers up to this many; beyond, the median |displacement| in cells.
DOT_MARKERS_MAX = 4000
#: Failed or replaced points marked one by one up to this many; beyond, the failed fraction in cells.
FAILED_MARKERS_MAX = 600
#: Cells along the longer side of the image for the maps of many points.
_CELLS = 64


def read_result(path) -> dict:
    """The points of a result file of ``synthbos process`` and what became of each.

    Returns
    -------
    dict
        ``method``, ``kind``, ``x``, ``y``, ``u``, ``v`` (1-D, px), ``grid_shape`` (or None),
        boolean ``measured``, ``replaced``, ``failed``, ``masked`` (one of them true per point),
        ``settings`` (dict) and ``attrs`` (the file's root attributes).
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
        attrs = {k: (v.decode("utf-8", "replace") if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
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
    return {"method": method, "kind": kind, "settings": settings, "grid_shape": grid_shape, "attrs": attrs,
            **{k: np.ravel(a) for k, a in (("x", x), ("y", y), ("u", u), ("v", v), ("measured", measured),
                                           ("replaced", replaced), ("failed", failed), ("masked", masked))}}


def summary_line(res, errors=None) -> str:
    """Counts and the measured displacement of a :func:`read_result` dict, on one line; with ``errors`` (per
    point, px, NaN where not scored: :func:`result_truth`), their median and 90th percentile too."""
    n = {k: int(res[k].sum()) for k in ("measured", "replaced", "failed", "masked")}
    mag = np.hypot(res["u"], res["v"])[res["measured"]]
    noun = {GRID: "vectors", DENSE: "pixels"}.get(res["kind"], "dots")
    text = (f"{res['method']}: {len(res['x'])} {noun}: {n['measured']} measured, {n['replaced']} replaced, "
            f"{n['failed']} failed, {n['masked']} masked")
    if len(mag):
        text += f"; |displacement| of the measured: median {np.median(mag):.3f} px, max {mag.max():.3f} px"
    if errors is not None:
        e = errors[np.isfinite(errors)]
        if len(e):
            text += (f"; error against the pair's truth: median {np.median(e):.4f} px, 90th percentile "
                     f"{np.percentile(e, 90):.4f} px ({len(e)} scored)")
    return text


def result_truth(res, pair):
    """The pair's true displacement at each point of a :func:`read_result` dict (linear interpolation of its
    valid dots, NaN outside their hull) and the error magnitude of each measured point (NaN elsewhere), px.

    A result whose image is not the pair's (its ``image_shape`` attribute) is refused with one line.
    """
    from .scoring import interpolate_truth, vector_errors

    shape = res["attrs"].get("image_shape")
    if shape is not None and tuple(int(k) for k in np.ravel(shape)) != tuple(pair.reference.shape):
        raise SynthbosError(f"the result's image is {' x '.join(str(int(k)) for k in np.ravel(shape)[::-1])} px, the "
                            f"pair's {pair.reference.shape[1]} x {pair.reference.shape[0]} px: they do not belong "
                            "together")
    ok = pair.valid & np.all(np.isfinite(pair.displacement_px), axis=1)
    if ok.sum() < 3:
        raise SynthbosError("the pair holds fewer than 3 valid dots: no truth to draw the errors against")
    xy = np.stack([res["x"], res["y"]], axis=1)
    truth = interpolate_truth(pair.reference_px[ok], pair.displacement_px[ok], xy)
    errors = vector_errors(np.stack([res["u"], res["v"]], axis=1), truth)
    return truth, np.where(res["measured"], errors, np.nan)


def _pair_file(res, pair):
    """The pair file to draw the errors against: the one given, else the pair file the result was processed
    from (its ``input`` attribute) when it still exists; None without one."""
    if pair is not None:
        return Path(pair)
    src = str(res["attrs"].get("input", ""))
    try:
        if src and Path(src).is_file() and h5py.is_hdf5(src):
            with h5py.File(src, "r") as f:
                if "images/reference" in f and "dots/displacement_px" in f:
                    return Path(src)
    except OSError:  # a name the system refuses, a file it cannot read: no pair
        pass
    return None


def _is_density_file(path) -> bool:
    path = Path(path)
    if not (path.is_file() and h5py.is_hdf5(path)):
        return False
    with h5py.File(path, "r") as f:
        return "density_kg_m3" in f


def plot_result(path, out, *, pair=None, max_arrows=16) -> str:
    """Draw a synthbos file (module docstring) and return its summary.

    Parameters
    ----------
    path : str or Path
        Result file of ``synthbos process``, or density file of ``synthbos integrate``.
    out : str or Path
        Figure to write, atomically, in the format of its suffix (.png at 300 dpi, .pdf, .svg, .jpg, ...
        whatever matplotlib writes); only this file is written.
    pair : str or Path, optional
        Pair file of ``synthbos render`` to draw the errors against; by default the pair file the result
        was processed from, when it still exists.
    max_arrows : int
        At most about this many arrows along the longer side of the image (one per cell).
    """
    from synthbos.raytrace import read_pair

    fmt = figure_format(out)
    if _is_density_file(path):
        if pair is not None:
            raise SynthbosError(f"--pair: {path} is a density file, which holds its truth itself (when it was "
                                "integrated with --pair)")
        from .show_density import plot_density_file

        return plot_density_file(path, out)
    res = read_result(path)
    pair_path, note = _pair_file(res, pair), ""
    errors = None
    if pair_path is not None:
        try:
            errors = result_truth(res, read_pair(pair_path))[1]
        except SynthbosError as err:
            if pair is not None:  # the pair asked for: refused
                raise
            note = f" (no error panel: the pair file it was processed from, {pair_path}, no longer fits: {err})"
    summary = summary_line(res, errors) + note
    with journal_style():
        fig = _result_figure(res, errors, name=Path(path).name, max_arrows=max_arrows)
        save_figure(fig, Path(out).with_suffix(""), formats=(fmt,))
    return summary


def _image_shape(res):
    """(H, W) of the result's image: its ``image_shape`` attribute, else what its points span."""
    shape = res["attrs"].get("image_shape")
    if shape is not None and np.size(shape) == 2:
        return tuple(int(k) for k in np.ravel(shape))
    x, y = res["x"][np.isfinite(res["x"])], res["y"][np.isfinite(res["y"])]
    return (int(np.ceil(y.max() + 0.5)) if len(y) else 1, int(np.ceil(x.max() + 0.5)) if len(x) else 1)


def _result_figure(res, errors, *, name, max_arrows):
    import matplotlib.pyplot as plt

    many = int(res["failed"].sum() + res["replaced"].sum()) > FAILED_MARKERS_MAX
    panels = ["field"] + (["failed"] if many else []) + (["error"] if errors is not None else [])
    h, w = _image_shape(res)
    width = ONE_COLUMN_IN if len(panels) == 1 else TWO_COLUMNS_IN
    fig, axes = plt.subplots(1, len(panels), figsize=(width, (width - 0.5) / len(panels) * h / w + 1.6),
                             squeeze=False, sharex=True, sharey=True, layout="constrained")
    axes = axes[0]
    _draw_field(fig, axes[0], res, (h, w), max_arrows=max_arrows, markers=not many)
    if many:
        _draw_failed(fig, axes[panels.index("failed")], res, (h, w))
    if errors is not None:
        _draw_errors(fig, axes[-1], res, errors, (h, w))
    for k, ax in enumerate(axes):
        ax.set_aspect("equal")
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)  # image coordinates: row 0 at the top
        ax.set_xlabel("x (px)")
        ax.tick_params(labelleft=k == 0)
    axes[0].set_ylabel("y (px)")
    n = {k: int(res[k].sum()) for k in ("measured", "replaced", "failed", "masked")}
    fig.suptitle(_fitted(f"{name}, {res['method']}: {n['measured']:,} of {len(res['x']):,} measured, "
                         f"{n['replaced']:,} replaced, {n['failed']:,} failed, {n['masked']:,} masked", width - 0.1))
    if fig.axes[0].get_legend_handles_labels()[0]:
        fig.legend(loc="outside lower center", ncols=3, frameon=False)
    return fig


#: Cells hold this many points on average at least, so that few cells are empty.
_POINTS_PER_CELL = 6


def _cell_size(shape, points: int = 0) -> float:
    """Side (px) of the square cells that gather ``points`` points: ``max(shape) / _CELLS`` or larger, so
    that a cell holds ``_POINTS_PER_CELL`` of them on average."""
    return max(max(shape) / _CELLS, float(np.sqrt(shape[0] * shape[1] * _POINTS_PER_CELL / max(points, 1))))


def _in_cells(x, y, values, shape, *, statistic="median"):
    """``values`` at points (x, y) gathered in square cells of ``_cell_size`` px: the image of their
    ``statistic`` (NaN in empty cells) and its extent."""
    from scipy.stats import binned_statistic_2d

    h, w = shape
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(values)
    cell = _cell_size(shape, int(ok.sum()))
    ex, ey = np.arange(-0.5, w - 0.5 + cell, cell), np.arange(-0.5, h - 0.5 + cell, cell)
    if not ok.any():
        return np.full((len(ey) - 1, len(ex) - 1), np.nan), (ex[0], ex[-1], ey[-1], ey[0])
    img = binned_statistic_2d(y[ok], x[ok], values[ok], statistic=statistic, bins=[ey, ex]).statistic
    return img, (ex[0], ex[-1], ey[-1], ey[0])


def _grid_image(res, values):
    """A grid or dense result's per-point ``values`` as an image, and its extent (the points are cell centres)."""
    ny, nx = res["grid_shape"]
    gx, gy = res["x"].reshape(ny, nx), res["y"].reshape(ny, nx)
    dx = float(gx[0, 1] - gx[0, 0]) if nx > 1 else 1.0
    dy = float(gy[1, 0] - gy[0, 0]) if ny > 1 else 1.0
    ext = (gx[0, 0] - dx / 2, gx[0, -1] + dx / 2, gy[-1, 0] + dy / 2, gy[0, 0] - dy / 2)
    return np.asarray(values, dtype=np.float64).reshape(ny, nx), ext


def _point_map(ax, res, values, shape, *, where, **kw):
    """Per-point ``values`` where ``where``: an image for a grid result or past ``DOT_MARKERS_MAX`` dots (their
    median in cells), else coloured dots; return the mappable."""
    vals = np.where(where, values, np.nan)
    if res["grid_shape"] is not None:
        img, ext = _grid_image(res, vals)
    elif where.sum() > DOT_MARKERS_MAX:
        img, ext = _in_cells(res["x"], res["y"], vals, shape)
    else:
        size = float(np.clip(2.0e4 / max(int(where.sum()), 1), 1.0, 12.0))
        return ax.scatter(res["x"][where], res["y"][where], c=vals[where], s=size, linewidths=0, **kw)
    return ax.imshow(img, extent=ext, interpolation="nearest", **kw)


def _nice(value: float) -> float:
    """A round number (1, 2 or 5 x 10^k) near ``value``."""
    if not np.isfinite(value) or value <= 0:
        return 1.0
    k = np.floor(np.log10(value))
    return float(min((1.0, 2.0, 5.0, 10.0), key=lambda m: abs(np.log(m * 10**k / value))) * 10**k)


def _draw_field(fig, ax, res, shape, *, max_arrows, markers):
    """The measured |displacement|, arrows with their key above the image, masked points in grey, and (with
    ``markers``) the replaced and failed points one by one."""
    from matplotlib.colors import ListedColormap

    from .figures import _colorbar

    x, y, u, v = res["x"], res["y"], res["u"], res["v"]
    mag = np.hypot(u, v)
    meas = res["measured"] & np.isfinite(mag)
    vmax = float(np.nanmax(mag[meas])) if meas.any() else 1.0
    im = _point_map(ax, res, mag, shape, where=meas, cmap="viridis", vmin=0.0, vmax=vmax if vmax > 0 else 1.0)
    _colorbar(fig, im, ax, location="bottom", shrink=0.9, label="|displacement| (px)")
    if res["masked"].any():
        grey = ListedColormap([MASKED_COLOR])
        _point_map(ax, res, np.ones(len(x)), shape, where=res["masked"], cmap=grey, vmin=0, vmax=1)
        ax.plot([], [], "s", color=MASKED_COLOR, ms=4, ls="none", label=f"masked ({int(res['masked'].sum()):,})")
    # one arrow a cell, the cells no finer than the points' own spacing (a grid's, or the dots' mean)
    cell = max(max(shape) / max(max_arrows, 1), float(np.sqrt(shape[0] * shape[1] / max(len(x), 1))))
    keep = np.zeros(len(x), bool)
    idx = np.flatnonzero(meas)
    if len(idx):
        _, first = np.unique(np.stack([np.floor(x[idx] / cell), np.floor(y[idx] / cell)], 1), axis=0,
                             return_index=True)
        keep[idx[first]] = True
    key = _nice(float(np.percentile(mag[meas], 90)) if meas.any() else 0.0)
    q = ax.quiver(x[keep], y[keep], u[keep], v[keep], angles="xy", scale_units="xy", scale=key / (0.9 * cell),
                  color="white", edgecolor="black", linewidth=0.3, width=0.005, headwidth=3.5, headlength=4,
                  headaxislength=3.5, minlength=0.2, pivot="middle")
    ax.quiverkey(q, X=0.99 - 0.45 * cell / shape[1], Y=1.035, U=key, label=f"{key:g} px", labelpos="W",
                 coordinates="axes", color="black", fontproperties={"size": 7})  # its arrow ends at the right edge
    ax.set_title("displacement", loc="left")
    if markers and res["replaced"].any():
        ax.scatter(x[res["replaced"]], y[res["replaced"]], s=14, facecolors="none", edgecolors=REPLACED_COLOR,
                   linewidths=0.8, label=f"replaced ({int(res['replaced'].sum()):,})")
    if markers and res["failed"].any():
        ax.scatter(x[res["failed"]], y[res["failed"]], s=12, marker="x", color=FAILED_COLOR, linewidths=0.8,
                   label=f"failed ({int(res['failed'].sum()):,})")


def _draw_failed(fig, ax, res, shape):
    """The failed (and replaced) fraction of the unmasked points in each cell: readable however many failed."""
    from .figures import _colorbar

    bad = (res["failed"] | res["replaced"]).astype(np.float64)
    bad[res["masked"]] = np.nan
    img, ext = _in_cells(res["x"], res["y"], bad, shape, statistic="mean")
    im = ax.imshow(img, extent=ext, interpolation="nearest", cmap="magma_r", vmin=0.0, vmax=1.0)
    cell = _cell_size(shape, int(np.isfinite(bad).sum()))
    _colorbar(fig, im, ax, location="bottom", shrink=0.9,
              label=f"failed or replaced: fraction\nof the points in each {cell:.3g} px cell")
    ax.set_title(f"{int(res['failed'].sum()):,} failed, {int(res['replaced'].sum()):,} replaced", loc="left")


def _draw_errors(fig, ax, res, errors, shape):
    """The error of each measured point against the pair's truth, on a log colour scale."""
    from matplotlib.colors import LogNorm

    from .figures import _colorbar

    ok = np.isfinite(errors)
    e = errors[ok]
    hi = float(e.max()) if len(e) else 1.0
    lo = max(float(np.percentile(e, 1)) if len(e) else 1e-3, hi * 1e-4, 1e-6)
    im = _point_map(ax, res, np.maximum(errors, lo), shape, where=ok, cmap="cividis",
                    norm=LogNorm(lo, max(hi, lo * 10)))
    _colorbar(fig, im, ax, location="bottom", shrink=0.9, label="|error| against the truth (px)")
    words = f"median {np.median(e):.3g} px, p90 {np.percentile(e, 90):.3g} px" if len(e) else "nothing scored"
    ax.set_title(f"error: {words}", loc="left")
