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
)
from .settings import ELLIPSE_MOMENT_ITERATIONS, ELLIPSE_SWEEPS

__all__ = ["ellipse_step"]


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
    row moves.
    """
    rows = params.shape[0]
    active = wp.empty(rows, dtype=wp.int32, device=device)
    ell = wp.empty((rows, 6), dtype=wp.float64, device=device)
    wp.launch(ellipse_start, dim=rows, inputs=[params, frame, partner, shift, active, ell], device=device)
    if not active.numpy().any():
        return
    height, width = gradients.shape[1], gradients.shape[2]

    def draw(symmetric, sign):
        inputs = [params, frame, active, ell, prof, symmetric, sign, half, scales, height, width, models]
        wp.launch(ellipse_render, dim=rows, inputs=inputs, device=device)

    draw(1, -1)  # the moving rows' symmetric models out: the model image of the others
    others = wp.clone(models)
    step_inputs = [gradients, models, scales, params, frame, partner, active, half, ell]
    for kernel, times in ((ellipse_fit_kernel, ELLIPSE_SWEEPS), (ellipse_moment_kernel, ELLIPSE_MOMENT_ITERATIONS)):
        for _ in range(times):
            wp.copy(models, others)
            draw(0, 1)
            wp.launch(kernel, dim=rows, inputs=step_inputs, device=device)
    wp.launch(ellipse_finish, dim=rows, inputs=[params, active, ell, float(max_shift), shift], device=device)
