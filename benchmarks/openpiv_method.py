"""The ``openpiv`` method: OpenPIV's window-deformation correlation (``openpiv.windef``), the external reference.

OpenPIV (``pip install "synthbos[methods]"``) runs with the passes of our own ``correlation`` method
(``correlation.CorrelationSettings``): 32 px then 16 px windows without overlap, two
correlate-deform iterations per window size (the first of all a plain correlation), a three-point
Gaussian peak fit, a normalised median test (threshold 2) and symmetric deformation by cubic
interpolation. Everything else is OpenPIV's own default (its signal-to-noise test, outlier replacement).
Its window centres are reported as OpenPIV gives them, ``a + w / 2`` for the window over columns
``a .. a + w - 1`` (half a pixel past its middle, in synthbos's convention of pixel centres at
integers): OpenPIV interpolates each pass's field from those positions to deform the images for the
next one, so the final vectors belong to them (a linear field, ``tests/benchmarks/test_external_methods.py``:
placed at the middles they are off by half the field's gradient).
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import asdict, dataclass

import numpy as np

from synthbos import SynthbosError

from .method_api import grid_result

__all__ = ["OpenPIVSettings", "run_openpiv"]


@dataclass(frozen=True)
class OpenPIVSettings:
    """Settings of the ``openpiv`` method (the ``[openpiv]`` table of a process configuration).

    Attributes
    ----------
    window_sizes : tuple of int
        Window size of each pass (px), as ``correlation``'s.
    overlaps : float
        Overlap fraction of every pass, in [0, 1).
    iterations : int
        Correlate-deform iterations per window size.
    subpixel : {"gaussian", "parabolic", "centroid"}
        OpenPIV's sub-pixel peak estimator.
    median_threshold : float
        Threshold of OpenPIV's normalised median test.
    deformation : {"symmetric", "second image"}
        Deform both images by half the field each, or the second by all of it.
    interpolation_order : int
        Spline order of the image deformation (3: cubic).
    """

    window_sizes: tuple = (32, 16)
    overlaps: float = 0.0
    iterations: int = 2
    subpixel: str = "gaussian"
    median_threshold: float = 2.0
    deformation: str = "symmetric"
    interpolation_order: int = 3

    def __post_init__(self):
        sizes = tuple(self.window_sizes) if np.ndim(self.window_sizes) else (self.window_sizes,)
        if not sizes or not all(isinstance(w, int | np.integer) and w >= 8 for w in sizes):
            raise ValueError(f"window_sizes must be whole numbers >= 8, got {self.window_sizes!r}")
        object.__setattr__(self, "window_sizes", tuple(int(w) for w in sizes))
        if not (isinstance(self.overlaps, int | float) and 0 <= self.overlaps < 1):
            raise ValueError(f"overlaps must be a fraction in [0, 1), got {self.overlaps!r}")
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            raise ValueError(f"iterations must be a whole number >= 1, got {self.iterations!r}")
        if self.subpixel not in ("gaussian", "parabolic", "centroid"):
            raise ValueError(f"subpixel must be gaussian, parabolic or centroid, got {self.subpixel!r}")
        if self.deformation not in ("symmetric", "second image"):
            raise ValueError(f"deformation must be 'symmetric' or 'second image', got {self.deformation!r}")
        if not (isinstance(self.median_threshold, int | float) and self.median_threshold > 0):
            raise ValueError(f"median_threshold must be positive, got {self.median_threshold!r}")
        if self.interpolation_order not in (1, 3, 5):
            raise ValueError(f"interpolation_order must be 1, 3 or 5, got {self.interpolation_order!r}")

    def as_dict(self) -> dict:
        return asdict(self)


def piv_settings(s: OpenPIVSettings):
    """OpenPIV's ``PIVSettings`` for our settings: each window size repeated ``iterations`` times."""
    from openpiv.settings import PIVSettings

    sizes = tuple(w for w in s.window_sizes for _ in range(s.iterations))
    p = PIVSettings()
    p.windowsizes = sizes
    p.overlap = tuple(round(w * s.overlaps) for w in sizes)
    p.num_iterations = len(sizes)
    p.subpixel_method = s.subpixel
    p.median_normalized = True
    p.median_threshold = s.median_threshold
    p.deformation_method = s.deformation
    p.interpolation_order = s.interpolation_order
    p.show_plot = p.show_all_plots = False
    return p


def _passes(reference, gradient, p, mask):
    """OpenPIV's passes as ``windef.simple_multipass`` runs them, without its change to physical
    coordinates (y up): ``x, y, u, v`` in image coordinates and the last pass's outlier flags."""
    from openpiv import filters, validation, windef

    a, b = np.asarray(reference, np.float64), np.asarray(gradient, np.float64)
    if mask is not None:
        a, b = np.where(mask, 0.0, a), np.where(mask, 0.0, b)
    with contextlib.redirect_stdout(io.StringIO()):  # OpenPIV prints its peak counts
        x, y, u, v, s2n = windef.first_pass(a, b, p)
        u, v = np.ma.masked_array(u, mask=np.zeros(u.shape, bool)), np.ma.masked_array(v, mask=np.zeros(v.shape, bool))
        flags = validation.typical_validation(u, v, s2n, p)
        u, v = filters.replace_outliers(u, v, flags, method=p.filter_method, max_iter=p.max_filter_iteration,
                                        kernel_size=p.filter_kernel_size)
        for i in range(1, p.num_iterations):
            x, y, u, v, _, flags = windef.multipass_img_deform(a, b, i, x, y, u, v, p)
    return x, y, u, v, flags


def run_openpiv(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
    """OpenPIV's window deformation on one pair; a ``grid`` result. Masked pixels are zeroed in both
    images (as OpenPIV does) and windows centred on them are not measured; the vectors OpenPIV's last
    validation replaced are not valid (as ``correlation``'s replaced ones). ``prior_xy`` and ``device``
    are not used."""
    s = settings or OpenPIVSettings()
    try:
        x, y, u, v, flags = _passes(reference, gradient, piv_settings(s), mask)
    except ValueError as err:  # OpenPIV gives up when every vector fails its validation
        raise SynthbosError(f"openpiv: {err}") from None
    u, v = np.ma.filled(u, np.nan).astype(np.float64), np.ma.filled(v, np.nan).astype(np.float64)
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    replaced = np.asarray(flags, bool).reshape(u.shape)
    valid = ~replaced
    if mask is not None:
        rows = np.clip(np.rint(y).astype(int), 0, mask.shape[0] - 1)
        cols = np.clip(np.rint(x).astype(int), 0, mask.shape[1] - 1)
        valid &= ~np.asarray(mask, bool)[rows, cols]
    res = grid_result("openpiv", x, y, u, v, valid=valid, settings=s, table={"replaced": replaced})
    res.counts["replaced"] = int(replaced.sum())
    res.counts["failed"] -= res.counts["replaced"]
    return res
