"""The public method API: what a processing method declares, what its run returns, and how both are checked.

A method (built in, or from an installed package through the ``synthbos.methods`` entry-point group,
see ``benchmarks.plugins``) is one :class:`Method`: its name, its kind, its settings dataclass, its
run function and how figures draw it. Its run takes the two images and returns a
:class:`MethodResult` of its kind; :func:`grid_result`, :func:`dots_result` and :func:`dense_result`
build one from plain arrays. The scoring knows each kind (``items.score_result``):

``grid``
    vectors on a regular grid of window centres (correlation); the truth is interpolated to them.
``dots``
    vectors at scattered points. A method that uses the prior (tracking) returns one row per prior
    dot, in its order, and each is scored against that dot's own displacement; any other dots method
    is scored like a grid, against the dot displacements interpolated to its points.
``dense``
    a displacement at every pixel (optical flow); sampled bilinearly at the rendered dots and scored there.

A method written outside synthbos needs only this module::

    from dataclasses import dataclass
    from synthbos.benchmarks.method_api import GRID, Method, grid_result

    @dataclass(frozen=True)
    class MySettings:
        window: int = 32

    def run(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
        ...
        return grid_result("mine", x, y, u, v, settings=settings)

    METHOD = Method("mine", GRID, MySettings, run, label="my method", color="#56B4E9", linestyle="--",
                    marker="x")
"""

from __future__ import annotations

import dataclasses
import inspect
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from synthbos import SynthbosError

__all__ = ["DENSE", "DOTS", "GRID", "KINDS", "Method", "MethodResult", "check_method", "check_result",
           "dense_result", "dots_result", "grid_result", "settings_dict"]

GRID = "grid"  # a vector on a regular grid of window centres
DOTS = "dots"  # a vector at each of scattered points (tracked dots)
DENSE = "dense"  # a vector at every pixel of the reference image
KINDS = (GRID, DOTS, DENSE)

#: What a method may be called: it names files (``scores/..._{method}.npz``) and command-line choices.
NAME_PATTERN = re.compile(r"[a-z0-9][a-z0-9_-]{0,39}")


@dataclass
class MethodResult:
    """What a method measured: points (px), displacements (px), and method-specific extras.

    For a ``dense`` result the points are every pixel centre of the reference image, row after row,
    and ``grid_shape`` is the image's (H, W).
    """

    method: str
    xy: np.ndarray  # (N, 2) measurement points (window centres, reference dot positions, pixel centres)
    uv: np.ndarray  # (N, 2) displacements, NaN where nothing was measured
    grid_shape: tuple | None  # (ny, nx) for grid and dense methods, None for scattered dots
    table: dict  # every array the method returned, for the result file
    settings: dict
    valid: np.ndarray | None = None  # (N,) bool: a measured, unflagged vector
    counts: dict | None = None  # measured, replaced, failed, masked, total


