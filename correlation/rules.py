"""Rules of the multigrid correlation that its host loop (:mod:`correlation.multigrid`) and its device
engine (:mod:`correlation.device_pass`) both apply: written once, here, below both."""

from __future__ import annotations

__all__ = ["CONFIRM_CORRELATION", "EDGE_MARGIN", "SAMPLING_OFFSET", "WINDOW_SIZES", "judges_correlation"]

#: Deformed windows are sampled on pixel grids moved by this much (px, along x and y). The shift error
#: of a symmetric interpolation kernel at fractional position f, b(f), is odd about 0 and about 1/2;
#: the two images are sampled at fractions m - d/2 and m + d/2 about the midpoint m, so the
#: residual error is b(m + d/2) - b(m - d/2). For m = 0 (pixel centres) the odd harmonics of b add
#: up (0.01 px at d = 0.5 px for 3 px dots and cubic B-splines); for m = 1/4 they cancel,
#: sin(2 pi k (1/4 + d/2)) = sin(2 pi k (1/4 - d/2)) for odd k, leaving the much smaller even ones.
#: The vectors of deformed iterations are therefore located at window centre + 1/4 px.
SAMPLING_OFFSET = 0.25

#: A vector that fails the median test is confirmed (kept) only if its peak correlation coefficient is
#: at least this fraction of its valid neighbours' median (and the previous iteration measured it alike).
CONFIRM_CORRELATION = 0.7

#: The default passes' window sizes (px): 32 x 32 px windows, then 16 x 16 px.
WINDOW_SIZES = (32, 16)

#: Deformed pixels sampled closer than this to the image edge (px) are left out of the correlation.
EDGE_MARGIN = 2.0


def judges_correlation(settings, pass_index, iteration):
    """Whether iteration ``iteration`` of pass ``pass_index`` applies ``min_correlation``.

    The plain correlation (the first iteration of the first pass: nothing deformed, the windows as
    they are, where chance peaks of unrelated windows reach 0.4 and more) and the final iteration (the
    vectors returned) do. The deformed iterations in between do not: a window over a strong
    gradient (a shear layer, a front in turbulence) correlates poorly until the deformation follows
    the field, and failing it there replaces it by its neighbours' values, so that the next
    deformation cannot follow the field either. It still has to pass the peak ratio, the agreement
    with the coarser pass and the normalised median test. On the SQG pairs of
    ``benchmarks/bench_openpiv.py`` this lowers the RMS error over all vectors by 4-18 % (SQG 00001
    1.13 -> 1.09 px, 00003 1.14 -> 1.03, 00004 0.85 -> 0.75).
    """
    last = pass_index == len(settings.window_sizes) - 1 and iteration == settings.iterations[-1] - 1
    return (pass_index == 0 and iteration == 0) or last
