"""The multigrid pass sequence of :func:`correlation.correlate_pair`, written once.

:func:`pass_schedule` lays the passes out: one :class:`PassStep` per iteration of every pass, with its
window grid, the nodes its vectors sit on and the tests it applies. :func:`run_passes` walks the
schedule and writes the method's order of steps once: predictor and deformation, correlation, peak
fit and significance, normalised median test and confirmation, isolated vectors, filling. Each step
is done by an *engine*, chosen by :meth:`CorrelationSettings.uses_warp`:

- the host engine (:class:`correlation.host_pass.HostEngine`): NumPy/SciPy arrays, the image
  deformation on the settings' Warp device;
- the Warp engine (:class:`correlation.device_pass._Plan`): every step enqueues Warp launches on
  device arrays prepared once per image shape, so the walk is a fixed sequence of launches with no wait
  for the host, which a CUDA graph records and replays.

An engine has the methods of :func:`run_passes`' Notes; what they return (windows, planes, fields,
flags) is the engine's own (NumPy arrays, or Warp arrays it owns) and the walk only hands it on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

from .rules import SAMPLING_OFFSET, judges_correlation
from .windows import WindowGrid, window_grid

__all__ = ["Measured", "PassStep", "pass_schedule", "run_passes"]


@dataclass(frozen=True, eq=False)
class PassStep:
    """One iteration of one pass of the multigrid schedule.

    Attributes
    ----------
    index : int
        Position in the schedule.
    pass_index, iteration : int
        The pass, and the iteration within it.
    size : int
        Window size (px).
    grid : WindowGrid
        The pass's window grid.
    node : tuple of two 1-D float arrays
        Row and column coordinates of the vectors: the window centres for the plain correlation of the
        first step, moved by ``rules.SAMPLING_OFFSET`` for the deformed ones.
    deform : bool
        The images are deformed by the latest field (every step but the first).
    first_deformed : bool
        The first step that deforms: the image interpolant is made before it.
    first_of_pass : bool
        The first iteration of its pass.
    use_coarse : bool
        Vectors are tested against the previous pass's field (``DISAGREE``): passes after the first.
    confirm : bool
        Median-test rejections confirmed by the previous iteration are kept (iterations after the
        first of a pass, ``confirm_tolerance > 0``).
    judges_correlation : bool
        ``min_correlation`` applies (:func:`correlation.rules.judges_correlation`).
    last : bool
        The final step, whose vectors are returned.
    """

    index: int
    pass_index: int
    iteration: int
    size: int
    grid: WindowGrid
    node: tuple
    deform: bool
    first_deformed: bool
    first_of_pass: bool
    use_coarse: bool
    confirm: bool
    judges_correlation: bool
    last: bool


class Measured(NamedTuple):
    """One step's measured field before the median test, as its engine holds it.

    ``u``, ``v``: predictor plus the peak's offset; ``ratio``: peak ratio; ``coef``: peak correlation
    coefficient (NaN with RPC on the host); ``flags``: :class:`VectorFlag` bits of the tests before the
    median test.
    """

    u: Any
    v: Any
    ratio: Any
    coef: Any
    flags: Any


def pass_schedule(shape, settings):
    """The steps of :func:`correlation.correlate_pair` for images of ``shape`` and ``settings``.

    Parameters
    ----------
    shape : tuple of int
        Image shape (H, W).
    settings : CorrelationSettings

    Returns
    -------
    tuple of PassStep
        One per iteration of every pass, in order.

    Examples
    --------
    >>> from synthbos import CorrelationSettings
    >>> steps = pass_schedule((64, 64), CorrelationSettings(window_sizes=(32, 16), iterations=(2, 1)))
    >>> [(s.size, s.deform, s.confirm, s.judges_correlation) for s in steps]
    [(32, False, False, True), (32, True, True, False), (16, True, False, True)]
    """
    steps = []
    q = SAMPLING_OFFSET
    sizes, overlaps, iterations = settings.window_sizes, settings.overlaps, settings.iterations
    for pass_index, (size, overlap, n_iter) in enumerate(zip(sizes, overlaps, iterations, strict=True)):
        grid = window_grid(shape, size, overlap)
        for iteration in range(n_iter):
            deform = bool(steps)
            steps.append(
                PassStep(
                    index=len(steps),
                    pass_index=pass_index,
                    iteration=iteration,
                    size=size,
                    grid=grid,
                    node=(grid.yc + q, grid.xc + q) if deform else (grid.yc, grid.xc),
                    deform=deform,
                    first_deformed=len(steps) == 1,
                    first_of_pass=iteration == 0,
                    use_coarse=pass_index > 0,
                    confirm=iteration > 0 and settings.confirm_tolerance > 0,
                    judges_correlation=judges_correlation(settings, pass_index, iteration),
                    last=pass_index == len(sizes) - 1 and iteration == n_iter - 1,
                )
            )
    return tuple(steps)


def run_passes(engine, steps):
    """Walk the multigrid schedule ``steps`` with ``engine`` doing each step.

    Parameters
    ----------
    engine : object
        The host or the Warp engine (module docstring), with the methods below.
    steps : sequence of PassStep
        :func:`pass_schedule`.

    Returns
    -------
    field : (u, v)
        The last step's filled field, on its nodes.
    measured : Measured
        The last step's measured field (peak ratio and correlation coefficient of the result).
    flags
        The last step's :class:`VectorFlag` bits.

    Notes
    -----
    Every iteration (Scarano 2002): the latest field (None at the first step) is interpolated to the
    pixels and nodes, both images are deformed symmetrically by half of it, the windows are correlated,
    the peak is fitted and the vectors are tested (significance, agreement with the coarser pass), then
    the normalised median test (with confirmation by the previous iteration of the pass), the isolated
    vectors, and the filling of the rejected ones give the field of the next iteration. The engine's
    methods:

    - ``interpolant()``: the images' interpolant, before the first deformation;
    - ``windows(step, previous, field)`` -> ``(windows, predictor)``: the step's windows, of the images
      deformed by ``field`` (on ``previous.node``) unless it is the first step, and the predictor at
      ``step.node`` (zero at the first step);
    - ``correlate(step, windows)`` -> planes;
    - ``fit_peaks(step, planes, predictor, coarse)`` -> :class:`Measured`; ``coarse`` is the
      predictor of the first iteration of the pass when ``step.use_coarse``, else None;
    - ``median_test(step, measured, raw)`` -> flags; ``raw`` is the previous iteration's
      :class:`Measured` when ``step.confirm``, else None;
    - ``isolated_test(step, flags)`` -> flags;
    - ``fill(step, measured, flags)`` -> field ``(u, v)``.
    """
    previous = field = coarse = raw = None
    for step in steps:
        if step.first_deformed:
            engine.interpolant()
        windows, predictor = engine.windows(step, previous, field)
        if step.first_of_pass:
            coarse = predictor if step.use_coarse else None
            raw = None
        planes = engine.correlate(step, windows)
        measured = engine.fit_peaks(step, planes, predictor, coarse)
        flags = engine.median_test(step, measured, raw if step.confirm else None)
        flags = engine.isolated_test(step, flags)
        field = engine.fill(step, measured, flags)
        previous, raw = step, measured
    return field, measured, flags

