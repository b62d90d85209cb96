"""Advice after ``synthbos process``: when most points failed, say why, from what failed, and what to change.

The flags of the failed points tell the causes apart. For correlation (``correlation.VectorFlag``):

* windows that fail the peak test with a peak correlation below ``min_correlation``: the two images do
  not correlate there (another pattern, misaligned, swapped, or regions without dots);
* windows that fail the peak test with a good correlation but a peak ratio near 1: the second peak is as
  high as the first, so the pattern repeats itself (a regular dot grid): ``pattern = "periodic"`` where the
  correlation settings have a ``pattern`` (else ``peak_ratio_min = 1.0``), or tracking with a dots prior;
* a pattern the correlation took as periodic: displacements beyond half its pitch;
* windows whose peak lay on the edge of the correlation plane: displacements past a quarter of the first
  window: larger first windows;
* windows that disagree with the coarser pass: the final windows are too small for the field.

For tracking (``tracking.DotStatus``): prior positions outside the image, dots not found in the
reference image (diameter, polarity, prior), dots not paired in the gradient image (``max_displacement``),
and images that do not correlate.
"""

from __future__ import annotations

import numpy as np
from synthbos.correlation.multigrid import VectorFlag
from synthbos.tracking import DotStatus

from .registry import DOTS, GRID

__all__ = ["EQUAL_PEAKS", "MOST", "failure_advice", "failure_reason"]

#: "Most points failed": more than this fraction of the unmasked points.
MOST = 0.5
#: A peak ratio this close to 1 means two equal correlation peaks: a pattern that repeats itself.
EQUAL_PEAKS = 1.02


def failure_advice(result, *, kind: str, where: str = "") -> str | None:
    """One note for the user when most of a result's unmasked points failed, else None.

    Parameters
    ----------
    result : MethodResult
        A processed pair (``registry.MethodResult``) with its ``counts`` and, for the built-in methods, the
        flag columns of its table (``flags`` for a grid, ``status`` for dots).
    kind : str
        The method's kind (``registry.GRID``, ``DOTS``, ...).
    where : str
        The result file, named in the note (how to see the failures: ``synthbos show-result``).

    Returns
    -------
    str or None
        ``note: most points failed (N of M; ...): `` and :func:`failure_reason`.
    """
    c = result.counts or {}
    unmasked = c.get("total", 0) - c.get("masked", 0)
    if not c or unmasked <= 0 or c.get("failed", 0) <= MOST * unmasked:
        return None
    show = f"; synthbos show-result {where} -o FIG.png shows where" if where else ""
    return f"note: most points failed ({c['failed']} of {unmasked}{show}): {failure_reason(result, kind=kind)}"


def failure_reason(result, *, kind: str) -> str:
    """Why the failed points of a result failed, from their flags, and what to change (one clause)."""
    table = result.table or {}
    if kind == GRID and "flags" in table:
        return _grid_advice(table, result.settings or {})
    if kind == DOTS and "status" in table:
        return _dots_advice(table, result.settings or {})
    return "see the method's flags in the result file"


def _median(values, sel):
    v = np.asarray(values, dtype=np.float64).ravel()[sel]
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("nan")


def _windows(sizes, first):
    return ",".join(str(int(w)) for w in [first, *sizes])