@dataclass(frozen=True)
class Method:
    """One processing method.

    Attributes
    ----------
    name : str
        What ``--method`` and the campaign call it: lower-case letters, digits, ``-`` and ``_``.
    kind : {"grid", "dots", "dense"}
        Vectors on a grid of windows, at scattered dots, or at every pixel (decides how results are
        stored and scored).
    settings_class : type
        The frozen dataclass of the method's settings (its fields are the keys users may set; its
        ``__post_init__`` may refuse values by raising ``ValueError``).
    run : callable
        ``run(reference, gradient, *, prior_xy, settings, device, mask) -> MethodResult``; ``mask`` is a
        bool image, True on pixels to leave out, or None.
    label, color, linestyle, marker : str
        How figures draw it (any matplotlib colour, line style and marker).
    uses_prior : bool
        Whether the method takes predicted reference-image dot positions.
    settings_key : str
        The table of a process configuration (and the campaign spec's field) holding its settings;
        methods that share a settings class share it. Empty (the default): the method's name, which it
        then holds.
    make_settings : callable or None
        Builds the settings from overrides (default: ``settings_class``): how one algorithm is registered
        a second time with another procedure, e.g. the paper's exact tracking procedure
        (``TrackingSettings.paper``).
    in_default_campaign : bool
        Whether ``paper``, ``sweep`` and ``regress`` run it unless methods are named (never for a plugin).
    device_resident : bool
        Whether its run keeps the images on a CUDA processing device from upload to result, with no
        host work between its kernels. A campaign that processes on a GPU runs such methods in the
        process that drives the GPU and the others, whose host code would hold that process up, in
        its worker processes (on the same device): ``scheduling.run_pipeline``.
    kernels : tuple of str
        The modules of the Warp kernels its run launches: a campaign's worker processes that will run
        it load them as they start.
    cpu_kernels : tuple of str or None
        The modules its run launches when it processes on the CPU, where that is fewer than ``kernels``
        (a Warp path taken on CUDA devices only); None: ``kernels``. A CPU campaign builds them before
        its work starts (``scheduling.run_items``), so list none the run may not launch there.
    prepare : callable or None
        ``prepare(reference, settings, device) -> settings``: the settings with what the run would read
        from the reference image to choose its procedure already read (the correlation: a periodic or
        a random pattern), so that the run does not read it again. A campaign calls it in the thread
        that draws the noisy images, beside the device's work; the results are the same. None: the
        run reads nothing of the kind.
    requires : tuple of str
        Modules its run imports that synthbos does not install by default (``synthbos methods`` tells
        whether they are there).
    source : str
        Where it comes from: ``"synthbos 0.1.0"``, or the distribution and version of a plugin (set when
        it is registered).
    """

    name: str
    kind: str
    settings_class: type
    run: Callable
    label: str
    color: str
    linestyle: str | tuple
    marker: str
    uses_prior: bool = False
    settings_key: str = ""
    make_settings: Callable | None = None
    in_default_campaign: bool = True
    device_resident: bool = False
    kernels: tuple[str, ...] = ()
    cpu_kernels: tuple[str, ...] | None = None
    prepare: Callable | None = None
    requires: tuple[str, ...] = ()
    source: str = ""

    def __post_init__(self):
        if not self.settings_key:
            object.__setattr__(self, "settings_key", self.name)

    def kernels_on(self, device) -> tuple[str, ...]:
        """The modules of the Warp kernels its run launches on ``device`` ("cpu", "cuda:0"; None: the CPU)."""
        on_cpu = device is None or not str(device).startswith("cuda")
        return self.cpu_kernels if on_cpu and self.cpu_kernels is not None else self.kernels

    def settings(self, overrides: dict | None = None):
        """The settings object with ``overrides`` (field -> value) applied; unknown fields are refused."""
        overrides = dict(overrides or {})
        known = {f for f in self.settings_class.__dataclass_fields__}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise SynthbosError(f"unknown {self.name} setting(s) {', '.join(unknown)}; "
                                f"known: {', '.join(sorted(known))}")
        try:
            return (self.make_settings or self.settings_class)(**overrides)
        except (TypeError, ValueError) as err:
            raise SynthbosError(f"{self.name} settings: {err}") from None


def settings_dict(settings) -> dict:
    """A settings object as a plain dict (for result files and campaign specs)."""
    if settings is None:
        return {}
    if hasattr(settings, "as_dict"):
        return settings.as_dict()
    if dataclasses.is_dataclass(settings):
        return dataclasses.asdict(settings)
    return dict(settings)


def check_method(method, *, taken=()) -> None:
    """Refuse a malformed :class:`Method` with one line saying what is wrong.

    Checks the name (pattern, not in ``taken``), the kind, that the settings class is a dataclass whose
    defaults build, that ``run`` accepts the keyword arguments the harness passes, and that the colour,
    line style and marker are ones matplotlib draws.
    """
    from matplotlib.colors import is_color_like
    from matplotlib.lines import Line2D

    if not isinstance(method, Method):
        raise SynthbosError(f"not a synthbos Method but {type(method).__name__}")
    if not NAME_PATTERN.fullmatch(method.name):
        raise SynthbosError(f"method name {method.name!r} must match {NAME_PATTERN.pattern}")
    if method.name in taken:
        raise SynthbosError(f"method name {method.name!r} is taken")
    if method.kind not in KINDS:
        raise SynthbosError(f"kind {method.kind!r} is not one of {', '.join(KINDS)}")
    if not dataclasses.is_dataclass(method.settings_class):
        raise SynthbosError(f"settings_class {method.settings_class!r} is not a dataclass")
    method.settings()  # the defaults build
    if not callable(method.run):
        raise SynthbosError("run is not callable")
    try:
        inspect.signature(method.run).bind(None, None, prior_xy=None, settings=None, device=None, mask=None)
    except (TypeError, ValueError) as err:
        raise SynthbosError(f"run(reference, gradient, *, prior_xy, settings, device, mask) does not fit: {err}"
                            ) from None
    if not is_color_like(method.color):
        raise SynthbosError(f"color {method.color!r} is not a matplotlib colour")
    try:
        Line2D([], [], linestyle=method.linestyle, marker=method.marker)
    except (TypeError, ValueError) as err:
        raise SynthbosError(f"line style or marker: {err}") from None


