"""Multigrid window-deformation cross-correlation of an image pair.

The processor of Scarano (Meas. Sci. Technol. 13 (2002) R1) as PIV and BOS practice uses it: a
sequence of passes with decreasing window size, each made of one or more iterations; every iteration
after the first carries the current displacement estimate (the predictor) to every pixel, deforms both
images symmetrically by half of it, correlates the deformed windows in one batched real FFT, adds the
residual found by the three-point Gaussian fit to the predictor, validates the field (significance of
the correlation peak, agreement with the coarser pass, the normalised median test), and fills the
rejected vectors by interpolation from the valid ones around them (``validation.fill_by_interpolation``)
before the next iteration. Every vector ends up measured,
replaced or failed (:class:`VectorFlag`, :func:`count_vectors`).

This module holds the settings, the checks of the inputs and the result. The sequence of passes and
iterations is written once, in :func:`correlation.passes.run_passes`; each of its steps is done by the
engine that :meth:`CorrelationSettings.uses_warp` chooses: the host engine
(:mod:`correlation.host_pass`, NumPy/SciPy) or the Warp engine (:mod:`correlation.device_pass`, a fixed
sequence of launches that a CUDA graph records).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field, replace

import numpy as np

from synthbos import SynthbosError
from synthbos.values import check_ranges

from .deform import INTERPOLATORS
from .device_pass import correlate_on_device, device_supports
from .flags import (
    FLAG_BORDER,
    FLAG_DISAGREE,
    FLAG_ISOLATED,
    FLAG_MASKED,
    FLAG_MEDIAN,
    FLAG_PEAK_RATIO,
    VectorFlag,
)
from .host_pass import correlate_on_host
from .pattern import is_periodic
from .peak import PEAK_METHODS, overlap_weights
from .rules import SAMPLING_OFFSET, WINDOW_SIZES  # noqa: F401  (SAMPLING_OFFSET re-exported)
from .windows import WindowGrid, checked_mask, extract_windows, window_grid  # noqa: F401  (re-exported)

__all__ = [
    "FLAG_BORDER",
    "FLAG_DISAGREE",
    "FLAG_ISOLATED",
    "FLAG_MASKED",
    "FLAG_MEDIAN",
    "FLAG_PEAK_RATIO",
    "CorrelationResult",
    "CorrelationSettings",
    "VectorFlag",
    "correlate_pair",
    "count_vectors",
    "pattern_settings",
]


#: Bits meaning that a window gave no usable measurement.
FAILED_BITS = VectorFlag.PEAK | VectorFlag.BORDER | VectorFlag.DISAGREE | VectorFlag.ISOLATED



def count_vectors(flags):
    """Measured, replaced, failed and masked vectors of a flag array.

    Parameters
    ----------
    flags : int array
        :class:`VectorFlag` bits.

    Returns
    -------
    dict
        ``measured`` (flag 0), ``replaced`` (failed only the median test), ``failed`` (no usable
        peak: ``PEAK``, ``BORDER`` or ``DISAGREE``), ``masked``, and ``total``; the first four add up
        to ``total``.
    """
    f = np.asarray(flags, dtype=np.int64)
    masked = (f & FLAG_MASKED) != 0
    failed = ~masked & ((f & int(FAILED_BITS)) != 0)
    replaced = ~masked & ~failed & (f != 0)
    return {
        "measured": int(np.sum(f == 0)),
        "replaced": int(replaced.sum()),
        "failed": int(failed.sum()),
        "masked": int(masked.sum()),
        "total": int(f.size),
    }

#: Values of :attr:`CorrelationSettings.backend`.
BACKENDS = ("auto", "numpy", "warp")

#: Values of :attr:`CorrelationSettings.pattern`.
PATTERNS = ("auto", "random", "periodic")

def _tuple_of(value, n, name):
    if isinstance(value, (numbers.Number, str)):
        value = (value,) * n
    try:
        value = tuple(value)
    except TypeError:
        raise SynthbosError(
            f"correlation setting {name} must be a number or a sequence, got {value!r}"
        ) from None
    if len(value) != n:
        raise SynthbosError(f"correlation setting {name} has {len(value)} entries for {n} passes")
    return value


# Upper bounds of CorrelationSettings' numbers (``synthbos.values.check_ranges``), beyond the checks of
# ``__post_init__``: a window is at most MAX_WINDOW px, a pass iterates at most MAX_ITERATIONS times.
MAX_WINDOW = 1024
MAX_ITERATIONS = 20
CORRELATION_RANGES = {
    "window_sizes": {"list": {"max_size": 8}, "integer": True, "minimum": 4, "maximum": MAX_WINDOW},
    "iterations": {"list": {"max_size": 8}, "integer": True, "minimum": 1, "maximum": MAX_ITERATIONS},
    "median_epsilon": {"minimum": 0.0, "maximum": 100.0},
    "median_threshold": {"above": 0.0, "maximum": 100.0},
    "confirm_tolerance": {"minimum": 0.0, "maximum": 100.0},
    "peak_ratio_min": {"minimum": 0.0, "maximum": 100.0},
    "max_disagreement": {"above": 0.0, "maximum": 10.0},
    "rpc_diameter": {"above": 0.0, "maximum": 64.0},
    "workers": {"integer": True, "minimum": -1024, "maximum": 1024},
}


@dataclass(frozen=True)
class CorrelationSettings:
    """Settings of :func:`correlate_pair`; the defaults are those of the published comparison.

    Parameters
    ----------
    window_sizes : tuple of int
        Square window size of each pass in pixels, e.g. ``(32, 16)``: 32x32 px then 16x16 px.
    overlaps : tuple of float, or float
        Overlap fraction of each pass, in ``[0, 1)``: 0, 0.5 and 0.75 are the usual ones.
        Default (None): 0 for every pass, so ``(0.0, 0.0)`` for the default passes.
    iterations : tuple of int, or int
        Correlate-deform iterations per pass. The first iteration of the first pass is a plain
        correlation; every other one deforms the images with the latest field. Default (None): 2 for
        every pass. Iterating the coarse pass matters most: its converged field is a smooth, accurate
        predictor for the fine pass (6 uniform-shift pairs of the tests, rms error over 16 px
        windows: 0.028 px for (1, 1), 0.010 for (2, 2); (1, 1) with ``interpolator="keys"``, the
        fast setting, 0.030). On the benchmark's 1024x1024 px pairs (one core) (2, 2) takes about
        0.6x OpenPIV windef's time, (1, 1) with "keys" about 0.2x at 0.8-0.9x its rms error.
    subpixel : {"gaussian", "parabolic", "centroid"}
        Three-point peak estimator.
    interpolator : {"cubic", "keys", "lanczos"}
        Image interpolation of the deformation: cubic B-spline (exact at the pixels, as
        ``scipy.ndimage`` order 3; needs a recursive prefilter of each image), Keys cubic
        convolution (a = -1/2, 4x4 taps straight on the pixels: no prefilter, faster, a little less
        accurate) or Lanczos-3 windowed sinc.
    median_epsilon, median_threshold : float
        Normalised median test (Westerweel and Scarano 2005) on the 3x3 neighbourhood: 0.1 px and 2.
    confirm_tolerance : float
        A vector that fails the median test in an iteration after the first of its pass is kept when
        the previous iteration, whose windows were deformed differently, measured the same vector to
        within this many pixels (1 px) and its correlation coefficient is at least 0.7 times its
        neighbours' (``CONFIRM_CORRELATION``): two measurements agree,
        and the median of the neighbours is off because the field varies faster than the vector
        grid resolves (turbulent fields, 16 px windows without overlap: on the benchmark's
        random-phase fields the median test rejects 20 % of such vectors, whose errors are a third
        of their replacements'). 0 replaces every vector that fails the test.
    peak_ratio_min : float
        Vectors whose peak ratio (:func:`correlation.peak.peak_ratio`) is below this failed (flag
        ``PEAK``); 1 disables the check. Not applied to periodic patterns (``pattern``).
    pattern : {"auto", "random", "periodic"}
        The background pattern. ``random`` (dots, speckle, particles): the integer correlation peak
        is the plane's highest sample, and ``peak_ratio_min`` judges its significance. ``periodic``
        (a regular dot grid, a grating): every plane has peaks of equal height at the lattice vectors
        (the FFT correlation is circular), so the peak ratio says nothing and the highest peak may be
        a lattice vector off; the peak taken is the highest of the plane times the window overlap
        (:func:`correlation.peak.overlap_weights`), the one nearest to the predictor (zero
        displacement in the first iteration), and the peak ratio is not tested (``min_correlation``,
        the disagreement with the coarser pass and the median test are). Displacements must then
        stay below half the lattice pitch in the first pass, and the predictor within half a pitch
        in the others. ``auto`` (default): ``periodic`` when the reference image's mean window
        autocorrelation has a secondary peak of at least ``pattern.PERIODIC_PEAK`` within the first
        pass's windows (:func:`correlation.pattern.is_periodic`), else ``random``; the result's
        ``settings.pattern`` says which.
    min_correlation : float
        Vectors whose correlation peak, as a correlation coefficient of the two (deformed) windows,
        is below this failed (flag ``PEAK``): 0.5. Unrelated 16 px windows of 3 px dots reach 0.4
        in the median and pure noise 0.2; matched windows of the same images 0.9 and more, 0.6 at
        5 % noise. 0 disables the check; not applied with ``rpc`` (its planes are not
        coefficients). Applied to the plain correlation of the first iteration and to the final
        iteration, not to the deformed iterations in between (:func:`judges_correlation`).
    max_disagreement : float
        In every pass after the first, vectors that differ from the previous pass's field by more
        than this fraction of the window size failed (flag ``DISAGREE``): 0.25, the one-quarter rule
        for the displacement left after the deformation by the coarser pass.
    rpc : bool
        Use robust phase correlation (Eckstein and Vlachos 2009) instead of the standard one.
    rpc_diameter : float
        Dot diameter in pixels for the RPC spectral filter.
    workers : int
        Threads for ``scipy.fft``.
    device : str
        Warp device ("cpu", "cuda:0"): of the deformation kernels on the NumPy path, of everything on
        the Warp path.
    backend : {"auto", "numpy", "warp"}
        The engine of the steps; both walk the one sequence of passes
        (:func:`correlation.passes.run_passes`). ``numpy``: the host engine
        (:mod:`correlation.host_pass`): windows, FFTs, peak fit and validation in NumPy/SciPy on the
        host, the image deformation on ``device``, host copies every iteration (the reference).
        ``warp``: the Warp engine, every step as Warp kernels on ``device``
        (:mod:`correlation.device_pass`; the images go up once, the vectors come back once;
        power-of-two window sizes). ``auto`` (default): ``warp`` on CUDA devices when the window sizes
        allow it, else ``numpy``. Both give the same vectors and flags to float32 rounding (1e-4 px).

    Examples
    --------
    >>> from synthbos import CorrelationSettings
    >>> settings = CorrelationSettings(window_sizes=(64, 32, 16), overlaps=0.5)
    >>> settings.overlaps, settings.iterations  # one entry per pass
    ((0.5, 0.5, 0.5), (2, 2, 2))
    """

    window_sizes: tuple = WINDOW_SIZES
    overlaps: tuple | float | None = None
    iterations: tuple | int | None = None
    subpixel: str = "gaussian"
    interpolator: str = "cubic"
    median_epsilon: float = 0.1
    median_threshold: float = 2.0
    confirm_tolerance: float = 1.0
    peak_ratio_min: float = 1.05
    pattern: str = "auto"
    min_correlation: float = 0.5
    max_disagreement: float = 0.25
    rpc: bool = False
    rpc_diameter: float = 2.8
    workers: int = 1
    device: str = "cpu"
    backend: str = "auto"

    def __post_init__(self):
        sizes = _tuple_of(self.window_sizes, 1, "window_sizes") if np.ndim(self.window_sizes) == 0 else None
        sizes = sizes if sizes is not None else tuple(self.window_sizes)
        if not sizes:
            raise SynthbosError("correlation setting window_sizes is empty: give at least one pass")
        for s in sizes:
            if not isinstance(s, numbers.Integral) or isinstance(s, bool) or s < 4:
                raise SynthbosError(f"window size {s!r} is not an integer of at least 4 pixels")
        n = len(sizes)
        overlaps = _tuple_of(0.0 if self.overlaps is None else self.overlaps, n, "overlaps")
        for o in overlaps:
            if not isinstance(o, numbers.Real) or not 0.0 <= float(o) < 1.0:
                raise SynthbosError(f"overlap {o!r} is not a fraction in [0, 1) (50% overlap is 0.5)")
        iterations = _tuple_of(
            2 if self.iterations is None else self.iterations, n, "iterations"
        )
        for it in iterations:
            if not isinstance(it, numbers.Integral) or isinstance(it, bool) or it < 1:
                raise SynthbosError(f"iterations per pass {it!r} is not an integer of at least 1")
        if self.subpixel not in PEAK_METHODS:
            raise SynthbosError(f"sub-pixel method {self.subpixel!r} is not one of {', '.join(PEAK_METHODS)}")
        if self.interpolator not in INTERPOLATORS:
            raise SynthbosError(
                f"interpolator {self.interpolator!r} is not one of {', '.join(INTERPOLATORS)}"
            )
        for name in (
            "median_epsilon",
            "median_threshold",
            "confirm_tolerance",
            "peak_ratio_min",
            "min_correlation",
            "max_disagreement",
            "rpc_diameter",
        ):
            value = getattr(self, name)
            if not isinstance(value, numbers.Real) or not np.isfinite(value) or value < 0:
                raise SynthbosError(f"correlation setting {name} must be a finite number >= 0, got {value!r}")
        if self.median_threshold <= 0 or self.rpc_diameter <= 0 or self.max_disagreement <= 0:
            raise SynthbosError(
                "correlation settings median_threshold, max_disagreement and rpc_diameter must be positive"
            )
        if self.min_correlation > 1:
            raise SynthbosError(
                f"correlation setting min_correlation is a correlation coefficient <= 1, got {self.min_correlation!r}"
            )
        if self.pattern not in PATTERNS:
            raise SynthbosError(f"correlation pattern {self.pattern!r} is not one of {', '.join(PATTERNS)}")
        if self.backend not in BACKENDS:
            raise SynthbosError(f"correlation backend {self.backend!r} is not one of {', '.join(BACKENDS)}")
        if not isinstance(self.workers, numbers.Integral) or self.workers == 0:
            raise SynthbosError(
                f"correlation setting workers must be a non-zero integer, got {self.workers!r}"
            )
        object.__setattr__(self, "window_sizes", tuple(int(s) for s in sizes))
        object.__setattr__(self, "overlaps", tuple(float(o) for o in overlaps))
        object.__setattr__(self, "iterations", tuple(int(i) for i in iterations))
        object.__setattr__(self, "rpc", bool(self.rpc))
        check_ranges(self, CORRELATION_RANGES, "")

    def as_dict(self):
        """Settings as plain values (lists, numbers, strings) for file attributes."""
        return {
            "window_sizes": list(self.window_sizes),
            "overlaps": list(self.overlaps),
            "iterations": list(self.iterations),
            "subpixel": self.subpixel,
            "interpolator": self.interpolator,
            "median_epsilon": float(self.median_epsilon),
            "median_threshold": float(self.median_threshold),
            "confirm_tolerance": float(self.confirm_tolerance),
            "peak_ratio_min": float(self.peak_ratio_min),
            "pattern": str(self.pattern),
            "min_correlation": float(self.min_correlation),
            "max_disagreement": float(self.max_disagreement),
            "rpc": bool(self.rpc),
            "rpc_diameter": float(self.rpc_diameter),
            "workers": int(self.workers),
            "device": str(self.device),
            "backend": str(self.backend),
        }

    def is_periodic(self):
        """True for ``pattern="periodic"`` (``auto`` is resolved by :func:`correlate_pair`)."""
        return self.pattern == "periodic"

    def peak_selection(self, size):
        """The ``select`` weights of the peak search for ``size`` px windows (None: the plane maximum)."""
        return overlap_weights((size, size)) if self.is_periodic() else None

    def peak_ratio_threshold(self):
        """``peak_ratio_min``, or 0 (no test) for periodic patterns (whose chosen peak, the one nearest
        to the predictor, may be a little lower than another: a ratio below 1)."""
        return 0.0 if self.is_periodic() else float(self.peak_ratio_min)

    def uses_warp(self):
        """True when :func:`correlate_pair` runs these settings on the Warp path (see ``backend``)."""
        if self.backend != "auto":
            return self.backend == "warp"
        return str(self.device).startswith("cuda") and device_supports(self) is None


@dataclass
class CorrelationResult:
    """Vector field of :func:`correlate_pair` on the last pass's window grid.

    Attributes
    ----------
    x, y : (ny, nx) float arrays
        Window centres in pixels, x = column, y = row (pixel centres at integers).
    u, v : (ny, nx) float arrays
        Displacement from the reference to the gradient image in pixels (x and y); NaN only where
        the window is masked.
    peak_ratio : (ny, nx) float array
        Correlation peak ratio of the last iteration.
    correlation : (ny, nx) float array
        Correlation coefficient of the two deformed windows at the peak, last iteration (NaN with
        ``rpc``).
    flags : (ny, nx) int32 array
        :class:`VectorFlag` bits: 0 measured, ``MEDIAN`` replaced, ``PEAK``, ``BORDER``,
        ``DISAGREE`` failed, ``MASKED``; :func:`count_vectors` counts them.
    settings : CorrelationSettings
        As used: ``pattern`` is "random" or "periodic" (``auto`` resolved).
    """

    x: np.ndarray
    y: np.ndarray
    u: np.ndarray
    v: np.ndarray
    peak_ratio: np.ndarray
    flags: np.ndarray
    settings: CorrelationSettings = field(default_factory=CorrelationSettings)
    correlation: np.ndarray | None = None

    def counts(self):
        """Measured, replaced, failed and masked vectors (:func:`count_vectors`)."""
        return count_vectors(self.flags)


def _checked_array(image, name):
    """The image as an array, after the checks that need no pass over its pixels."""
    arr = np.asarray(image)
    if arr.dtype.kind not in "iuf":
        raise SynthbosError(f"{name} has dtype {arr.dtype}; expected a real or integer image")
    if arr.ndim != 2:
        raise SynthbosError(f"{name} has shape {arr.shape}; expected a 2-D image")
    if arr.size == 0:
        raise SynthbosError(f"{name} is empty (shape {arr.shape})")
    return arr


def _pixel_error(name, arr, nonfinite):
    """The error for an image with ``nonfinite`` non-finite pixels (> 0), or else a constant one."""
    if nonfinite:
        return SynthbosError(f"{name} has {int(nonfinite)} non-finite pixels")
    return SynthbosError(f"{name} is constant (value {arr.flat[0]:g}): there is nothing to correlate")


def _checked_image(image, name):
    arr = _checked_array(image, name).astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise _pixel_error(name, arr, np.sum(~np.isfinite(arr)))
    if arr.max() == arr.min():
        raise _pixel_error(name, arr, 0)
    # zero mean, unit standard deviation: the correlation is linear in each image, so this changes
    # nothing but keeps float32 sums of squares finite for images of any scale (1e-30 to 1e38)
    arr -= arr.mean()
    arr /= np.abs(arr).max()  # first to [-1, 1], so that the squares below cannot overflow
    arr /= np.std(arr)
    return arr.astype(np.float32)


def correlate_pair(reference, gradient, *, settings=None, mask=None):
    """Displacement field between two images by multigrid window-deformation cross-correlation.

    Parameters
    ----------
    reference, gradient : (H, W) arrays of any real or integer dtype
        The reference (undisturbed) image and the image seen through the disturbance (first and
        second frame in PIV terms).
    settings : CorrelationSettings, optional
        Passes, iterations, peak fit, interpolator, validation; the defaults if omitted.
    mask : (H, W) bool array, optional
        True on pixels to exclude. Masked pixels do not take part in the correlation; windows
        more than half masked give NaN vectors flagged ``FLAG_MASKED``.

    Returns
    -------
    CorrelationResult
        Field on the window grid of the last pass.

    Raises
    ------
    synthbos.SynthbosError
        Images of different shapes or not 2-D, empty or constant images, non-finite pixels, windows
        larger than the image, a mask of the wrong shape or covering every window, bad settings.

    Notes
    -----
    Each iteration correlates ``A(x - d(x)/2)`` with ``B(x + d(x)/2)``, where ``d`` is the predictor
    interpolated to every pixel by a separable not-a-knot cubic spline of the previous field; the
    vector is ``d(x_c) + r`` with ``r`` the residual peak position from the three-point fit (Scarano
    2002, eqs. 13-15, symmetric "central difference" deformation). Validation, in every iteration:
    a vector *fails* when its peak is not significant (peak ratio, Keane and Adrian 1992, below
    ``peak_ratio_min``, or peak correlation coefficient below ``min_correlation``), lies on the plane's
    border, differs from the previous pass's field by more than ``max_disagreement`` times the window
    size, or has fewer than two measured neighbours; the others go through the normalised median test
    (Westerweel and Scarano 2005, eq. 2), whose rejections are *replaced* unless the previous
    iteration confirmed them (``confirm_tolerance``). On a periodic pattern (``pattern``, found from
    the reference image with ``auto``) the peak taken is the one nearest to the predictor and the
    peak ratio is not tested. Failed and replaced vectors are filled by harmonic
    interpolation from the valid ones (``validation.fill_by_interpolation``: the discrete Laplace
    equation with the valid vectors as boundary values), and the next iteration deforms the images
    with that field. The images are first brought to zero mean and unit variance.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy import ndimage
    >>> import synthbos
    >>> rng = np.random.default_rng(0)
    >>> reference = ndimage.gaussian_filter(rng.random((64, 64)), 1.0)
    >>> gradient = ndimage.shift(reference, (0.0, 1.5), order=3, mode="wrap")  # 1.5 px along x
    >>> res = synthbos.correlate_pair(reference, gradient)  # 32 px, then 16 px windows
    >>> res.u.shape
    (4, 4)
    >>> bool(np.allclose(res.u, 1.5, atol=0.02)), bool(np.allclose(res.v, 0.0, atol=0.02))
    (True, True)
    """
    a, b, valid_px, settings = _checked_inputs(reference, gradient, settings, mask)
    if settings.uses_warp():
        out = correlate_on_device(
            a, b, settings=settings, valid_px=valid_px, device=settings.device, raise_for=_pixel_error
        )
    else:
        out = correlate_on_host(a, b, settings=settings, valid_px=valid_px)
    return _result(out, settings)


def pattern_settings(reference, settings=None, mask=None):
    """``settings`` with an ``auto`` pattern resolved from ``reference`` (and ``mask``) as
    :func:`correlate_pair` resolves it, which then reads no more from the image to choose it: work that
    a caller may do ahead, in another thread (a campaign does it where it draws the noisy images).

    Examples
    --------
    >>> import numpy as np
    >>> pattern_settings(np.random.default_rng(0).random((64, 64))).pattern
    'random'
    """
    settings = _settings(settings)
    if settings.pattern != "auto":
        return settings
    a = _checker(settings)(reference, "reference image")
    return _resolved(a, checked_mask(mask, a.shape), settings)


def _settings(settings):
    if settings is None:
        return CorrelationSettings()
    if not isinstance(settings, CorrelationSettings):
        raise SynthbosError(f"settings must be a CorrelationSettings, got {type(settings).__name__}")
    return settings


def _checker(settings):
    """How the images are checked (and on the host normalised; the Warp path normalises on the device)."""
    return _checked_array if settings.uses_warp() else _checked_image


def _resolved(a, excluded, settings):
    """``settings`` with an ``auto`` pattern resolved from the checked reference image ``a``."""
    if settings.pattern != "auto":
        return settings
    periodic = is_periodic(a if excluded is None else np.where(excluded, np.mean(a), a), settings.window_sizes[0])
    return replace(settings, pattern="periodic" if periodic else "random")


def _checked_inputs(reference, gradient, settings, mask):
    """``correlate_pair``'s inputs checked: the two images, the valid-pixel weights (None without a mask) and
    the settings with an ``auto`` pattern resolved from the reference image."""
    settings = _settings(settings)
    checked = _checker(settings)
    a = checked(reference, "reference image")
    b = checked(gradient, "gradient image")
    if a.shape != b.shape:
        raise SynthbosError(f"images differ in shape: reference {a.shape}, gradient {b.shape}")
    shape = a.shape
    biggest = max(settings.window_sizes)
    if biggest > min(shape):
        raise SynthbosError(f"window size {biggest} px does not fit in the {shape[0]}x{shape[1]} px image")
    excluded = checked_mask(mask, shape)
    valid_px = None if excluded is None else (~excluded).astype(np.float32)
    return a, b, valid_px, _resolved(a, excluded, settings)


def _result(out, settings):
    """The :class:`CorrelationResult` of an engine's last iteration (``correlate_on_host`` or
    ``correlate_on_device``): NaN where the window is masked, or everywhere when nothing was measured."""
    u, v, flags, masked = out["u"], out["v"], out["flags"], out["masked"]
    if not np.any(flags == 0):  # nothing measured anywhere: there is nothing to fill from
        u = np.full_like(u, np.nan)
        v = np.full_like(v, np.nan)
    u = np.where(masked, np.nan, u)
    v = np.where(masked, np.nan, v)
    coef = np.full(u.shape, np.nan) if settings.rpc else out["correlation"]
    x, y = np.meshgrid(out["node"][1], out["node"][0])
    return CorrelationResult(
        x=x, y=y, u=u, v=v, peak_ratio=out["peak_ratio"], flags=flags, settings=settings, correlation=coef
    )
