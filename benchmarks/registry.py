"""The method registry: one table maps each processing method's name to everything the harness needs.

The command line (``--method``), ``synthbos process``, the campaign, the scoring and the figures read
this table and never switch on a method's name. Adding a method takes its algorithm module and one
``Method`` entry in ``BUILT_IN`` below (its ``run`` adapter turns the algorithm's output into a
:class:`MethodResult`); the public method API (``Method``, ``MethodResult``, the kinds, the result
builders and checks) lives in ``method_api``. Installed packages add methods through the
``synthbos.methods`` entry points (``plugins``): ``METHODS`` holds the built-in methods, then theirs,
each loaded when first asked for; a plugin's run is checked (``method_api.check_result``).

Styles use the Okabe-Ito colour-blind-safe palette, with a distinct line style and marker per method,
so the curves stay apart in grey-scale print too.
"""

from __future__ import annotations

import hashlib
import importlib.util
import threading
from collections.abc import Mapping
from dataclasses import replace

import numpy as np
from synthbos.correlation import CorrelationSettings, correlate_pair
from synthbos.correlation.multigrid import pattern_settings
from synthbos.tracking import DotStatus, TrackingSettings, is_valid, track_pair
from synthbos.tracking.identify import kernels_measure

import synthbos
from synthbos import SynthbosError

from .method_api import DENSE, DOTS, GRID, KINDS, Method, MethodResult, check_result, settings_dict
from .openpiv_method import OpenPIVSettings, run_openpiv
from .optical_flow import OpticalFlowSettings, run_optical_flow
from .plugins import load_plugins

__all__ = ["BUILT_IN", "DENSE", "DOTS", "GRID", "KINDS", "METHODS", "STACK_CPU_KERNELS", "STACK_KERNELS", "Method",
           "MethodResult",
           "check_available", "correlation_result", "default_methods", "forget_plugins", "forget_shared_results",
           "get_method", "method_names", "methods_table", "missing_modules", "settings_dict", "stack_settings",
           "stacked_result", "tracking_result"]