def check_result(method: Method, result, image_shape, *, prior_count=None) -> MethodResult:
    """Check a run's result against its method's kind; return it, or raise one line naming the fault.

    ``prior_count``: the number of prior dots the run was given; a dots method that uses the prior
    returns one row per prior dot.
    """
    what = f"method {method.name!r} returned"
    if not isinstance(result, MethodResult):
        raise SynthbosError(f"{what} {type(result).__name__}, not a MethodResult")
    xy, uv = np.asarray(result.xy), np.asarray(result.uv)
    if xy.ndim != 2 or xy.shape[1:] != (2,) or uv.shape != xy.shape:
        raise SynthbosError(f"{what} points {xy.shape} and displacements {uv.shape}; both must be (N, 2)")
    if result.valid is not None and np.shape(result.valid) != (len(xy),):
        raise SynthbosError(f"{what} valid of shape {np.shape(result.valid)}; expected ({len(xy)},)")
    shape = result.grid_shape
    if method.kind == DOTS and shape is not None:
        raise SynthbosError(f"{what} a grid_shape {shape}; a dots result has none")
    if method.kind in (GRID, DENSE) and (shape is None or len(shape) != 2 or int(np.prod(shape)) != len(xy)):
        raise SynthbosError(f"{what} grid_shape {shape} for {len(xy)} points")
    if method.kind == DOTS and method.uses_prior and prior_count is not None and len(xy) != prior_count:
        raise SynthbosError(f"{what} {len(xy)} dots for {prior_count} prior dots; one row per prior dot")
    if method.kind == DENSE and tuple(shape) != tuple(image_shape):
        raise SynthbosError(f"{what} a dense field of shape {tuple(shape)}; the images are {tuple(image_shape)}")
    if not np.isfinite(xy).all():
        raise SynthbosError(f"{what} non-finite points")
    if result.method != method.name:
        raise SynthbosError(f"{what} a result named {result.method!r}")
    return result


def _as_valid(valid, uv):
    ok = np.all(np.isfinite(uv), axis=1)
    return ok if valid is None else ok & np.asarray(valid, bool).ravel()


def _counts(valid) -> dict:
    return {"measured": int(valid.sum()), "replaced": 0, "failed": int((~valid).sum()), "masked": 0,
            "total": len(valid)}


def grid_result(method: str, x, y, u, v, *, valid=None, settings=None, table=None, counts=None) -> MethodResult:
    """A ``grid`` result from 2-D arrays ``x``, ``y`` (window centres, px) and ``u``, ``v`` (px; NaN = none).

    ``table`` adds arrays to the result file (``x``, ``y``, ``u``, ``v`` and ``valid`` are written anyway).
    """
    x, y, u, v = (np.asarray(a, dtype=np.float64) for a in (x, y, u, v))
    if not (x.ndim == 2 and x.shape == y.shape == u.shape == v.shape):
        shapes = [a.shape for a in (x, y, u, v)]
        raise SynthbosError(f"{method}: grid arrays must be 2-D and of one shape, got {shapes}")
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    ok = _as_valid(valid, uv)
    return MethodResult(method, xy, uv, tuple(u.shape), {"x": x, "y": y, "u": u, "v": v, **(table or {})},
                        settings_dict(settings), ok, counts or _counts(ok))


def dots_result(method: str, x, y, u, v, *, valid=None, settings=None, table=None, counts=None) -> MethodResult:
    """A ``dots`` result from 1-D arrays: reference positions ``x``, ``y`` and displacements ``u``, ``v`` (px)."""
    x, y, u, v = (np.asarray(a, dtype=np.float64).ravel() for a in (x, y, u, v))
    if not (len(x) == len(y) == len(u) == len(v)):
        raise SynthbosError(f"{method}: dot arrays differ in length {[len(a) for a in (x, y, u, v)]}")
    uv = np.stack([u, v], axis=1)
    ok = _as_valid(valid, uv)
    return MethodResult(method, np.stack([x, y], axis=1), uv, None, {"x": x, "y": y, **(table or {})},
                        settings_dict(settings), ok, counts or _counts(ok))


def dense_result(method: str, u, v, *, valid=None, settings=None, table=None, counts=None) -> MethodResult:
    """A ``dense`` result from (H, W) displacement images ``u`` (along x, columns) and ``v`` (along y, rows).

    ``u[i, j]`` is the displacement of the reference image's pixel centre (x, y) = (j, i).
    """
    u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
    if u.ndim != 2 or u.shape != v.shape:
        raise SynthbosError(f"{method}: u and v must be images of one shape, got {u.shape} and {v.shape}")
    y, x = np.mgrid[0:u.shape[0], 0:u.shape[1]].astype(np.float64)
    return grid_result(method, x, y, u, v, valid=valid, settings=settings, table=table, counts=counts)
