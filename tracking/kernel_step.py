"""The shared-kernel step: host code shared by ``track_pair`` and the stacked tracker.

After the elliptical step (:func:`tracking.ellipse.ellipse_step`), every distorted dot gets a
non-parametric ray-landing kernel fitted to the pixels about it and shared there by its neighbours (the
dots near it keep their elliptical prior), and it moves to the first moment of the share of the light its
kernel model gets
(:mod:`tracking.kernel_step_kernels`; the NumPy reference is ``tracking.reference.moment_shifts_numpy``
with ``kernel=True``). Which dots take the result is still the first-moment step's gate.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .ellipse import flagged_rows, redraw_is_cheaper
from .ellipse_kernels import ellipse_render
from .kernel_step_kernels import (
    fit_column,
    fit_rows_normal,
    fit_rows_one_thread,
    fit_rows_ridge,
    fit_rows_setup,
    fit_rows_solve,
    kernel_accumulate,
    kernel_finish,
    kernel_frames,
    kernel_hold,
    kernel_moment,
    kernel_points,
    kernel_render,
    kernel_reweigh,
    kernel_rows,
    kernel_start,
    not_taking_part,
    prior_fit,
    prior_start,
    row_points,
    vec_taps,
)
from .settings import (
    ELLIPSE_SWEEPS,
    KERNEL_FITS,
    KERNEL_FLUX_SWEEPS,
    KERNEL_ITERATIONS,
    KERNEL_MAX_NEIGHBOURS,
    KERNEL_REACH_PX,
    KERNEL_TAPS,
    KERNEL_WINDOW_HALF,
)

__all__ = ["kernel_step"]

#: Rows fitted per launch (their scratch is ~104 kB each; on a GPU at most, :func:`chunk_rows`).
CHUNK_ROWS = {"cpu": 512, "cuda": 65536}
#: Frames lie this far apart along the hash grid's z axis.
Z_STEP = 4.0 * (KERNEL_REACH_PX + 1.0)


def kernel_step(refs, grads, models, scales, params, frame, partner, live, prof, shift, *, half, max_shift, fit=True,
                record=None, device=None):  # fmt: skip
    """Replace the shifts of the moving dots by their shared-kernel moments.

    Parameters
    ----------
    refs, grads : Warp float64 arrays (B, H, W)
        The reference and gradient image of each pair (frame ``f``: image ``f % 2`` of pair ``f // 2``).
    models : Warp int64 array, flat ``[frames, H, W]``
        Scratch for the fixed-point model images (units of ``1 / scales[f]`` in frame f): overwritten.
    scales : Warp float64 array (frames,)
        Fixed-point units per intensity, per frame.
    params : Warp float64 array (N, 5)
        Fitted parameters of every row.
    frame, partner, live : Warp int32 arrays (N,)
        Frame of each row, the row of its partner in the other image (-1 for none), and whether it was fitted.
    prof : Warp float64 array (N, 6, 2 half + 1)
        The rows' profiles on their stamps (``render_dots_kernel``): the rows that do not take part are
        drawn with their symmetric models.
    shift : Warp vec3d array (N,)
        The earlier steps' shifts and codes: the moving rows' shifts are replaced where their kernel
        moment is usable (``kernel_finish``), the codes kept.
    half : int, keyword-only
        Stamp half-width of the models and moments (the fit's ``render_half``).
    max_shift : float, keyword-only
        Largest shift taken (px).
    fit : bool, keyword-only
        Fit the kernels; False leaves each at its elliptical prior (``TrackingSettings.distortion`` "flux").
    record : dict, optional, keyword-only
        Receives ``rows`` (the rows that took part), ``kernel`` (their last kernels, (R, T^2), index
        ``b T + a`` for the y tap b and the x tap a) and ``position`` (their last positions, (R, 2)).
    device : str or None, keyword-only
        Warp device.

    Notes
    -----
    Every live row within ``KERNEL_REACH_PX`` of a moving row of its frame takes part (``kernel_rows``: the
    moving dots' neighbours share their light). Their prior is the elliptical fit of all of them together
    (``ELLIPSE_SWEEPS`` sweeps of ``ellipse_fit_step``); then ``KERNEL_ITERATIONS`` times: in the first
    ``KERNEL_FITS``, every distorted row's kernel fit (``fit_rows_setup`` and an engine, chunked; the others keep their
    prior), every row's kernel model drawn (``kernel_render``) with its
    reference partner's flux, the shares held to that flux (``KERNEL_FLUX_SWEEPS`` sweeps of ``kernel_hold``,
    each row's multiplier in the shares, and ``kernel_reweigh``, the stamps redrawn with the new multipliers
    in one pass) and every row moved to
    its moment (``kernel_moment``). Nothing past ``kernel_frames`` runs where no row moves.
    """
    n = params.shape[0]
    height, width = refs.shape[1], refs.shape[2]
    frames = scales.shape[0]
    busy = wp.zeros(frames, dtype=wp.int32, device=device)
    wp.launch(kernel_frames, dim=n, inputs=[shift, partner, live, frame, busy], device=device)
    if not busy.numpy().any():
        return
    near = stack_grid(frames, height, width, device)
    points = wp.empty(n, dtype=wp.vec3, device=device)
    wp.launch(row_points, dim=n, inputs=[params, frame, live, Z_STEP, points], device=device)
    near.build(points, KERNEL_REACH_PX + 0.5)
    part = wp.empty(n, dtype=wp.int32, device=device)
    wp.launch(kernel_rows, dim=n, inputs=[near.id, Z_STEP, params, shift, partner, live, frame, busy, part],
              device=device)  # fmt: skip
    rows, frames_of_rows = flagged_rows(part, frame, device)  # listed on the device
    m = rows.shape[0]
    # the model image of the live rows of the busy frames that do not take part: their symmetric models
    others = wp.empty(n, dtype=wp.int32, device=device)
    wp.launch(not_taking_part, dim=n, inputs=[live, part, frame, busy, others], device=device)
    models.zero_()
    wp.launch(ellipse_render, dim=n, inputs=[params, frame, others, params, prof, 1, 1, half, scales, height, width,
                                             models], device=device)  # fmt: skip
    # the taking-part rows are drawn in and taken out again after each use: by drawing them with the opposite
    # sign (fixed point: to the bit) where that is cheaper than copying the others' image back
    redraw = redraw_is_cheaper(m, half, frames * height * width)
    base = None if redraw else wp.clone(models)
    ell = _prior_fit(refs, grads, models, base, scales, params, frame, partner, part, rows, half, device)
    state = _State(m, half, device)
    start = [params, frame, partner, shift, rows, ell, state.pos, state.flux, state.sigma, state.background,
             state.prior, state.kern]  # fmt: skip
    wp.launch(kernel_start, dim=m, inputs=start, device=device)
    if fit:  # the kernel fit's frame levels and scratch
        level = _frame_levels(state.background.numpy(), frames_of_rows.numpy(), frames, device)
        grid = stack_grid(frames, height, width, device)
        scratch = _Scratch(m, device)
    if base is not None:
        wp.copy(models, base)  # the others

    def accumulate(sign):
        if sign < 0 and not redraw:
            wp.copy(models, base)
            return
        inputs = [rows, frame, state.pos, half, state.stamp, state.alpha, scales, height, width, models, sign]
        wp.launch(kernel_accumulate, dim=m, inputs=inputs, device=device)

    for iteration in range(KERNEL_ITERATIONS):
        if fit and iteration < KERNEL_FITS:
            _fit_kernels(refs, grads, rows, frame, level, state, scratch, grid, shift, device)  # swaps state.kern
        draw = [state.pos, state.flux, state.sigma, state.kern, half, state.stamp_prof, state.stamp]
        wp.launch(kernel_render, dim=m, inputs=draw, device=device)
        accumulate(1)
        # The shares held to the reference flux: each sweep, the multipliers from one buffer into the other
        # (kernel_hold), then the stamps redrawn with them, out with the old and in with the new in one pass
        # (kernel_reweigh). The two ways of each launch are recorded once and replayed: Warp packs no
        # arguments again (240 launches per stack).
        sweeps = []
        for old, new in ((state.alpha, state.spare_alpha), (state.spare_alpha, state.alpha)):
            hold = [refs, grads, models, scales, params, rows, frame, half, state.stamp, state.background, state.pos,
                    state.kern, old, new]  # fmt: skip
            reweigh = [rows, frame, state.pos, half, state.stamp, old, new, scales, height, width, models]
            sweeps.append([wp.launch(k, dim=m, inputs=a, device=device, record_cmd=True)
                           for k, a in ((kernel_hold, hold), (kernel_reweigh, reweigh))])  # fmt: skip
        for sweep in range(KERNEL_FLUX_SWEEPS if m else 0):  # (Warp records no launch of no threads)
            for launch in sweeps[sweep % 2]:
                launch.launch()
        if KERNEL_FLUX_SWEEPS % 2:
            state.alpha, state.spare_alpha = state.spare_alpha, state.alpha
        moment = [refs, grads, models, scales, params, rows, frame, half, state.stamp, state.background, state.pos,
                  state.alpha, state.failed, state.spare_pos]  # fmt: skip
        wp.launch(kernel_moment, dim=m, inputs=moment, device=device)
        accumulate(-1)  # where it was drawn
        state.pos, state.spare_pos = state.spare_pos, state.pos
    wp.launch(kernel_finish, dim=m, inputs=[params, partner, rows, state.pos, state.failed, float(max_shift), shift],
              device=device)  # fmt: skip
    if record is not None:
        record.update(rows=rows.numpy(), kernel=state.kern.numpy(), position=state.pos.numpy())


class _State:
    """The step's per-row state (compact rows) and the render's scratch."""

    def __init__(self, m, half, device):
        taps2 = KERNEL_TAPS * KERNEL_TAPS
        n = 2 * half + 1
        self.pos = wp.empty(m, dtype=wp.vec2d, device=device)
        self.spare_pos = wp.empty(m, dtype=wp.vec2d, device=device)
        self.flux = wp.empty(m, dtype=wp.float64, device=device)
        self.sigma = wp.empty(m, dtype=wp.float64, device=device)
        self.background = wp.empty(m, dtype=wp.float64, device=device)
        self.prior = wp.empty((m, taps2), dtype=wp.float64, device=device)
        self.kern = wp.empty((m, taps2), dtype=wp.float64, device=device)
        self.spare = wp.empty((m, taps2), dtype=wp.float64, device=device)
        self.failed = wp.zeros(m, dtype=wp.int32, device=device)
        self.alpha = wp.full(m, 1.0, dtype=wp.float64, device=device)  # the shares' multipliers (kernel_hold)
        self.spare_alpha = wp.empty(m, dtype=wp.float64, device=device)
        self.stamp = wp.empty((m, n, n), dtype=wp.float64, device=device)
        self.stamp_prof = wp.empty((m, 2 * KERNEL_TAPS, n), dtype=wp.float64, device=device)


class _Scratch:
    """The kernel fit's per-thread scratch for one chunk of rows: neighbours, their window profiles, the
    normal matrix and the right side."""

    def __init__(self, m, device):
        taps, window = KERNEL_TAPS, 2 * KERNEL_WINDOW_HALF + 1
        self.chunk = min(m, chunk_rows(device))
        self.nbr = wp.empty((self.chunk, KERNEL_MAX_NEIGHBOURS), dtype=wp.int32, device=device)
        self.prof = wp.empty((self.chunk, 2 * KERNEL_MAX_NEIGHBOURS * taps, window), dtype=wp.float64, device=device)
        self.normal = wp.empty((self.chunk, taps * taps, taps * taps), dtype=wp.float64, device=device)
        self.rhs = wp.empty((self.chunk, taps * taps), dtype=wp.float64, device=device)
        self.weights = wp.empty((self.chunk, 2, window), dtype=wp.float64, device=device)
        self.diag = wp.empty((self.chunk, taps * taps), dtype=wp.float64, device=device)
        self.count = wp.empty(self.chunk, dtype=wp.int32, device=device)
        self.failed = wp.empty(self.chunk, dtype=wp.int32, device=device)
        self.points = wp.empty(m, dtype=wp.vec3, device=device)
        self._pairs = 0  # the CPU engine's factor scratch (``factors``), grown as needed
        self._factors = None

    def factors(self, n):
        """The CPU engine's factor scratch for the first n rows of the chunk (``fit_rows_setup`` counted their
        neighbours, ``count (count + 1) / 2`` pairs a row): each row's first pair, and the pairs' rows and
        columns of X and their Y (``normal_equations``)."""
        count = self.count.numpy()[:n].astype(np.int64)
        pairs = count * (count + 1) // 2
        first = np.concatenate([[0], np.cumsum(pairs)[:-1]]).astype(np.int32)
        device = self.count.device
        if self._factors is None or self._pairs < pairs.sum():
            self._pairs = int(pairs.sum())
            self._factors = (wp.empty((self._pairs, KERNEL_TAPS), dtype=vec_taps, device=device),
                             wp.empty((self._pairs, KERNEL_TAPS), dtype=vec_taps, device=device),
                             wp.empty((self._pairs, KERNEL_TAPS**2), dtype=wp.float64, device=device))  # fmt: skip
        return (wp.array(first, dtype=wp.int32, device=device), *self._factors)


def stack_grid(frames: int, height: int, width: int, device) -> wp.HashGrid:
    """A hash grid for the rows of ``frames`` frames of ``height`` x ``width`` px (frame f at z = f Z_STEP),
    with a cell for every place of every frame up to ``MAX_GRID_CELLS`` cells: a fixed 128 x 128 x 64 grid
    folded a stack's frames onto each other along z (400 pairs: a query looked through the rows of some 37
    frames to find those of its own), and on a pair held 1 M cells for some 6,000.

    Examples
    --------
    >>> grid_dims(2, 512, 512)  # a pair: its two frames
    (55, 55, 10)
    """
    return wp.HashGrid(*grid_dims(frames, height, width), device=device)


#: The most cells :func:`stack_grid` holds (two int32 each): past it, frames share cells again.
MAX_GRID_CELLS = 1 << 25


def grid_dims(frames: int, height: int, width: int) -> tuple[int, int, int]:
    """:func:`stack_grid`'s cells along x, y and z (cells ``KERNEL_REACH_PX + 0.5`` wide, the queries' radius).

    Examples
    --------
    >>> grid_dims(800, 512, 512)
    (55, 55, 3370)
    """
    cell = KERNEL_REACH_PX + 0.5
    nx, ny = int(width // cell) + 2, int(height // cell) + 2
    nz = int(frames * Z_STEP // cell) + 2
    return nx, ny, max(1, min(nz, MAX_GRID_CELLS // (nx * ny)))


def chunk_rows(device) -> int:
    """Rows fitted per launch of the kernel fit: on the CPU ``CHUNK_ROWS["cpu"]``; on a GPU as many as an eighth
    of its free memory holds (some 104 kB of scratch a row), within ``CHUNK_ROWS["cuda"]``: each thread
    solves its row alone, so a GPU needs many of them at once (a stack of 8 zero-noise 512-px pairs on an
    H100: 1.27 s at 8192 rows a launch, 0.55 s at 32768, 0.39 s at 65536).

    Examples
    --------
    >>> chunk_rows("cpu")
    512
    """
    d = wp.get_device(device)
    if not d.is_cuda:
        return CHUNK_ROWS["cpu"]
    taps2, window = KERNEL_TAPS**2, 2 * KERNEL_WINDOW_HALF + 1
    floats = taps2 * taps2 + taps2 + 2 * KERNEL_MAX_NEIGHBOURS * KERNEL_TAPS * window
    row_bytes = 8 * floats + 4 * KERNEL_MAX_NEIGHBOURS
    return int(np.clip(d.free_memory // (8 * row_bytes), CHUNK_ROWS["cpu"], CHUNK_ROWS["cuda"]))


def _prior_fit(refs, grads, models, base, scales, params, frame, partner, part, rows, half, device):
    """The elliptical fit of every taking-part row at once (both images), from the symmetric fit, against
    the model image of the others (``models``; ``base`` its copy, or None where the taking-part rows are
    taken out by drawing them with the opposite sign, the image left as it came): ``(N, 6)`` Warp array of
    ``(F, x0, y0, r1, r2, r3)`` (rows not taking part left unset)."""
    n, m = params.shape[0], rows.shape[0]
    height, width = refs.shape[1], refs.shape[2]
    ell = wp.zeros((n, 6), dtype=wp.float64, device=device)
    drawn = wp.empty_like(ell) if base is None else None  # the parameters the rows were drawn with
    unused = wp.empty((1, 1, 1), dtype=wp.float64, device=device)  # the symmetric models' profiles: not drawn

    def draw(at, sign):
        inputs = [params, frame, part, at, unused, 0, sign, half, scales, height, width, models]
        wp.launch(ellipse_render, dim=n, inputs=inputs, device=device)

    wp.launch(prior_start, dim=m, inputs=[params, rows, ell], device=device)
    for _ in range(ELLIPSE_SWEEPS):
        if base is not None:
            wp.copy(models, base)
        draw(ell, 1)
        if drawn is not None:
            wp.copy(drawn, ell)
        wp.launch(prior_fit, dim=m, inputs=[refs, grads, models, scales, params, frame, partner, rows, half, ell],
                  device=device)  # fmt: skip
        if drawn is not None:
            draw(drawn, -1)
    return ell


def _frame_levels(background, frames_of_rows, frames, device):
    """Per frame, the median of its taking-part rows' backgrounds (0 for a frame without any)."""
    level = np.zeros(frames)
    order = np.lexsort((background, frames_of_rows))
    f, v = frames_of_rows[order], background[order]
    first = np.searchsorted(f, np.arange(frames))
    count = np.bincount(f, minlength=frames)
    has = count > 0
    lo, hi = first[has] + (count[has] - 1) // 2, first[has] + count[has] // 2
    level[has] = 0.5 * (v[lo] + v[hi])
    return wp.array(level, dtype=wp.float64, device=device)


