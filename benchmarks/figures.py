"""Figures of a campaign: the flows and displacements (fig4) and the error CDFs (fig5), as in
section 4 of Rajendran, Bane & Vlachos (2019); the density integrated from each method (fig_density);
the error budget (fig_budget: error against the dots' in-cone spread); and the experiment-design plots
of a sweep (sweep, sweep_budget)."""

from __future__ import annotations

import functools
import gc
import textwrap
import tomllib
from contextlib import contextmanager
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.backends.backend_pdf  # with this module (a worker imports it early), not at the first PDF
import matplotlib.pyplot as plt
import numpy as np
from cycler import cycler
from matplotlib.colors import BoundaryNorm
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter, NullLocator
from matplotlib.tri import LinearTriInterpolator, Triangulation
from synthbos.raytrace import load_config, read_pair
from synthbos.raytrace.sources import density_from_config

from synthbos import SynthbosError, atomic_output
from synthbos.values import shorten

from . import scoring
from .campaign_figures import CAMPAIGN_FIGURES as _CAMPAIGN_STEMS
from .campaign_figures import FIRST_PAIR_FIGURES, FORMATS
from .registry import METHODS
from .storage import DENSITY_TRUTHS, load_density_map, load_scores, pair_path
from .tables import split_masks

__all__ = [
    "CAMPAIGN_FIGURES",
    "FIRST_PAIR_FIGURES",
    "FORMATS",
    "JOURNAL_STYLE",
    "OKABE_ITO",
    "ONE_COLUMN_IN",
    "TWO_COLUMNS_IN",
    "binned_errors",
    "campaign_figure",
    "figure4",
    "figure5",
    "figure_budget",
    "figure_density",
    "figure_format",
    "journal_style",
    "method_style",
    "save_figure",
    "sweep_budget_figure",
    "sweep_figure",
    "yield_limits",
]


def figure_format(out) -> str:
    """The image format of a figure path, from its suffix; refused unless matplotlib writes it."""
    kinds = Figure().canvas.get_supported_filetypes()
    kind = Path(out).suffix[1:]  # as written: the file gets exactly the name asked for
    if kind.lower() not in kinds:
        raise SynthbosError(f"-o {shorten(str(out))}: name a figure file ending in one of "
                            f"{', '.join('.' + k for k in sorted(kinds))}")
    return kind


_DPI = 300
#: What each figure reads of the score files (``storage.load_scores``): the error CDFs split at the threshold,
#: the density error CDFs, the error budget against the in-cone spread.
_CDF_FIELDS = ("error", "grad_error", "true_mag", "threshold")
_DENSITY_FIELDS = tuple(f"density_{t}_rel" for t in DENSITY_TRUTHS)
_BUDGET_FIELDS = ("error", "spread", "true_mag", "threshold")

#: Figure widths (in): one journal column, two columns. Every figure is drawn at one of them, so that its
#: text keeps the size it was drawn with when the figure is printed.
ONE_COLUMN_IN, TWO_COLUMNS_IN = 3.5, 7.2
#: The Okabe & Ito (2008) colour-blind-safe colours (the registry styles its methods with them).
OKABE_ITO = ("#0072B2", "#D55E00", "#009E73", "#E69F00", "#CC79A7", "#56B4E9", "#000000", "#F0E442")
_CYCLE_STYLES = ("-", "--", "-.", ":", (0, (3, 1, 1, 1, 1, 1)), (0, (5, 2)), (0, (8, 2, 2, 2)), (0, (1, 1)))
#: The one style of synthbos's figures (``journal_style()``): text of 7 to 8 pt at print size, thin lines,
#: the Okabe-Ito colours each with its own line style for whatever the registry does not style, vector
#: text in the PDF (TrueType) and SVG (text elements), 300 dpi.
JOURNAL_STYLE = {
    "font.size": 7.5, "axes.titlesize": 7.5, "axes.labelsize": 7.5, "xtick.labelsize": 7.0, "ytick.labelsize": 7.0,
    "legend.fontsize": 7.0, "legend.title_fontsize": 7.0, "figure.titlesize": 8.0, "figure.labelsize": 7.5,
    "axes.prop_cycle": cycler(color=OKABE_ITO) + cycler(linestyle=_CYCLE_STYLES),
    "lines.linewidth": 1.0, "lines.markersize": 3.0, "axes.linewidth": 0.6, "grid.linewidth": 0.4,
    "xtick.major.width": 0.6, "ytick.major.width": 0.6, "xtick.minor.width": 0.4, "ytick.minor.width": 0.4,
    "xtick.major.size": 2.5, "ytick.major.size": 2.5, "xtick.minor.size": 1.5, "ytick.minor.size": 1.5,
    "legend.handlelength": 2.6, "legend.borderaxespad": 0.3, "legend.columnspacing": 1.2,
    "figure.constrained_layout.h_pad": 0.02, "figure.constrained_layout.w_pad": 0.02,
    "image.cmap": "cividis", "pdf.fonttype": 42, "svg.fonttype": "none", "savefig.dpi": _DPI,
    "svg.hashsalt": "synthbos",  # the SVG's element ids the same in every run
}
#: The smallest text of a figure, pt.
MIN_FONT_PT = 7.0
#: savefig's keywords per format: zlib level 3 for the PNG writes the same pixels in 0.6 of the time
#: of the default level (6) into a file about 1/6 larger; no date in the PDF and SVG, so that the same
#: results give the same files, byte for byte.
_SAVE_OPTIONS = {"png": {"pil_kwargs": {"compress_level": 3}}, "pdf": {"metadata": {"CreationDate": None}},
                 "svg": {"metadata": {"Date": None}}}

#: Points drawn per error CDF (``scoring.empirical_cdf``'s ``max_points``): finer than the pixels of a
#: 300 dpi panel, however many errors a campaign scored.
_CDF_POINTS = 4096


def _count(n: int, noun: str) -> str:
    return f"{n:,} {noun}{'' if n == 1 else 's'}"


def _collector_paused(draw):
    """Run the figure function ``draw`` with Python's cyclic garbage collector paused.

    A figure is tens of thousands of small objects, many in reference cycles (artists and their axes,
    transforms and their parents), all alive until it is saved: each full collection while it is drawn
    walks all of them to free nothing. Collection resumes (if it was on) when the function returns, and
    the closed figure's cycles go with the next one, a single pass (on the quick campaign: collections
    took 0.19 s while fig5 was drawn, 0.24 s for fig_density and 0.57 s for fig4; the one pass after
    each 0.09, 0.10 and 0.38 s).
    """

    @functools.wraps(draw)
    def paused(*args, **kwargs):
        was_on = gc.isenabled()
        gc.disable()
        try:
            return draw(*args, **kwargs)
        finally:
            if was_on:
                gc.enable()

    return paused


