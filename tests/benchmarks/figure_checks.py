"""What a journal asks of a figure, measured on the figure as saved (used by the figure tests)."""

import itertools

import matplotlib.pyplot as plt
from matplotlib.backends.backend_agg import FigureCanvasAgg
from synthbos.benchmarks import figures


def _boxes_overlap(a, b, tol=1.0) -> bool:
    return min(a.x1, b.x1) - max(a.x0, b.x0) > tol and min(a.y1, b.y1) - max(a.y0, b.y0) > tol


def _unused_tick_labels(fig) -> set:
    """The ids of the tick labels that an axis holds but does not draw (ticks outside its view)."""
    held, drawn = set(), set()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            for tick in [*axis.majorTicks, *axis.minorTicks]:
                held |= {id(tick.label1), id(tick.label2)}
            for tick in axis._update_ticks():
                drawn |= {id(tick.label1), id(tick.label2)}
    return held - drawn


def assert_journal_figure(fig):
    """What a journal asks of a figure, measured on the figure as saved: one or two columns wide, no text
    under 7 pt or beyond the figure's edge, no legend over an axes' data area, the title clear of every
    panel and of every other text."""
    assert round(fig.get_figwidth(), 3) in (figures.ONE_COLUMN_IN, figures.TWO_COLUMNS_IN)
    canvas = FigureCanvasAgg(fig)  # a saved figure is closed: draw it again on a canvas of its own
    canvas.draw()
    r = canvas.get_renderer()
    page = fig.bbox
    unused = _unused_tick_labels(fig)
    texts = [t for t in fig.findobj(plt.Text) if t.get_text().strip() and t.get_visible() and id(t) not in unused]
    for t in texts:
        assert t.get_fontsize() >= 7.0, (t.get_text(), t.get_fontsize())
        box = t.get_window_extent(r)
        assert box.x0 >= page.x0 - 1 and box.x1 <= page.x1 + 1 and box.y0 >= page.y0 - 1 and box.y1 <= page.y1 + 1, (
            t.get_text(), box, page)
    for ax in fig.axes:  # the tick labels of an axis apart
        for axis in (ax.xaxis, ax.yaxis):
            boxes = [t.label1.get_window_extent(r) for t in axis._update_ticks()
                     if t.label1.get_visible() and t.label1.get_text()]
            for a, b in itertools.pairwise(boxes):
                assert not _boxes_overlap(a, b, tol=0.0), ("tick labels overlap", ax.get_title(), ax.get_xlabel())
    labels = [t for ax in fig.axes for t in (ax.xaxis.label, ax.yaxis.label, ax.title, ax._left_title,
                                              ax._right_title) if t.get_visible() and t.get_text()]
    boxes = [(t.get_text(), t.get_window_extent(r)) for t in labels]
    for (ta, a), (tb, b) in itertools.combinations(boxes, 2):  # axis labels and titles apart
        assert not _boxes_overlap(a, b), ("labels overlap", ta, tb)
    data_axes = [ax for ax in fig.axes if getattr(ax, "_colorbar", None) is None]
    legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    for leg in legends:
        box = leg.get_window_extent(r)
        for ax in data_axes:
            assert not _boxes_overlap(box, ax.bbox), ("legend over the data of", ax.get_title())
    title = fig._suptitle
    if title is not None:
        tbox = title.get_window_extent(r)
        for ax in fig.axes:
            assert not _boxes_overlap(tbox, ax.get_tightbbox(r)), ("title over", ax.get_title(), ax.get_label())
