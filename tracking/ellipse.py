"""The elliptical moment step: host code shared by ``track_pair`` and the stacked tracker.

After the first-moment step (:func:`tracking.dotfit.moment_shifts`) has said which dots are distorted,
each gradient-image dot that moves gets an elliptical Gaussian model, fitted against the image less its
neighbours' models, and moves instead to the first moment of the share of the light these models give it
(:mod:`tracking.ellipse_kernels`; the NumPy reference is ``tracking.reference.moment_shifts_numpy`` with
``ellipse=True``). The symmetric shares hand a distorted dot's light spread along the flow's gradient
to its neighbours; the elliptical shares follow it.
"""

from __future__ import annotations

import warp as wp

from .ellipse_kernels import (
    ellipse_finish,
    ellipse_fit_kernel,
    ellipse_moment_kernel,
    ellipse_render,
    ellipse_start,
    flag_set,
    list_flagged,
)
from .settings import ELLIPSE_MOMENT_ITERATIONS, ELLIPSE_SWEEPS

__all__ = ["ellipse_step", "flagged_rows", "redraw_is_cheaper"]


def ellipse_step(gradients, models, scales, params, frame, partner, prof, shift, *, half, max_shift, device=None):
    """Replace the first-moment shifts of the gradient-image dots that move by their elliptical moments.

    Parameters
    ----------
    gradients : Warp float64 array (B, H, W)
        The gradient image of each pair; row i's image is ``gradients[frame[i] // 2]``.
    models : Warp int64 array, flat ``[frames, H, W]``
        The fixed-point model image (units of ``1 / scales[f]`` in frame f) of every row's symmetric model at
        ``params``, as ``render_dots_kernel`` drew it with profiles ``prof``: overwritten.
    scales : Warp float64 array (frames,)
        Its fixed-point units per intensity, per frame.
    params : Warp float64 array (N, 5)
        Fitted parameters of every row (frames ``f``: image ``f % 2`` of pair ``f // 2``).
    frame, partner : Warp int32 arrays (N,)
        Frame of each row and the row of its partner in the other image (-1 for none).
    prof : Warp float64 array (N, 6, 2 half + 1)
        The rows' profiles on their stamps.
    shift : Warp vec3d array (N,)
        The first-moment step's shifts and codes (``moment_shift``): the active rows' shifts are replaced
        where their elliptical moment is usable (``ellipse_finish``), the codes kept.
    half : int, keyword-only
        Stamp half-width (the fit's ``render_half``).
    max_shift : float, keyword-only
        Largest shift taken (px).
    device : str or None, keyword-only
        Warp device.

    Notes
    -----
    ``ELLIPSE_SWEEPS`` block-Jacobi Gauss-Newton sweeps fit the elliptical models (every active row at
    once, against the others' models of the sweep before; the rows that do not move keep their symmetric
    models), then ``ELLIPSE_MOMENT_ITERATIONS`` times each model moves to the first moment of its share of
    the light, the model image drawn again in between. Nothing is launched past ``ellipse_start`` where no
    row moves. Between two steps the moving rows' models are taken out again by drawing them with the
    opposite sign (the model image is fixed-point: the others' image comes back to the bit) where their
    stamps cover less than an eighth of the model images (:func:`redraw_is_cheaper`; a GPU stack's few
    moving dots), else the others' image is copied back.
    """
    rows = params.shape[0]
    active = wp.empty(rows, dtype=wp.int32, device=device)
    ell = wp.empty((rows, 6), dtype=wp.float64, device=device)
    wp.launch(ellipse_start, dim=rows, inputs=[params, frame, partner, shift, active, ell], device=device)
    moving = _prefix_sum(active, device)[2]
    if not moving:
        return
    height, width = gradients.shape[1], gradients.shape[2]

    def draw(symmetric, sign, at=ell):
        inputs = [params, frame, active, at, prof, symmetric, sign, half, scales, height, width, models]
        wp.launch(ellipse_render, dim=rows, inputs=inputs, device=device)

    draw(1, -1)  # the moving rows' symmetric models out: the model image of the others
    redraw = redraw_is_cheaper(moving, half, models.size)
    others = None if redraw else wp.clone(models)
    drawn = wp.empty_like(ell) if redraw else None  # the parameters the moving rows were drawn with
    step_inputs = [gradients, models, scales, params, frame, partner, active, half, ell]
    steps = [ellipse_fit_kernel] * ELLIPSE_SWEEPS + [ellipse_moment_kernel] * ELLIPSE_MOMENT_ITERATIONS
    for k, kernel in enumerate(steps):
        if k and not redraw:
            wp.copy(models, others)
        draw(0, 1)
        if redraw and k + 1 < len(steps):
            wp.copy(drawn, ell)
        wp.launch(kernel, dim=rows, inputs=step_inputs, device=device)
        if redraw and k + 1 < len(steps):
            draw(0, -1, drawn)  # out again, as drawn
    wp.launch(ellipse_finish, dim=rows, inputs=[params, active, ell, float(max_shift), shift], device=device)


def flagged_rows(flags, frame, device):
    """The rows whose int32 ``flags`` are set, in order, and their ``frame``s: two (M,) int32 Warp arrays
    on ``device``, listed there (a prefix sum; the host reads only their count, not the N flags).

    Examples
    --------
    >>> import numpy as np
    >>> flags = wp.array(np.array([0, 1, 1, 0, 2], dtype=np.int32), device="cpu")
    >>> frame = wp.array(np.array([0, 0, 1, 1, 3], dtype=np.int32), device="cpu")
    >>> rows, frames = flagged_rows(flags, frame, "cpu")
    >>> rows.numpy().tolist(), frames.numpy().tolist()
    ([1, 2, 4], [0, 1, 3])
    """
    set_, start, count = _prefix_sum(flags, device)
    rows = wp.empty(count, dtype=wp.int32, device=device)
    frames = wp.empty(count, dtype=wp.int32, device=device)
    if count:
        wp.launch(list_flagged, dim=flags.shape[0], inputs=[set_, start, frame, rows, frames], device=device)
    return rows, frames


def _prefix_sum(flags, device):
    """``(set, start, count)``: 1 where an int32 flag is set, the exclusive prefix sum of that (each set
    row's place in the list of set rows), and how many are set (the host reads that one number)."""
    n = flags.shape[0]
    set_ = wp.empty(n, dtype=wp.int32, device=device)
    start = wp.empty(n, dtype=wp.int32, device=device)
    if n == 0:
        return set_, start, 0
    wp.launch(flag_set, dim=n, inputs=[flags, set_], device=device)
    wp.utils.array_scan(set_, start, inclusive=False)
    return set_, start, int(start[n - 1 :].numpy()[0] + set_[n - 1 :].numpy()[0])


def redraw_is_cheaper(rows, half, pixels):
    """Whether taking ``rows`` stamps of half-size ``half`` out of a model image of ``pixels`` pixels by
    drawing them again with the opposite sign costs less than copying the image back: their stamps cover
    less than an eighth of it.

    Examples
    --------
    >>> redraw_is_cheaper(100, 6, 2 * 512 * 512), redraw_is_cheaper(5000, 6, 2 * 512 * 512)
    (True, False)
    """
    return 8 * rows * (2 * half + 1) ** 2 < pixels
