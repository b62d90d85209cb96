"""The method registry: one table maps each processing method's name to everything the harness needs.

The command line (``--method``), ``synthbos process``, the campaign, the scoring and the figures read
this table and never switch on a method's name. Adding a method takes its algorithm module and one
``Method`` entry in ``METHODS`` below (its ``run`` adapter turns the algorithm's output into a
:class:`MethodResult`).

Styles use the Okabe-Ito colour-blind-safe palette, with a distinct line style and marker per method,
so the curves stay apart in grey-scale print too.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from synthbos.correlation import CorrelationSettings, correlate_pair
from synthbos.tracking import DotStatus, TrackingSettings, is_valid, track_pair

from synthbos import SynthbosError

__all__ = ["METHODS", "Method", "MethodResult", "default_methods", "forget_shared_results", "get_method",
           "method_names", "settings_dict"]

GRID = "grid"  # a vector on a regular grid of window centres
DOTS = "dots"  # a vector at each tracked dot's reference position


@dataclass
class MethodResult:
    """What a method measured: points (px), displacements (px), and method-specific extras."""

    method: str
    xy: np.ndarray  # (N, 2) measurement points (window centres or reference dot positions)
    uv: np.ndarray  # (N, 2) displacements, NaN where nothing was measured
    grid_shape: tuple | None  # (ny, nx) for grid methods, None for scattered dots
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
        What ``--method`` and the campaign call it.
    kind : {"grid", "dots"}
        Vectors on a grid of windows, or at scattered dots (decides how results are stored and scored).
    settings_class : type
        The frozen dataclass of the method's settings (its fields are the keys users may set).
    run : callable
        ``run(reference, gradient, *, prior_xy, settings, device, mask) -> MethodResult``; ``mask`` is a
        bool image, True on pixels to leave out, or None.
    label, color, linestyle, marker : str
        How figures draw it.
    uses_prior : bool
        Whether the method takes predicted reference-image dot positions.
    settings_key : str
        The table of a process configuration (and the campaign spec's field) holding its settings;
        methods that share a settings class share it.
    make_settings : callable or None
        Builds the settings from overrides (default: ``settings_class``): how one algorithm is registered
        a second time with another procedure, e.g. the paper's exact tracking procedure
        (``TrackingSettings.paper``).
    in_default_campaign : bool
        Whether ``paper``, ``sweep`` and ``regress`` run it unless methods are named.
    device_resident : bool
        Whether its run keeps the images on a CUDA processing device from upload to result, with no
        host work between its kernels. A campaign that processes on a GPU runs such methods in the
        process that drives the GPU and the others, whose host code would hold that process up, in
        its worker processes (on the same device): ``scheduling.run_pipeline``.
    kernels : tuple of str
        The modules of the Warp kernels its run launches: a campaign's worker processes that will run
        it load them as they start.
    """

    name: str
    kind: str
    settings_class: type
    run: Callable
    label: str
    color: str
    linestyle: str
    marker: str
    uses_prior: bool = False
    settings_key: str = ""
    make_settings: Callable | None = None
    in_default_campaign: bool = True
    device_resident: bool = False
    kernels: tuple[str, ...] = ()

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
    return dict(settings)


def _run_correlation(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
    if device is not None:  # the processing device travels in the correlation settings
        settings = replace(settings or CorrelationSettings(), device=str(device))
    res = correlate_pair(reference, gradient, settings=settings, mask=mask)
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


def _tracker(columns: tuple[str, str], name: str):
    def run(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
        tab = _track_pair(reference, gradient, prior_xy=prior_xy, settings=settings, device=device, mask=mask)
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
        return MethodResult(name, xy, uv, None, table, settings_dict(settings), valid,
                            counts=counts)

    run.__name__ = f"_run_{name.replace('-', '_')}"
    run.__doc__ = f"Dot tracking; the displacement is the table's ({columns[0]}, {columns[1]})."
    return run


_TRACKING_KERNELS = ("synthbos.tracking.kernels",)

# Okabe-Ito: blue #0072B2, vermillion #D55E00, bluish green #009E73, reddish purple #CC79A7, orange #E69F00.
METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("correlation", GRID, CorrelationSettings, _run_correlation,
               label="correlation (32→16 px)", color="#0072B2", linestyle="-", marker="o",
               settings_key="correlation", device_resident=True,
               kernels=("synthbos.correlation.kernels", "synthbos.correlation.pass_kernels")),
        Method("tracking", DOTS, TrackingSettings, _tracker(("u", "v"), "tracking"),
               label="tracking", color="#D55E00", linestyle="--", marker="s", uses_prior=True,
               settings_key="tracking", kernels=_TRACKING_KERNELS),
        Method("tracking-cc", DOTS, TrackingSettings, _tracker(("u_cc", "v_cc"), "tracking-cc"),
               label="tracking + correlation correction", color="#009E73", linestyle="-.", marker="^",
               uses_prior=True, settings_key="tracking", kernels=_TRACKING_KERNELS),
        # The exact procedure of Rajendran, Bane & Vlachos (2019): three-point Gaussian centroids and the
        # correlation of the segmented dot maps, kept so the paper's comparison can be run as published.
        Method("tracking-paper", DOTS, TrackingSettings, _tracker(("u", "v"), "tracking-paper"),
               label="tracking, paper's procedure", color="#E69F00", linestyle=":", marker="v",
               uses_prior=True, settings_key="tracking", make_settings=TrackingSettings.paper,
               kernels=_TRACKING_KERNELS, in_default_campaign=False),
        Method("tracking-cc-paper", DOTS, TrackingSettings, _tracker(("u_cc", "v_cc"), "tracking-cc-paper"),
               label="tracking + cc, paper's procedure", color="#CC79A7", linestyle=(0, (3, 1, 1, 1, 1, 1)),
               marker="D", uses_prior=True, settings_key="tracking", make_settings=TrackingSettings.paper,
               kernels=_TRACKING_KERNELS, in_default_campaign=False),
    )
}


def method_names() -> tuple[str, ...]:
    """The registered method names, in the registry's order."""
    return tuple(METHODS)


def default_methods() -> tuple[str, ...]:
    """The methods a campaign runs unless it names others."""
    return tuple(name for name, m in METHODS.items() if m.in_default_campaign)


def get_method(name: str) -> Method:
    """The registry entry of ``name``; a one-line error naming the choices otherwise."""
    try:
        return METHODS[name]
    except KeyError:
        raise SynthbosError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}") from None