def journal_style():
    """A context in which figures take synthbos's one style (``JOURNAL_STYLE``); ``with journal_style(): ...``."""
    return plt.rc_context(JOURNAL_STYLE)


def _journal(draw):
    """Run the figure function ``draw`` in the journal style (``journal_style``), collector paused
    (``_collector_paused``)."""
    paused = _collector_paused(draw)

    @functools.wraps(draw)
    def styled(*args, **kwargs):
        with journal_style():
            return paused(*args, **kwargs)

    return styled


def _fitted(text: str, width_in: float, *, fontsize: float = 8.0) -> str:
    """``text`` wrapped, paragraph by paragraph (its newlines kept), into lines that fit ``width_in`` inches
    at ``fontsize`` pt (an average glyph of DejaVu Sans is under 0.58 em wide)."""
    chars = max(20, int(width_in * 72.0 / (0.58 * fontsize)))
    return "\n".join(textwrap.fill(line, chars) for line in text.split("\n"))


def _suptitle(fig, text: str):
    """The figure's title, wrapped to its width."""
    size = plt.rcParams["figure.titlesize"]
    size = float(size) if not isinstance(size, str) else 8.0
    return fig.suptitle(_fitted(text, fig.get_figwidth() - 0.1, fontsize=size))


def method_style(name: str) -> dict:
    """Matplotlib keywords (colour, line style, marker, label) of a method, from the registry."""
    m = METHODS.get(name)
    if m is None:
        return {"label": name}
    return {"color": m.color, "ls": m.linestyle, "label": m.label}


def save_figure(fig, path, *, formats=None) -> list[Path]:
    """Save ``fig`` as ``path`` with each suffix of ``formats`` (``FORMATS`` by default), atomically; return
    the paths written.

    ``path`` may carry a suffix (``fig4.png``) or not (``fig4``); either way every format is written.
    """
    path = Path(path)
    stem = path.with_suffix("") if path.suffix.lower() in {f".{f}" for f in FORMATS} else path
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            _minor_ticks_as_lines(axis)
    written = []
    with _ticks_cached(fig):
        _lay_out(fig, dpi=_DPI)
        for fmt in FORMATS if formats is None else formats:
            out = stem.with_name(f"{stem.name}.{fmt}")
            with atomic_output(out) as tmp:
                fig.savefig(tmp, dpi=_DPI, format=fmt, **_SAVE_OPTIONS.get(fmt, {}))
            written.append(out)
    plt.close(fig)
    return written


def _minor_ticks_as_lines(axis) -> bool:
    """Draw the unlabelled minor ticks of ``axis`` (their marks and grid lines) as one line each, with the
    properties of the axis's own minor tick, instead of one `~matplotlib.axis.Tick` per tick; return whether
    it did.

    A log axis has up to eight minor ticks a decade, each a Tick of five artists that every layout pass and
    every draw positions, measures and draws again; drawn as two lines of the same marks at the same places
    they look the same for a fraction of the time. Call it when the axis's limits are final. Axes whose
    minor ticks carry labels, shared axes (one locator for several) and colour bars keep their ticks.
    """
    ax = axis.axes
    siblings = (ax.get_shared_x_axes() if axis.axis_name == "x" else ax.get_shared_y_axes()).get_siblings(ax)
    if (
        len(siblings) > 1
        or getattr(ax, "_colorbar", None) is not None
        or isinstance(axis.get_minor_locator(), NullLocator)
    ):
        return False
    locs = np.asarray(axis.get_minorticklocs(), dtype=np.float64)
    if len(locs) == 0:
        return False
    lo, hi = sorted(axis.get_view_interval())
    a, b = axis.get_transform().transform([lo, hi])  # kept as Axis._update_ticks keeps them: inside, give or take
    tol = (b - a) * 1e-10
    t = axis.get_transform().transform(locs)
    locs = locs[(t >= a - tol) & (t <= b + tol)]
    if any(axis.get_minor_formatter().format_ticks(locs)):
        return False
    tick = axis.get_minor_ticks(1)[0]  # its marks and grid line hold the axis's minor tick parameters
    tick.update_position(locs[0] if len(locs) else lo)
    for src, one in ((tick.tick1line, False), (tick.tick2line, False), (tick.gridline, True)):
        if not src.get_visible() or len(locs) == 0:
            continue
        across = src.get_xdata() if axis.axis_name == "y" else src.get_ydata()  # e.g. 0 (a mark), 0 to 1 (grid)
        if one:  # one segment per tick, separated by NaN
            pos = np.repeat(locs, 3)
            pos[2::3] = np.nan
            oth = np.tile(np.append(np.asarray(across, dtype=np.float64), np.nan), len(locs))
        else:
            pos, oth = locs, np.full(len(locs), float(np.asarray(across)[0]))
        line = Line2D(*((oth, pos) if axis.axis_name == "y" else (pos, oth)))
        line.update_from(src)
        line.set(
            antialiased=src.get_antialiased(),
            snap=src.get_snap(),
            zorder=axis.get_zorder(),
            label="_minor ticks",
            in_layout=False,
        )
        ax.add_artist(line)
        line.set_clip_box(src.get_clip_box())  # add_artist clips to the axes; the marks lie outside them
        line.set_clip_path(src.get_clip_path())
    axis.set_minor_locator(NullLocator())
    return True


@contextmanager
def _ticks_cached(fig):
    """Within the block, each axis of ``fig`` works out its ticks once per layout state, not at every call.

    Matplotlib's ``Axis._update_ticks`` (run the locator and formatter, place every tick) runs three to five
    times per axis in each layout pass and each draw (for its bounding box, its label's position, the
    title's position, the draw), always to the same result while the view limits, the dpi and the axes'
    place stay put; here it runs again only when one of those moved. Likewise the tick labels' boxes
    (``Axis._get_ticklabel_bboxes``: a text extent per label), measured twice per axis in each pass, once
    for the label's position and once for the axis's box. For the saving of a finished figure.
    """
    patched = []
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            update = getattr(axis, "_update_ticks", None)
            if update is None:  # a matplotlib without it: nothing to cache
                continue
            axis._update_ticks = _cached_ticks(fig, axis, update)
            patched.append(axis)
            boxes = getattr(axis, "_get_ticklabel_bboxes", None)
            if boxes is not None:
                axis._get_ticklabel_bboxes = _cached_boxes(fig, axis, boxes)
    try:
        yield
    finally:
        for axis in patched:
            del axis._update_ticks  # the class's method again
            axis.__dict__.pop("_get_ticklabel_bboxes", None)