def column_engine(device) -> bool:
    """Whether the kernel fit takes a GPU's engine: the normal matrix a thread per row of it, the Cholesky
    factorisation a launch per column (``fit_rows_setup`` .. ``fit_rows_solve``); on the CPU one thread
    fits a row alone (``fit_rows_one_thread``). A row's solve is some 0.25 M multiply-adds in sequence: one GPU
    thread each leaves the GPU waiting on memory. The two give the same kernels to rounding.

    Examples
    --------
    >>> column_engine("cpu")
    False
    """
    return wp.get_device(device).is_cuda


def _fit_kernels(refs, grads, rows, frame, level, state, scratch, grid, shift, device):
    """Every distorted row's kernel fit, in chunks (:func:`column_engine`); the new kernels replace the old
    (the grid is rebuilt on the rows' positions)."""
    m, chunk, sc = rows.shape[0], scratch.chunk, scratch
    wp.launch(kernel_points, dim=m, inputs=[state.pos, rows, frame, Z_STEP, sc.points], device=device)
    grid.build(sc.points, KERNEL_REACH_PX + 0.5)
    columns = column_engine(device)
    taps2 = KERNEL_TAPS * KERNEL_TAPS
    for start in range(0, m, chunk):
        n = min(chunk, m - start)
        wp.launch(fit_rows_setup, dim=n, inputs=[start, grid.id, Z_STEP, refs, grads, rows, frame, level, state.pos,
                                                 state.flux, state.sigma, state.kern, sc.nbr, sc.prof, sc.rhs, shift,
                                                 sc.weights, sc.count], device=device)  # fmt: skip
        if not columns:
            wp.launch(fit_rows_one_thread, dim=n, inputs=[start, sc.count, sc.prof, sc.weights, sc.normal, sc.rhs,
                                                          sc.diag, state.prior, state.kern, state.spare,
                                                          *sc.factors(n)], device=device)  # fmt: skip
            continue
        wp.launch(fit_rows_normal, dim=(n, taps2), inputs=[sc.prof, sc.weights, sc.count, sc.normal], device=device)
        wp.launch(fit_rows_ridge, dim=n, inputs=[start, sc.count, sc.normal, sc.rhs, state.prior, sc.failed],
                  device=device)  # fmt: skip
        column = wp.launch(fit_column, dim=(n, taps2), inputs=[0, sc.count, sc.normal, sc.diag, sc.failed],
                           device=device, record_cmd=True)  # fmt: skip
        for j in range(taps2):  # recorded once, replayed column after column
            column.set_param_at_index(0, j)
            column.launch()
        wp.launch(fit_rows_solve, dim=n, inputs=[start, sc.count, sc.normal, sc.diag, sc.rhs, sc.failed, state.kern,
                                                 state.spare], device=device)  # fmt: skip
    state.kern, state.spare = state.spare, state.kern