def _run_correlation(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
    return correlation_result(correlate_pair(reference, gradient, settings=_on(settings, device), mask=mask))


def _prepare_correlation(reference, settings, device=None):
    """The correlation's settings with the pattern read from ``reference`` (``pattern_settings``)."""
    return pattern_settings(reference, _on(settings, device))


def _on(settings, device):
    """Correlation ``settings`` on the processing ``device``, which travels in them (None: as they are)."""
    return settings if device is None else replace(settings or CorrelationSettings(), device=str(device))


def correlation_result(res) -> MethodResult:
    """A :func:`synthbos.correlation.correlate_pair` result as the ``correlation`` method's ``MethodResult``:
    valid where the vector is finite and its flags are 0."""
    xy = np.stack([res.x.ravel(), res.y.ravel()], axis=1).astype(np.float64)
    uv = np.stack([res.u.ravel(), res.v.ravel()], axis=1).astype(np.float64)
    table = {"x": res.x, "y": res.y, "u": res.u, "v": res.v, "flags": res.flags, "peak_ratio": res.peak_ratio,
             "correlation": res.correlation}
    valid = np.all(np.isfinite(uv), axis=1) & (np.asarray(res.flags).ravel() == 0)
    return MethodResult("correlation", xy, uv, tuple(res.u.shape), table, settings_dict(res.settings), valid,
                        counts=res.counts())


class _LastCall:
    """The last call of a function and its result, by the contents of its array arguments.

    ``tracking`` and ``tracking-cc`` read two columns of one ``track_pair`` table; a campaign that
    processes a pair's items one after another (``scheduling.run_pipeline``) runs ``track_pair`` once
    for both. The key holds a digest of every array's bytes, shape and dtype, so equal inputs, not
    merely the same objects, hit; the result is handed out as a copy.
    """

    def __init__(self, fn):
        self.fn = fn
        self.key = None
        self.value = None
        self.lock = threading.Lock()

    @staticmethod
    def _digest(value):
        if value is None:
            return None
        a = np.ascontiguousarray(value)
        return a.shape, a.dtype.str, hashlib.blake2b(a.view(np.uint8).ravel(), digest_size=16).digest()

    def __call__(self, reference, gradient, *, prior_xy, settings, device, mask):
        key = (*map(self._digest, (reference, gradient, prior_xy, mask)), settings, str(device))
        with self.lock:
            if key != self.key:
                self.key, self.value = None, None  # no stale result if the call fails
                self.value = self.fn(reference, gradient, prior_xy=prior_xy, settings=settings, device=device,
                                     mask=mask)
                self.key = key
            return self.value.copy()


    def forget(self) -> None:
        with self.lock:
            self.key, self.value = None, None


_track_pair = _LastCall(track_pair)


def forget_shared_results() -> None:
    """Drop the remembered ``track_pair`` result (benchmarks time each method on its own)."""
    _track_pair.forget()


def tracking_result(tab, *, name="tracking", columns=("u", "v"), settings=None) -> MethodResult:
    """A :func:`synthbos.tracking.track_pair` table as the ``MethodResult`` of the tracking method ``name``,
    whose displacement is the table's ``columns``; rows flagged MASKED are NaN and not valid."""
    xy = np.stack([tab["x"], tab["y"]], axis=1).astype(np.float64)
    uv = np.stack([tab[columns[0]], tab[columns[1]]], axis=1).astype(np.float64)
    table = {c: tab[c] for c in tab.dtype.names}
    # dots that touch the mask's excluded pixels (track_pair's MASKED bit) are not measured: NaN,
    # and marked in the column "masked"
    masked = (tab["status"] & DotStatus.MASKED) != 0
    uv[masked] = np.nan
    table["masked"] = masked
    valid = is_valid(tab["status"]) & np.all(np.isfinite(uv), axis=1) & ~masked
    counts = {"measured": int(valid.sum()), "replaced": 0, "failed": int((~valid & ~masked).sum()),
              "masked": int(masked.sum()), "total": len(valid)}
    return MethodResult(name, xy, uv, None, table, settings_dict(settings), valid, counts=counts)


def _tracker(columns: tuple[str, str], name: str):
    def run(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
        tab = _track_pair(reference, gradient, prior_xy=prior_xy, settings=settings, device=device, mask=mask)
        return tracking_result(tab, name=name, columns=columns, settings=settings)

    run.__name__ = f"_run_{name.replace('-', '_')}"
    run.__doc__ = f"Dot tracking; the displacement is the table's ({columns[0]}, {columns[1]})."
    run.columns = columns  # what tracking_result reads from a table for this method
    return run


def stack_settings(name: str, overrides: dict):
    """The settings with which a stack (``tracking.stack.track_pairs``) tracks the items of method ``name``,
    or None where they are tracked one by one (``track_pair``).

    Stacks hold the built-in trackers with a prior, whose result is two columns of one ``track_pair``
    table (``tracking``, ``tracking-cc``), with settings whose identification the stack's kernels measure
    (``tracking.identify.kernels_measure``). The others (the paper's procedure, other centroids) identify
    their dots with host code, pair by pair: in the process that drives the device that would take the
    time of a stack's every pair in turn, so they are tracked item by item in the worker processes, each a
    stack of one, side by side on the cores.
    """
    m = get_method(name)
    if name not in BUILT_IN or not m.uses_prior or getattr(m.run, "columns", None) is None:
        return None
    settings = m.settings(overrides)
    return settings if kernels_measure(settings) else None


def stacked_result(name: str, table, settings) -> MethodResult:
    """Method ``name``'s result from its image pair's row of a ``track_pairs`` table (:func:`stack_settings`):
    what its run gives from ``track_pair``'s table of that pair."""
    return tracking_result(table, name=name, columns=get_method(name).run.columns, settings=settings)


def _checked(method: Method) -> Method:
    """``method`` whose run first checks that its modules are there and then checks its result
    (``method_api.check_result``): how a method the project does not test itself is registered."""
    run = method.run

    def checked_run(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
        check_available(method)
        res = run(reference, gradient, prior_xy=prior_xy, settings=settings, device=device, mask=mask)
        return check_result(method, res, np.shape(reference), prior_count=None if prior_xy is None else len(prior_xy))

    checked_run.__name__ = getattr(run, "__name__", "run")
    checked_run.__doc__ = getattr(run, "__doc__", None)
    return replace(method, run=checked_run)


# The Warp modules of the GPU's engines of a step, which a CPU run never launches (each step's kernel module
# names its own ``GPU_MODULE``: the kernel fit a thread per entry, the frame statistics, the claim board's
# rounds).
_GPU_ENGINES = (
    "synthbos.tracking.claim_kernels.gpu",
    "synthbos.tracking.kernel_step_kernels.gpu",
    "synthbos.tracking.stats_kernels.gpu",
)
# the Warp modules that track_pair launches (compiled ahead of the work by a campaign: scheduling)
_TRACKING_KERNELS = (
    "synthbos.tracking.identify_kernels",
    "synthbos.tracking.fit_kernels",
    "synthbos.tracking.moment_kernels",
    "synthbos.tracking.ellipse_kernels",
    "synthbos.tracking.kernel_step_kernels",
    "synthbos.tracking.kernel_step_kernels.gpu",
    "synthbos.tracking.neighbour_kernels",
    "synthbos.tracking.deform_kernels",
)
#: the Warp modules that ``tracking.stack.track_pairs`` launches on a GPU (a campaign that tracks stacks:
#: scheduling)
STACK_KERNELS = (
    "synthbos.tracking.claim_kernels",
    "synthbos.tracking.ellipse_kernels",
    "synthbos.tracking.fit_kernels",
    "synthbos.tracking.identify_kernels",
    "synthbos.tracking.kernel_step_kernels",
    "synthbos.tracking.moment_kernels",
    "synthbos.tracking.neighbour_kernels",
    "synthbos.tracking.predict_fft_kernels",
    "synthbos.tracking.predict_kernels",
    "synthbos.tracking.stats_kernels",
    "synthbos.tracking.table_kernels",
    "synthbos.tracking.wide_search_kernels",
    *_GPU_ENGINES,
)
#: those it launches on the CPU, where its frame statistics, identification and predictor run their host
#: engines (the predictor's deformation kernel instead of the tile engine's FFT and tile kernels) and no
#: step builds its GPU engine
STACK_CPU_KERNELS = tuple(
    sorted(
        {*STACK_KERNELS, "synthbos.tracking.deform_kernels"}
        - {"synthbos.tracking.predict_fft_kernels", "synthbos.tracking.predict_kernels", *_GPU_ENGINES}
    )
)
# those it launches on every pair: the window deformation of a prediction pass (deform_kernels) runs only
# where a coarser pass left a field, and is built on its first launch.
_TRACKING_CPU_KERNELS = tuple(
    name for name in _TRACKING_KERNELS if name != "synthbos.tracking.deform_kernels" and name not in _GPU_ENGINES
)
# track_pair is a stack of one: those of the stack too (on the CPU, deform_kernels again left to its first
# launch)
_DEFAULT_KERNELS = tuple(sorted({*_TRACKING_KERNELS, *STACK_KERNELS}))
_DEFAULT_CPU_KERNELS = tuple(
    sorted({*_TRACKING_CPU_KERNELS, *STACK_CPU_KERNELS} - {"synthbos.tracking.deform_kernels"})
)
_SYNTHBOS = f"synthbos {synthbos.__version__}"

# Okabe-Ito: blue #0072B2, vermillion #D55E00, bluish green #009E73, reddish purple #CC79A7, orange #E69F00,
# sky blue #56B4E9, yellow #F0E442, black.
BUILT_IN: dict[str, Method] = {
    m.name: replace(m, source=_SYNTHBOS)
    for m in (
        Method("correlation", GRID, CorrelationSettings, _run_correlation,
               label="correlation (32→16 px)", color="#0072B2", linestyle="-", marker="o",
               settings_key="correlation", device_resident=True, prepare=_prepare_correlation,
               kernels=("synthbos.correlation.kernels", "synthbos.correlation.pass_kernels",
                        "synthbos.correlation.line_kernels"),
               cpu_kernels=("synthbos.correlation.kernels",)),  # the Warp pass runs on CUDA only
        Method("tracking", DOTS, TrackingSettings, _tracker(("u", "v"), "tracking"),
               label="tracking", color="#D55E00", linestyle="--", marker="s", uses_prior=True,
               settings_key="tracking", kernels=_DEFAULT_KERNELS, cpu_kernels=_DEFAULT_CPU_KERNELS),
        Method("tracking-cc", DOTS, TrackingSettings, _tracker(("u_cc", "v_cc"), "tracking-cc"),
               label="tracking + correlation correction", color="#009E73", linestyle="-.", marker="^",
               uses_prior=True, settings_key="tracking", kernels=_DEFAULT_KERNELS, cpu_kernels=_DEFAULT_CPU_KERNELS),
        # The exact procedure of Rajendran, Bane & Vlachos (2019): three-point Gaussian centroids and the
        # correlation of the segmented dot maps, kept so the paper's comparison can be run as published.
        Method("tracking-paper", DOTS, TrackingSettings, _tracker(("u", "v"), "tracking-paper"),
               label="tracking, paper's procedure", color="#E69F00", linestyle=":", marker="v",
               uses_prior=True, settings_key="tracking", make_settings=TrackingSettings.paper,
               kernels=_TRACKING_KERNELS, cpu_kernels=_TRACKING_CPU_KERNELS, in_default_campaign=False),
        Method("tracking-cc-paper", DOTS, TrackingSettings, _tracker(("u_cc", "v_cc"), "tracking-cc-paper"),
               label="tracking + cc, paper's procedure", color="#CC79A7", linestyle=(0, (3, 1, 1, 1, 1, 1)),
               marker="D", uses_prior=True, settings_key="tracking", make_settings=TrackingSettings.paper,
               kernels=_TRACKING_KERNELS, cpu_kernels=_TRACKING_CPU_KERNELS, in_default_campaign=False),
        # Two families from other libraries (``pip install "synthbos[methods]"``), for comparison.
        _checked(Method("optical-flow", DENSE, OpticalFlowSettings, run_optical_flow,
                        label="optical flow (TV-L1, scikit-image)", color="#56B4E9", linestyle=(0, (5, 2)),
                        marker="P", settings_key="optical_flow", in_default_campaign=False,
                        requires=("skimage",))),
        _checked(Method("openpiv", GRID, OpenPIVSettings, run_openpiv,
                        label="OpenPIV (32→16 px)", color="#7F7F7F", linestyle=(0, (8, 2, 2, 2)), marker="X",
                        settings_key="openpiv", in_default_campaign=False, requires=("openpiv",))),
    )
}

#: How to get the modules a method ``requires``: module -> what to install.
INSTALL_HINTS = {"skimage": 'scikit-image (pip install "synthbos[methods]")',
                 "openpiv": 'openpiv (pip install "synthbos[methods]")'}


class MethodTable(Mapping):
    """The registered methods: the built-in ones, then the plugins (``plugins.load_plugins``).

    A built-in name never loads a plugin; another name loads only the plugin of that name; listing
    the table (iterating, ``len``, ``values``) loads every plugin, once per process. A name that no
    method answers to is simply absent.
    """

    def __init__(self, built_in: dict[str, Method]):
        self._built_in = built_in
        self._all: dict[str, Method] | None = None
        self._one: dict[str, Method] = {}
        self.problems: dict[str, str] = {}
        self._lock = threading.RLock()

    def __getitem__(self, name: str) -> Method:
        if name in self._built_in:
            return self._built_in[name]
        with self._lock:
            if self._all is not None:
                return self._all[name]
            if name not in self._one and name not in self.problems and isinstance(name, str):
                found, problems = load_plugins(taken=self._built_in, name=name)
                self._one.update({k: _checked(m) for k, m in found.items()})
                self.problems.update(problems)
            return self._one[name]

    def _everything(self) -> dict[str, Method]:
        with self._lock:
            if self._all is None:
                found, problems = load_plugins(taken=self._built_in)
                self.problems.update(problems)
                self._all = {**self._built_in, **{k: self._one.get(k) or _checked(m) for k, m in found.items()}}
            return self._all

    def __iter__(self):
        return iter(self._everything())

    def __len__(self) -> int:
        return len(self._everything())

    def forget(self) -> None:
        """Forget the loaded plugins (the next look-up finds them again, e.g. after an install)."""
        with self._lock:
            self._all, self._one, self.problems = None, {}, {}


METHODS = MethodTable(BUILT_IN)


def forget_plugins() -> None:
    """Forget the loaded plugins: the next look-up reads the installed entry points again."""
    METHODS.forget()


def method_names() -> tuple[str, ...]:
    """The registered method names: the built-in ones in the registry's order, then the plugins'."""
    return tuple(METHODS)


def default_methods() -> tuple[str, ...]:
    """The methods a campaign runs unless it names others (built-in ones only: no plugin is loaded)."""
    return tuple(name for name, m in BUILT_IN.items() if m.in_default_campaign)


def get_method(name: str) -> Method:
    """The registry entry of ``name``; a one-line error naming the choices (or the plugin's fault) otherwise."""
    try:
        return METHODS[name]
    except KeyError:
        if name in METHODS.problems:
            raise SynthbosError(METHODS.problems[name]) from None
        raise SynthbosError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}") from None


def missing_modules(method: Method) -> list[str]:
    """The modules a method ``requires`` that cannot be imported here."""
    return [name for name in method.requires if importlib.util.find_spec(name) is None]


def check_available(method: Method) -> None:
    """Refuse, in one line, a method whose required modules are not installed."""
    missing = missing_modules(method)
    if missing:
        raise SynthbosError(f"method {method.name} needs {', '.join(INSTALL_HINTS.get(m, m) for m in missing)}")


def methods_table() -> str:
    """Every registered method on one line each: name, kind, whether campaigns run it by default, its
    source package and version, and what is missing to run it; then the plugins that were skipped."""
    lines = [f"{'method':<20} {'kind':<6} {'default':<8} {'source':<28} label"]
    for name, m in METHODS.items():
        missing = missing_modules(m)
        note = f"  [needs {', '.join(INSTALL_HINTS.get(x, x) for x in missing)}]" if missing else ""
        lines.append(f"{name:<20} {m.kind:<6} {'yes' if m.in_default_campaign else 'no':<8} {m.source:<28} "
                     f"{m.label}{note}")
    lines += [f"skipped: {line}" for line in METHODS.problems.values()]
    return "\n".join(lines)