def _cached_ticks(fig, axis, update):
    cache = {}

    def ticks():
        key = (tuple(axis.get_view_interval()), fig.dpi, tuple(axis.axes.bbox.bounds))
        if key not in cache:
            cache.clear()
            cache[key] = update()
        return cache[key]

    return ticks


def _cached_boxes(fig, axis, boxes):
    cache = {}

    def ticklabel_boxes(ticks, renderer):
        key = (id(ticks), len(ticks), id(renderer), fig.dpi, tuple(axis.axes.bbox.bounds))
        if key not in cache:
            cache.clear()
            cache[key] = (ticks, boxes(ticks, renderer))  # ticks kept so that their id stays theirs
        tlb1, tlb2 = cache[key][1]
        return list(tlb1), list(tlb2)

    return ticklabel_boxes


def _lay_out(fig, *, dpi):
    """Run ``fig``'s layout engine (the figures' constrained layout) once, measuring text at ``dpi``, and
    switch it off, so that every format is drawn with that one layout.

    ``savefig`` would otherwise lay the figure out again for each format, each time after a complete draw
    that renders nothing: with dozens of axes that is most of the time a figure takes. The layout is what
    the PNG's ``savefig`` computes (the Agg renderer at the PNG's dpi); the PDF, laid out with its own
    text metrics before, now shares it (its panels lie within a point of where the PDF's own layout put them).
    """
    engine = fig.get_layout_engine()
    if engine is None or not fig.axes:
        return
    saved = fig.dpi
    fig.dpi = dpi
    try:
        for _ in range(8):
            engine.execute(fig)
            if _title_clear(fig):
                break
            fig.set_figheight(fig.get_figheight() * 1.06)
    finally:
        fig.dpi = saved
    fig.set_layout_engine(None)  # not "none": savefig still draws once before each file with a placeholder


def _title_clear(fig) -> bool:
    """Whether the figure's title (suptitle) clears every axes with its labels and title.

    Constrained layout gives the title its room, but panels of a fixed aspect (images) in a figure too short
    for them can still end up under it; ``_lay_out`` then makes the figure taller, a step at a time.
    """
    title = fig._suptitle
    if title is None or not title.get_text() or not hasattr(fig.canvas, "get_renderer"):
        return True
    renderer = fig.canvas.get_renderer()
    box = title.get_window_extent(renderer)
    for ax in fig.axes:
        other = ax.get_tightbbox(renderer)
        if other is not None and min(box.x1, other.x1) > max(box.x0, other.x0) and min(box.y1, other.y1) > max(
                box.y0, other.y0):
            return False
    return True


def _nice_levels(vmax: float, n: int = 12) -> np.ndarray:
    """Contour levels from 0 to at least ``vmax`` at round steps (0.05, 0.1, 0.2, ...)."""
    return MaxNLocator(nbins=n, steps=[1, 2, 2.5, 5, 10]).tick_values(0.0, max(float(vmax), 1e-9))


def _colorbar(fig, mappable, ax, **kwargs):
    """``fig.colorbar`` with its colour strip kept as vector quads: matplotlib rasterises a strip of 50
    colours or more, and in a PDF every rasterised artist renders the whole figure at 300 dpi once."""
    cb = fig.colorbar(mappable, ax=ax, **kwargs)
    if cb.solids is not None:
        cb.solids.set_rasterized(False)
    return cb


def _level_map(ax, tri, values, shape, levels, *, cell=2.0):
    """Values at scattered dots as filled bands between ``levels`` over an image of ``shape`` (px).

    The dots' values are interpolated linearly over ``tri``, the dots' Delaunay `Triangulation`, onto a
    grid of ``cell`` px and shown as an image in the colour of each level band (what ``tricontourf``
    draws, as one small image instead of thousands of polygons: quick to draw, and a small PDF); blank
    outside the dots' hull. Maps of the same dots share ``tri`` and so its triangle finder, built once.
    """
    h, w = shape
    gx = np.arange(0.0, w + cell / 2, cell)
    gy = np.arange(0.0, h + cell / 2, cell)
    grid = LinearTriInterpolator(tri, values)(*np.meshgrid(gx, gy))
    cmap = plt.get_cmap("cividis")
    im = ax.imshow(
        grid,
        extent=(gx[0] - cell / 2, gx[-1] + cell / 2, gy[-1] + cell / 2, gy[0] - cell / 2),
        cmap=cmap,
        norm=BoundaryNorm(levels, cmap.N),
        interpolation="nearest",
    )
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    return im