def _grid_advice(table, settings) -> str:
    """Why most correlation windows failed, from their flag bits, and what to change."""
    flags = np.asarray(table["flags"], dtype=np.int64).ravel()
    failed = ((flags & int(VectorFlag.MASKED)) == 0) & ((flags & int(VectorFlag.PEAK | VectorFlag.BORDER
                                                                  | VectorFlag.DISAGREE | VectorFlag.ISOLATED)) != 0)
    n = max(int(failed.sum()), 1)
    peak = failed & ((flags & int(VectorFlag.PEAK)) != 0)
    border = failed & ((flags & int(VectorFlag.BORDER)) != 0)
    disagree = failed & ((flags & int(VectorFlag.DISAGREE)) != 0)
    sizes = [int(w) for w in np.atleast_1d(settings.get("window_sizes", (32, 16)))]
    min_corr = float(settings.get("min_correlation", np.nan))
    ratio_min = float(settings.get("peak_ratio_min", np.nan))
    prior = "track the dots with a prior (--method tracking-cc --dots DOTS.csv, from synthbos calibrate)"
    if settings.get("pattern") == "periodic":
        return ("the pattern was taken as periodic (settings.pattern), so the displacements must stay below half "
                f"its pitch in the first pass and the windows must hold whole periods; beyond that, {prior}")
    if peak.sum() >= MOST * n:
        corr = _median(table.get("correlation", np.full(flags.size, np.nan)), peak)
        ratio = _median(table.get("peak_ratio", np.full(flags.size, np.nan)), peak)
        if corr < min_corr:
            return (f"the two images do not correlate in {int(peak.sum())} windows (median peak correlation "
                    f"{corr:.2f}, below min_correlation {min_corr:g}): check that they show the same pattern, "
                    "aligned and in the right order (--reference, then --gradient); leave regions without dots "
                    f"out with --mask; larger windows hold more dots (--windows {_windows(sizes, 2 * sizes[0])})")
        if ratio < EQUAL_PEAKS:
            fix = ('pattern = "periodic"' if "pattern" in settings else "peak_ratio_min = 1.0")
            return (f"in {int(peak.sum())} windows the second correlation peak is as high as the first (median "
                    f"peak ratio {ratio:.4f}, peak_ratio_min {ratio_min:g}) with a good correlation ({corr:.2f}): "
                    "the pattern repeats itself, as a regular dot grid does, so every dot spacing gives a peak; "
                    f"set {fix} in the [correlation] table of a --settings file, or {prior}")
        return (f"{int(peak.sum())} windows had no significant correlation peak (median peak ratio {ratio:.3g}, "
                f"peak_ratio_min {ratio_min:g}; median correlation {corr:.2f}): larger windows hold more dots "
                f"(--windows {_windows(sizes, 2 * sizes[0])}); check the dot density and the image contrast")
    if border.sum() >= MOST * n:
        return (f"in {int(border.sum())} windows the correlation peak lay on the edge of the correlation plane: "
                f"the displacements reach past a quarter of the first window ({sizes[0]} px); start with larger "
                f"windows: --windows {_windows(sizes, 2 * sizes[0])}")
    if disagree.sum() >= MOST * n:
        larger = _windows(sizes[:-1] or sizes, 2 * sizes[0])
        return (f"{int(disagree.sum())} windows disagree with the coarser pass by more than max_disagreement "
                f"({settings.get('max_disagreement', '?')} of the window): the {sizes[-1]} px final windows hold "
                f"too few dots for this field; end with larger windows (--windows {larger})")
    return ("the failures have mixed causes (flag bits in the result's /flags, named in its flag_bits attribute); "
            f"larger windows (--windows {_windows(sizes, 2 * sizes[0])}) often help")


def _dots_advice(table, settings) -> str:
    """Why most dots failed, from their status bits, and what to change."""
    status = np.asarray(table["status"], dtype=np.int64).ravel()
    masked = (status & int(DotStatus.MASKED)) != 0
    failed = ~masked & ((status & int(DotStatus.MATCHED)) == 0)
    n = max(int(failed.sum()), 1)

    def has(bit, sel=failed):
        return sel & ((status & int(bit)) != 0)

    outside = has(DotStatus.OUTSIDE_IMAGE)
    not_found = failed & ~outside & ~has(DotStatus.FOUND_REFERENCE)
    weak = has(DotStatus.PREDICTOR_WEAK)
    unpaired = failed & ~outside & ~not_found & ~weak
    diameter = settings.get("diameter")
    d_text = f"{diameter:g} px" if isinstance(diameter, int | float) else "measured from the images"
    if outside.sum() >= MOST * n:
        return (f"the prior puts {int(outside.sum())} dots outside the image: is --dots the prior of these "
                "images, in pixels (x to the right, y down, from 0 at the first pixel's centre)?")
    if not_found.sum() >= MOST * n:
        return (f"{int(not_found.sum())} dots were not found in the reference image: check the dot diameter "
                f"(--diameter, now {d_text}), the polarity (--invert true for dark dots on a bright background) "
                "and that the prior (--dots) belongs to this image")
    if weak.sum() >= MOST * n:
        return (f"the images do not correlate around {int(weak.sum())} dots (predictor_min_correlation "
                f"{settings.get('predictor_min_correlation', '?')}): check that they show the same pattern, "
                "aligned and in the right order (--reference, then --gradient)")
    if unpaired.sum() >= MOST * n:
        return (f"{int(unpaired.sum())} dots found in the reference image were not paired in the gradient image: "
                "the displacements may be larger than --max-displacement (now "
                f"{settings.get('max_displacement', '?')} px); raise it, or check the dot diameter (--diameter, "
                f"now {d_text})")
    return ("the failures have mixed causes (status bits in the result's /dots/status, named in its flag_bits "
            "attribute)")