def _figure4_row(folder, snapshot):
    """What fig4 draws of one snapshot: its first pair's mid-plane density and gradient magnitude, the dots'
    three displacement magnitudes (chief-ray Eq. 4, Eq. 4 over the cone, ray-traced) and the counts."""
    pair = read_pair(pair_path(folder, snapshot, 0))
    cfg = load_config(tomllib.loads(pair.attrs["config"]))
    vol = {k: v for k, v in cfg["volume"].items() if k != "offset_mm"}
    dens = density_from_config(vol)
    rho = dens.rho[dens.rho.shape[0] // 2]
    lx, ly = dens.size_m[0] * 1e3, dens.size_m[1] * 1e3
    gy, gx = np.gradient(rho, ly * 1e-3 / (rho.shape[0] - 1), lx * 1e-3 / (rho.shape[1] - 1))
    ok = pair.valid
    cone = pair.theory_cone_px if pair.theory_cone_px is not None else np.full_like(pair.theory_px, np.nan)
    mags = [np.hypot(*a[ok].T) for a in (pair.theory_px, cone, pair.displacement_px)]
    return {"rho": rho, "grad": np.hypot(gx, gy), "extent": (-lx / 2, lx / 2, ly / 2, -ly / 2),
            "xy": pair.reference_px[ok], "mags": mags, "shape": pair.reference.shape,
            "counts": (int(ok.sum()), pair.n_dots), "rays": pair.attrs.get("rays_per_dot", "?")}


_FIG4_TITLES = ("density ρ", "density gradient\n|∇ρ|", "|ΔX|, Eq. 4\n(chief ray)", "|ΔX|, Eq. 4\nover the ray cone",
                "|ΔX|,\nray-traced")


@_journal
def figure4(spec, folder, path, *, formats=None):
    """For each snapshot: density, density-gradient magnitude, theoretical (Eq. 4 along the chief ray),
    cone-averaged theoretical (Eq. 4 averaged over the rays traced for each dot) and ray-traced
    displacement magnitude (filled contours), from the first pair of the snapshot.

    Two columns wide (7.2 in), one row per snapshot. The rows of a column share one scale (its colour bar,
    under the column), so that the snapshots compare; each displacement column has its own: the
    ray-traced displacement is the aperture's average of Eq. 4's and several times weaker, so a shared
    scale would leave it dark.
    """
    folder = Path(folder)
    snaps = list(spec.snapshots)
    data = [_figure4_row(folder, s) for s in snaps]
    fig, axes = plt.subplots(len(snaps), 5, figsize=(TWO_COLUMNS_IN, 1.3 * len(snaps) + 1.6), squeeze=False,
                             layout="constrained")
    for c, title in enumerate(_FIG4_TITLES):
        axes[0, c].set_title(title)
    top = [max(float(np.nanmax(d["mags"][k])) if np.isfinite(d["mags"][k]).any() else 0.0 for d in data)
           for k in range(3)]
    rho_lim = (min(float(d["rho"].min()) for d in data), max(float(d["rho"].max()) for d in data))
    grad_max = max(float(d["grad"].max()) for d in data)
    mappables = [None] * 5
    for row, (s, d) in enumerate(zip(snaps, data, strict=True)):
        ax = axes[row]
        mappables[0] = ax[0].imshow(d["rho"], extent=d["extent"], cmap="viridis", vmin=rho_lim[0], vmax=rho_lim[1])
        mappables[1] = ax[1].imshow(d["grad"], extent=d["extent"], cmap="magma", vmin=0.0, vmax=grad_max)
        tri = None  # the dots' triangulation, one for the row's maps
        for k, vals in enumerate(d["mags"]):
            a = ax[k + 2]
            if not np.isfinite(vals).all():  # a pair file from before the cone truth
                a.text(0.5, 0.5, "not in this\npair file", ha="center", va="center", transform=a.transAxes)
                continue
            tri = Triangulation(d["xy"][:, 0], d["xy"][:, 1]) if tri is None else tri
            mappables[k + 2] = _level_map(a, tri, vals, d["shape"], _nice_levels(top[k]))
        ax[0].set_ylabel(f"snapshot {s}\ny (mm)")
        ax[2].set_ylabel("y (px)")
        for c, a in enumerate(ax):
            a.xaxis.set_major_locator(MaxNLocator(3))
            a.yaxis.set_major_locator(MaxNLocator(3))
            a.tick_params(labelleft=c in (0, 2), labelbottom=row == len(snaps) - 1)
    for c, unit in enumerate(("mm", "mm", "px", "px", "px")):
        axes[-1, c].set_xlabel(f"x ({unit})")
    _fig4_colorbars(fig, axes, mappables)
    used, total = (sum(d["counts"][k] for d in data) for k in range(2))
    _suptitle(fig, f"Campaign '{spec.name}', first pair of each snapshot: density at the volume's mid-plane and dot "
                   f"displacement magnitude ({used:,} of {total:,} dots valid, {data[-1]['rays']} rays per dot; "
                   "the rows of a column share its scale, each |ΔX| column on its own scale)")
    save_figure(fig, path, formats=formats)


def _fig4_colorbars(fig, axes, mappables):
    """fig4's colour bars: one under each column, for all its rows."""
    labels = ("ρ (kg/m³)", "|∇ρ| (kg/m⁴)", "|ΔX| (px)", "|ΔX| (px)", "|ΔX| (px)")
    for c, (im, label) in enumerate(zip(mappables, labels, strict=True)):
        if im is None:
            continue
        kw = {}
        if isinstance(im.norm, BoundaryNorm):
            levels = im.norm.boundaries
            kw["ticks"] = levels[:: max(1, (len(levels) + 2) // 3)]
        else:
            kw["ticks"] = MaxNLocator(3)
        cb = _colorbar(fig, im, axes[:, c], location="bottom", shrink=0.9, aspect=12, pad=0.01, label=label, **kw)
        if c == 1:
            cb.formatter.set_powerlimits((-2, 3))


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
    """A log axis whose labelled ticks suit its span: decades over two decades or more, 1 and 3 x 10^k over more
    than a factor 15, else 1, 2, 5 x 10^k, and 1, 2, 3, 5 x 10^k below a factor 4 (a narrow axis still has
    numbers, a panel of a two-column figure room for them)."""
    axis.axes.set_xscale("log") if axis.axis_name == "x" else axis.axes.set_yscale("log")
    span = hi / lo if lo > 0 else np.inf
    if span >= 100:
        axis.set_major_locator(LogLocator(base=10, subs=(1.0,)))
    else:
        subs = (1.0, 3.0) if span >= 15 else (1.0, 2.0, 5.0) if span >= 4 else (1.0, 2.0, 3.0, 5.0)
        axis.set_major_locator(LogLocator(base=10, subs=subs))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
    axis.set_minor_formatter(NullFormatter())


def _counts_width(fig, ncols, curves) -> float:
    """The width of a CDF panel's column of counts (``n = 12,345`` at 7 pt), as a fraction of the panel's."""
    chars = max((len(f"n = {int(np.isfinite(e).sum()):,}") for _, e in curves), default=8)
    panel_pt = fig.get_figwidth() * 72.0 * 0.88 / ncols
    return min(0.9, (chars * 0.6 * MIN_FONT_PT + 4.0) / panel_pt)


def _room_for_counts(curves, lo, hi, *, top, left):
    """The right end of a CDF panel's log error axis from ``lo``: ``hi``, or farther where a curve would still be
    below ``top`` (the counts' top, axes fraction) right of ``left`` (their left edge): as a CDF rises, a
    curve that has reached ``top`` before ``left`` stays clear of the counts in the panel's lower right."""
    finite = [np.asarray(e, dtype=np.float64)[np.isfinite(e)] for e in curves]
    q = max((float(np.quantile(e, min(top, 1.0))) for e in finite if len(e)), default=lo)
    if q <= lo or left <= 0.0:
        return hi
    return max(hi, lo * (q / lo) ** (1.0 / left))


@_journal
def figure5(spec, folder, path, *, formats=None):
    """Error CDFs on a log error axis: one row per noise level; columns: displacement error below and
    above the threshold, displacement-gradient error below and above; all methods; the Cramér-Rao bound
    of the displacement as a dashed line.

    The threshold (half the standard deviation of Eq. 4's displacement magnitudes, per pair) is stated in
    the title, the number of points of each method in each panel; each panel's error axis spans its data
    (the smallest 0.5 % of the errors sit at its left edge).
    """
    noises = list(spec.noise_percent)
    cols = [("displacement", "below"), ("displacement", "above"), ("gradient", "below"), ("gradient", "above")]
    fig, axes = plt.subplots(
        len(noises), 4, figsize=(TWO_COLUMNS_IN, 1.45 * len(noises) + 1.3), squeeze=False, sharey=True,
        layout="constrained"
    )
    thresholds = None
    for r, noise in enumerate(noises):
        curves = {c: [] for c in range(len(cols))}
        for method in spec.methods:
            sc = load_scores(spec, folder, method, noise, fields=_CDF_FIELDS)
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
            step = min(0.1, 0.6 / max(len(curves[c]), 1))
            hi = _room_for_counts([e for _, e in curves[c]], lo, hi, top=0.04 + step * len(curves[c]) + 0.04,
                                  left=1.0 - _counts_width(fig, len(cols), curves[c]))
            counts = []
            for method, e in curves[c]:
                x, y = scoring.empirical_cdf(e, max_points=_CDF_POINTS)
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
                ax.text(0.98, 0.04 + step * k, f"n = {n:,}", transform=ax.transAxes, ha="right", va="bottom",
                        fontsize=MIN_FONT_PT, color=method_style(method).get("color", "k"))
            unit = "px" if quantity == "displacement" else "px/px"
            ax.set_xlabel(f"{quantity} error ({unit})")
            if r == 0:
                what = "displacement" if quantity == "displacement" else "displacement gradient"
                ax.set_title(f"{what},\n|ΔX| {'<' if split == 'below' else '≥'} threshold")
        axes[r, 0].set_ylabel(f"noise {noise:g} %\nCDF")
    handles = [plt.Line2D([], [], **method_style(m)) for m in spec.methods]
    labels = [method_style(m)["label"] for m in spec.methods]
    handles.append(plt.Line2D([], [], color="k", ls=":", lw=1.2))
    labels.append("Cramér-Rao bound (displacement)")
    fig.legend(handles, labels, loc="outside lower center", ncol=min(len(labels), 3), frameon=False)
    _suptitle(
        fig,
        f"Error CDFs, campaign '{spec.name}' ({_count(len(spec.pair_keys()), 'pair')}). Threshold: half the standard "
        f"deviation of Eq. 4's |ΔX| in each pair, {_threshold_text(thresholds)}; "
        "n: points scored per method",
    )
    save_figure(fig, path, formats=formats)


#: How fig_density tells its noise levels apart, besides the line width: line style and marker.
_NOISE_STYLES = (("-", None), ("--", "o"), (":", "s"), ("-.", "^"), ((0, (5, 1, 1, 1)), "D"), ((0, (1, 2)), "v"))


def _density_maps(folder, s0, n0, methods):
    """fig_density's maps of each method (``storage.load_density_map``, None where there is none) and the
    shared limits: the truth's range and the largest |reconstructed - true|, over all methods."""
    maps = {m: load_density_map(folder, s0, 0, n0, m) for m in methods}
    lo, hi, lim = np.inf, -np.inf, 1e-12
    for mp in maps.values():
        if mp is None:
            continue
        truth = mp["density_truth_cone"]
        lo, hi = min(lo, float(np.nanmin(truth))), max(hi, float(np.nanmax(truth)))
        diff = mp["density_map"] - truth
        if np.isfinite(diff).any():
            lim = max(lim, float(np.nanmax(np.abs(diff))))
    return maps, (lo, hi), lim


@_journal
def figure_density(spec, folder, path, *, formats=None):
    """True and reconstructed depth-averaged density per method, with the error CDFs.

    One row per method. Maps from the first pair of the first snapshot at the lowest noise level: the
    cone truth, the reconstruction (integrated by ``integrate.DENSITY_SOLVER``, the constant from the
    truth over the measured domain's border) and their difference. Then the CDFs of the absolute
    density error relative to the truth's range, over all pairs, against the cone truth and against the
    chief-ray truth, one line per noise level (its own line style and marker). Every row shares the same
    scales: one density scale, one error scale, one CDF axis; each row's legend (noise level and count)
    sits outside its axes, at the right.
    """
    folder = Path(folder)
    methods, noises = list(spec.methods), list(spec.noise_percent)
    s0, n0 = spec.snapshots[0], min(noises)
    maps, (lo, hi), lim = _density_maps(folder, s0, n0, methods)
    fig, axes = plt.subplots(len(methods), 5, figsize=(TWO_COLUMNS_IN, 1.3 * len(methods) + 1.3), squeeze=False,
                             layout="constrained")
    dens_im = diff_im = None
    for r, method in enumerate(methods):
        ax = axes[r]
        label = textwrap.fill(method_style(method)["label"], 22)
        mp = maps[method]
        if mp is not None:
            x, y = mp["density_x_mm"], mp["density_y_mm"]
            ext = (x[0], x[-1], y[-1], y[0])
            truth, rec = mp["density_truth_cone"], mp["density_map"]
            for k, field in enumerate((truth, rec)):
                dens_im = ax[k].imshow(field, extent=ext, vmin=lo, vmax=hi, cmap="viridis", interpolation="nearest")
            diff_im = ax[2].imshow(rec - truth, extent=ext, vmin=-lim, vmax=lim, cmap="RdBu_r",
                                   interpolation="nearest")
        for c, a in enumerate(ax[:3]):
            a.xaxis.set_major_locator(MaxNLocator(3))
            a.yaxis.set_major_locator(MaxNLocator(3))
            a.tick_params(labelleft=c == 0, labelbottom=r == len(methods) - 1)
        ax[0].set_ylabel(f"{label}\ny (mm)", color=method_style(method).get("color", "k"))
        _density_cdfs(ax[3:], spec, folder, method, noises, last_row=r == len(methods) - 1)
    titles = ("true (cone)\ndensity", "reconstructed\ndensity", "reconstructed\n− true",
              "|error| vs the\ncone-of-rays truth", "|error| vs the\nchief-ray truth")
    for c, title in enumerate(titles):
        axes[0, c].set_title(title)
    for c in range(3):
        axes[-1, c].set_xlabel("x (mm)")
    if dens_im is not None:
        _colorbar(fig, dens_im, axes[:, :2], location="bottom", shrink=0.8, aspect=20, pad=0.01, label="ρ (kg/m³)",
                  ticks=MaxNLocator(4))
        _colorbar(fig, diff_im, axes[:, 2], location="bottom", shrink=0.9, aspect=10, pad=0.01, label="Δρ (kg/m³)",
                  ticks=MaxNLocator(3))
    _suptitle(fig, f"Campaign '{spec.name}': depth-averaged density from each method's displacements (least "
                   f"squares), against the cone and chief-ray truths; maps: snapshot {s0}, first pair, noise "
                   f"{n0:g} %, one density scale and one error scale for all rows")
    save_figure(fig, path, formats=formats)


def _density_cdfs(axes, spec, folder, method, noises, *, last_row):
    """One fig_density row's two CDF panels (cone truth, chief-ray truth), with the row's legend at the right."""
    style = method_style(method)
    widths = np.linspace(1.4, 0.8, len(noises))
    scores = [load_scores(spec, folder, method, noise, fields=_DENSITY_FIELDS) for noise in noises]  # both truths
    for c, truth in enumerate(DENSITY_TRUTHS):
        for k, (noise, sc) in enumerate(zip(noises, scores, strict=True)):
            e = sc[f"density_{truth}_rel"]
            xs, ys = scoring.empirical_cdf(e, max_points=_CDF_POINTS)
            ls, marker = _NOISE_STYLES[k % len(_NOISE_STYLES)]
            axes[c].step(np.maximum(xs, 1e-6), ys, where="post", color=style.get("color"), ls=ls, lw=widths[k],
                         marker=marker, ms=2.5, markevery=(0.03 * k, 0.25),
                         label=f"noise {noise:g}% (n = {np.isfinite(e).sum()})")
        a = axes[c]
        a.set_xscale("log")
        a.set_xlim(1e-5, 1)
        a.set_ylim(0, 1.02)
        a.xaxis.set_major_locator(LogLocator(base=10, numticks=4))
        a.grid(True, which="major", alpha=0.3)
        a.tick_params(labelleft=c == 0, labelbottom=last_row)
        if last_row:
            a.set_xlabel("|Δρ| / true range")
    axes[0].set_ylabel("CDF")
    axes[1].legend(loc="center left", bbox_to_anchor=(1.02, 0.5), frameon=False, handlelength=2.4,
                   title=textwrap.fill(style["label"], 18))


#: The in-cone spread bins (edges, px) along the budget figures' x axis; a bin is drawn where it holds at
#: least ``_BUDGET_MIN_POINTS`` scored points, at the median spread of its points (spreads below
#: ``_BUDGET_LEFT`` at that left edge of the log axis).
_BUDGET_EDGES = np.array([0.0, 0.01, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0, 1.5, 2.0, np.inf])
_BUDGET_MIN_POINTS = 10
_BUDGET_LEFT = 5e-3


def binned_errors(spread, errors, *, edges=_BUDGET_EDGES, min_points=_BUDGET_MIN_POINTS) -> np.ndarray:
    """Errors binned by in-cone spread: (k, 4) rows (median spread, median error, p90 error, count) of
    the bins of ``edges`` (px) that hold at least ``min_points`` points with a finite spread and error."""
    s, e = np.asarray(spread, dtype=np.float64), np.asarray(errors, dtype=np.float64)
    ok = np.isfinite(s) & np.isfinite(e)
    s, e = s[ok], e[ok]
    idx = np.digitize(s, edges[1:-1])
    rows = []
    for b in range(len(edges) - 1):
        sel = idx == b
        if sel.sum() >= min_points:
            rows.append((np.median(s[sel]), np.median(e[sel]), np.percentile(e[sel], 90), sel.sum()))
    return np.array(rows, dtype=np.float64).reshape(-1, 4)


def _crlb_quantile(noise: float, q: float) -> float:
    """The ``q`` quantile of the displacement error magnitude at the Cramér-Rao bound (a Rayleigh law)."""
    return scoring.cramer_rao_displacement(noise) * float(np.sqrt(-2.0 * np.log(1.0 - q)))


def _has_spread(scores) -> bool:
    return any(np.isfinite(sc["spread"]).any() for sc in scores)


def _budget_axes(ax, lo, hi, xmax):
    """Log axes of a budget panel: spread from ``_BUDGET_LEFT`` to ``xmax``, error ``lo``..``hi``; the
    table's bins (``scoring.SPREAD_BINS``) as dashed grey lines."""
    for _, edge, _ in scoring.SPREAD_BINS[1:]:
        ax.axvline(edge, color="0.7", ls="--", lw=0.6, zorder=0)
    ax.set_xscale("log")
    ax.set_xlim(_BUDGET_LEFT / 1.2, xmax)
    _log_axis(ax.yaxis, lo, hi)
    ax.set_ylim(lo, hi)
    ax.grid(True, which="major", alpha=0.3)


def _budget_legend(fig, methods, *, crlb=True, ncol=3):
    handles = [plt.Line2D([], [], marker=METHODS[m].marker if m in METHODS else "o", ms=3, **method_style(m))
               for m in methods]
    labels = [method_style(m)["label"] for m in methods]
    handles += [plt.Line2D([], [], color="0.3", marker="o", ms=3, lw=1.1), plt.Line2D([], [], color="0.3", lw=0.6)]
    labels += ["median (markers)", "90th percentile (thin)"]
    if crlb:
        handles += [plt.Line2D([], [], color="k", ls=":", lw=1.0), plt.Line2D([], [], color="0.5", ls=":", lw=0.8)]
        labels += ["Cramér-Rao bound, median", "Cramér-Rao bound, 90th pct."]
    fig.legend(handles, labels, loc="outside lower center", ncol=ncol, frameon=False)


def _bins_text() -> str:
    names = ", ".join(f"{n} < {hi:g}" if lo == 0 else (f"{n} {lo:g}-{hi:g}" if np.isfinite(hi) else f"{n} ≥ {lo:g}")
                      for n, lo, hi in scoring.SPREAD_BINS)
    return f"dashed: the bins of results.csv ({names} px)"


@_journal
def figure_budget(spec, folder, path, *, formats=None):
    """The error budget: displacement error against each dot's in-cone spread, per method and noise level.

    One column per noise level; rows: points whose true displacement is below and above the threshold
    (fig5's split: the spatial-resolution part); the Cramér-Rao bound's median and 90th percentile of the
    error magnitude as dotted lines (the noise part); the spread (``raytrace.pairfile.in_cone_spread_px``)
    on the x axis (the part of distorted dots). Each method's median error per spread bin with markers,
    its 90th percentile as a thin line. 7.2 in wide, text >= 7 pt.

    Returns the paths written, or None (and writes nothing) when no score holds a spread: pairs rendered
    before the ray covariance was recorded.
    """
    noises, methods = list(spec.noise_percent), list(spec.methods)
    scores = {(m, n): load_scores(spec, folder, m, n, fields=_BUDGET_FIELDS) for m in methods for n in noises}
    if not _has_spread(scores.values()):
        return None
    splits = (("below", "<"), ("above", "≥"))
    thresholds = np.concatenate([sc["threshold"] for sc in scores.values()])
    fig, axes = plt.subplots(2, len(noises), figsize=(TWO_COLUMNS_IN, 4.4), squeeze=False, sharex=True, sharey=True,
                             layout="constrained")
    ys, xmax = [], 2 * _BUDGET_LEFT
    for c, noise in enumerate(noises):
        for m in methods:
            sc = scores[(m, noise)]
            masks = split_masks(sc)
            for r, (split, _) in enumerate(splits):
                b = binned_errors(sc["spread"][masks[split]], sc["error"][masks[split]])
                _draw_binned(axes[r, c], b, m)
                ys.append(b[:, 1:3])
                xmax = max(xmax, float(b[:, 0].max()) * 1.3 if len(b) else xmax)
        if noise > 0:
            for r in range(2):
                axes[r, c].axhline(_crlb_quantile(noise, 0.5), color="k", ls=":", lw=1.0)
                axes[r, c].axhline(_crlb_quantile(noise, 0.9), color="0.5", ls=":", lw=0.8)
            ys.append(np.array([_crlb_quantile(noise, 0.5), _crlb_quantile(noise, 0.9)]))
        axes[0, c].set_title(f"noise {noise:g} %")
        axes[-1, c].set_xlabel("in-cone spread (px)")
    lo, hi = _log_limits(ys, low_quantile=0.0, margin=1.3)
    for ax in axes.ravel():
        _budget_axes(ax, lo, hi, xmax)
    for r, (_, sign) in enumerate(splits):
        axes[r, 0].set_ylabel(f"|ΔX| {sign} threshold\nerror (px)")
    _budget_legend(fig, methods, crlb=any(n > 0 for n in noises))
    _suptitle(
        fig,
        f"Error budget, campaign '{spec.name}': displacement error against the in-cone spread of each dot's "
        f"rays;\nthreshold {_threshold_text(thresholds)} (fig5's split); spread bins of ≥ {_BUDGET_MIN_POINTS} "
        f"points drawn;\n{_bins_text()}"
    )
    return save_figure(fig, path, formats=formats)


def _draw_binned(ax, b, method, *, color=None, p90=True):
    """One method's binned median (markers) and 90th percentile (thin line) on a budget panel."""
    style = method_style(method)
    if color is not None:
        style["color"] = color
    style.pop("label", None)
    x = np.maximum(b[:, 0], _BUDGET_LEFT)
    marker = METHODS[method].marker if method in METHODS else "o"
    ax.plot(x, b[:, 1], marker=marker, ms=3, lw=1.1, **style)
    if p90:
        ax.plot(x, b[:, 2], lw=0.6, alpha=0.8, **style)


@_journal
def sweep_budget_figure(points, path, *, param_label, formats=None):
    """The error budget of a sweep: median displacement error against the in-cone spread, one column per
    method (its line style), one row per noise level, one colour per sweep point (cividis, colour-blind safe).

    ``points``: ``(label, spec, folder)`` of each sweep point (label: its value(s) in words). The Cramér-Rao
    bound's median as a dotted line where the row has one noise level. Returns the paths written, or None
    (nothing written) when no point's scores hold a spread.
    """
    methods = list(dict.fromkeys(m for _, spec, _ in points for m in spec.methods))
    noise_swept = len({tuple(spec.noise_percent) for _, spec, _ in points}) > 1
    noises = [None] if noise_swept else list(points[0][1].noise_percent)
    scores = {}
    for k, (_, spec, folder) in enumerate(points):
        for m in spec.methods:
            for n in spec.noise_percent:
                scores[(k, m, None if noise_swept else n)] = load_scores(spec, folder, m, n, fields=_BUDGET_FIELDS)
    if not _has_spread(scores.values()):
        return None
    colors = plt.get_cmap("cividis")(np.linspace(0.0, 0.9, len(points)))
    fig, axes = plt.subplots(len(noises), len(methods), figsize=(TWO_COLUMNS_IN, 1.9 * len(noises) + 1.1),
                             squeeze=False, sharex=True, sharey=True, layout="constrained")
    ys, xmax = [], 2 * _BUDGET_LEFT
    for (k, m, n), sc in scores.items():
        b = binned_errors(sc["spread"], sc["error"])
        _draw_binned(axes[noises.index(n), methods.index(m)], b, m, color=colors[k], p90=False)
        ys.append(b[:, 1])
        xmax = max(xmax, float(b[:, 0].max()) * 1.3 if len(b) else xmax)
    for r, n in enumerate(noises):
        if n:
            for ax in axes[r]:
                ax.axhline(_crlb_quantile(n, 0.5), color="k", ls=":", lw=1.0)
            ys.append(np.array([_crlb_quantile(n, 0.5)]))
        axes[r, 0].set_ylabel(("" if n is None else f"noise {n:g} %\n") + "median error (px)")
    lo, hi = _log_limits(ys, low_quantile=0.0, margin=1.3)
    for ax in axes.ravel():
        _budget_axes(ax, lo, hi, xmax)
    for c, m in enumerate(methods):
        axes[0, c].set_title(textwrap.fill(method_style(m)["label"], max(12, int(62 / len(methods)))))
        axes[-1, c].set_xlabel("in-cone spread (px)")
    fig.legend([plt.Line2D([], [], color=colors[k], lw=1.1) for k in range(len(points))],
               [label for label, _, _ in points], title=param_label.replace(" (", "\n("),
               loc="outside right center", frameon=False)
    _suptitle(fig, f"Error budget of the sweep: median displacement error against the in-cone spread "
              f"(bins of ≥ {_BUDGET_MIN_POINTS} points);\ndotted: Cramér-Rao bound, median;\n{_bins_text()}")
    return save_figure(fig, path, formats=formats)


#: A campaign's figures: file stem (``campaign_figures.CAMPAIGN_FIGURES``) -> the function that draws it
#: (``f(spec, folder, path, *, formats=None)``).
CAMPAIGN_FIGURES = dict(zip(_CAMPAIGN_STEMS, (figure4, figure5, figure_density, figure_budget), strict=True))


def campaign_figure(stem: str, spec, folder, formats=None) -> str:
    """Draw the campaign figure ``stem`` (a key of ``CAMPAIGN_FIGURES``) into ``folder`` as each of
    ``formats`` (``FORMATS`` by default); return its stem path.

    One figure per call, so that a campaign can draw its figures side by side in worker processes, and
    one figure's formats too (each call draws the figure, and lays it out alike, for its own files).
    """
    path = Path(folder) / stem
    CAMPAIGN_FIGURES[stem](spec, folder, path, formats=formats)
    return str(path)


@_journal
def sweep_figure(rows, path, *, param, param2=None, param_label=None, param2_label=None, percentiles=(50, 90)):
    """Error percentiles (displacement, all points), yield, and the RMS density error relative to the
    density range (against the cone truth, when the rows hold it) against the swept parameter.

    One row of panels per noise level (one row in all when noise is swept); colour and marker per method
    (from the registry); with a second parameter, one line style per value of it. ``param_label`` and
    ``param2_label`` are the axis words with units (the parameter keys otherwise).
    """
    label1, label2 = param_label or param, param2_label or param2
    order = list(METHODS)
    methods = sorted(
        {r["method"] for r in rows}, key=lambda m: (m not in order, order.index(m) if m in order else 0, m)
    )
    by_noise = "noise" not in (param, param2)
    noises = sorted({r["noise_percent"] for r in rows}) if by_noise else [None]
    second = sorted({r.get("param2_value") for r in rows}, key=lambda v: (v is None, v))
    has_density = any(r["quantity"] == "density_cone_rel" for r in rows)
    ncols = len(percentiles) + 1 + has_density
    yc = len(percentiles)  # the yield column
    fig, axes = plt.subplots(
        len(noises), ncols, figsize=(TWO_COLUMNS_IN, 1.6 * len(noises) + 1.3), squeeze=False, layout="constrained"
    )
    dashes = ["-", "--", ":", "-.", (0, (5, 1, 1, 1, 1, 1))]
    for r, noise in enumerate(noises):
        for method in methods:
            style = method_style(method)
            for k, val2 in enumerate(second):
                sel = [
                    x
                    for x in rows
                    if x["method"] == method
                    and (noise is None or x["noise_percent"] == noise)
                    and x.get("param2_value") == val2
                    and x["split"] == "all"
                    and x["quantity"] == "displacement"
                ]
                sel.sort(key=lambda x: x["param_value"])
                xs = [x["param_value"] for x in sel]
                kw = {
                    "color": style.get("color"),
                    "marker": METHODS[method].marker if method in METHODS else "o",
                    "ls": dashes[k % len(dashes)] if val2 is not None else style.get("ls", "-"),
                    "ms": 3,
                }
                for c, p in enumerate(percentiles):
                    axes[r, c].plot(xs, [x[f"p{p}"] for x in sel], **kw)
                axes[r, yc].plot(xs, [x["yield"] for x in sel], **kw)
                if has_density:
                    dens = [
                        x
                        for x in rows
                        if x["method"] == method
                        and x["quantity"] == "density_cone_rel"
                        and (noise is None or x["noise_percent"] == noise)
                        and x.get("param2_value") == val2
                    ]
                    dens.sort(key=lambda x: x["param_value"])
                    axes[r, -1].plot([x["param_value"] for x in dens], [x.get("rms", np.nan) for x in dens], **kw)
        for c in range(len(percentiles)):
            lines = [ln.get_ydata() for ln in axes[r, c].get_lines()]
            lo, hi = _log_limits(lines, low_quantile=0.0, margin=1.1)
            _log_axis(axes[r, c].yaxis, lo, hi)
            axes[r, c].set_ylim(lo, hi)
            axes[r, c].set_ylabel("error (px)")
        axes[r, yc].set_ylim(*yield_limits([ln.get_ydata() for ln in axes[r, yc].get_lines()]))
        axes[r, yc].set_ylabel("fraction measured")
        if has_density:
            lo, hi = _log_limits([ln.get_ydata() for ln in axes[r, -1].get_lines()], low_quantile=0.0, margin=1.1)
            _log_axis(axes[r, -1].yaxis, lo, hi)
            axes[r, -1].set_ylim(lo, hi)
            axes[r, -1].set_ylabel("rms error / range")
        if noise is not None:
            axes[r, 0].set_ylabel(f"noise {noise:g} %\n" + axes[r, 0].get_ylabel())
        for ax in axes[r]:
            ax.set_xlabel(label1)
            ax.grid(True, alpha=0.3)
    for c, p in enumerate(percentiles):
        axes[0, c].set_title(f"displacement error,\n{'median' if p == 50 else f'{p}th percentile'}")
    axes[0, yc].set_title("yield")
    if has_density:
        axes[0, -1].set_title("density error\nvs the cone truth")
    marker = {m: METHODS[m].marker if m in METHODS else "o" for m in methods}
    if param2 is None:
        handles = [plt.Line2D([], [], marker=marker[m], **method_style(m)) for m in methods]
    else:  # the line style tells the second parameter's value: a legend of its own, at the right
        handles = [plt.Line2D([], [], color=method_style(m).get("color"), marker=marker[m]) for m in methods]
        fig.legend(
            [plt.Line2D([], [], color="k", ls=dashes[k % len(dashes)]) for k in range(len(second))],
            [f"{v:g}" for v in second],
            title=label2.replace(" (", "\n("),
            loc="outside right center",
            frameon=False,
        )
    fig.legend(
        handles,
        [method_style(m)["label"] for m in methods],
        loc="outside lower center",
        ncol=min(len(methods), 3),
        frameon=False,
    )
    what = label1 if param2 is None else f"{label1} and {label2}"
    extra = "; density error after integration" if has_density else ""
    _suptitle(fig, f"Sweep of {what}: displacement error over all scored points, and yield{extra}")
    return save_figure(fig, path)


def yield_limits(values) -> tuple[float, float]:
    """Limits of a yield axis (a fraction, at most 1): from a round 0.05 step below the smallest value (at
    least 0.01 below it) to just above 1, so that a yield of 0.9992 to 1 is not stretched over the axis."""
    v = np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in values] or [np.zeros(0)])
    v = v[np.isfinite(v)]
    low = float(v.min()) if len(v) else 0.0
    lo = max(0.0, np.floor((min(low, 1.0) - 0.01) * 20.0) / 20.0)
    return lo, 1.0 + 0.05 * (1.0 - lo)
