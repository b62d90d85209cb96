"""The correction step: a matched dot's displacement measured a second way (``u_cc, v_cc``).

Two corrections: the default model correction, both positions refitted with the pair's common peak and
width (:func:`tracking.dotfit.fit_stack` returns them), and the paper's, the correlation of the dot's two
intensity maps (Rajendran, Bane and Vlachos 2019, section 2.3; :func:`correlation_correction`).
:func:`paper_correction_stack` writes the paper's for a stack in the model correction's form, so that
the table (:func:`tracking.table.table_rows`) reads either one way.
"""

from __future__ import annotations

import numpy as np
import warp as wp
from synthbos.correlation.peak import subpixel_peak
from synthbos.correlation.xcorr import cross_correlate

__all__ = ["correlation_correction", "paper_correction_stack"]

#: The largest displacement (px) that the paper's correction resolves between two dot maps centred on
#: their peak pixels: the peak pixels' offset is known, the correlation only refines it.
MAX_SHIFT_PX = 2


def correlation_correction(reference_maps, gradient_maps, *, max_shift=None, method="gaussian"):
    """Displacement of each dot by cross-correlating its reference and gradient intensity maps.

    Parameters
    ----------
    reference_maps, gradient_maps : (N, h, w) arrays
        The dot's pixels in both images on one common window (background removed, pixels that are not
        the dot's zeroed).
    max_shift : int, optional
        Largest displacement to resolve; the maps are zero-padded by it so the circular correlation does
        not wrap. ``max(h, w) // 2`` by default.
    method : {"gaussian", "parabolic", "centroid"}
        Three-point peak fit (:func:`correlation.peak.subpixel_peak`).

    Returns
    -------
    u, v : (N,) arrays
        Displacement of the gradient dot relative to the reference dot (x = column), in pixels.
    ok : (N,) bool array
        False where the correlation peak sits on the padded plane's edge or both maps are empty
        (u, v are then still finite).

    Notes
    -----
    Rajendran, Bane and Vlachos (2019), section 2.3: the noise of the two frames is uncorrelated, so the
    correlation peak is less noise-sensitive than the difference of two three-point centroids. It is
    the pipeline's ``correction="paper"``. Its bias: the three-point Gaussian fit of the correlation
    peak (up to ~0.008 px for whole 3 px dots) plus the segmentation cutting the two maps differently
    (in a dense pattern p95 ~0.04 px without noise); the default ``correction="model"`` has neither.
    """
    a = np.asarray(reference_maps, dtype=np.float64)
    b = np.asarray(gradient_maps, dtype=np.float64)
    n, h, w = a.shape
    if max_shift is None:
        max_shift = max(h, w) // 2
    ph, pw = h + max_shift + 1, w + max_shift + 1
    ph += ph % 2
    pw += pw % 2
    pa = np.zeros((n, ph, pw))
    pb = np.zeros((n, ph, pw))
    pa[:, :h, :w] = a
    pb[:, :h, :w] = b
    corr = cross_correlate(pa, pb, subtract_mean=False)
    row, col, on_border = subpixel_peak(corr, method=method)
    ok = ~on_border & (np.abs(a).sum(axis=(1, 2)) > 0) & (np.abs(b).sum(axis=(1, 2)) > 0)
    return col - pw // 2, row - ph // 2, ok


def paper_correction_stack(r, g, *, device):
    """The paper's correction of every row of a stack found in both images, as ``(shared, valid)``: a
    (2 M, 2) float64 Warp array whose gradient rows minus reference rows are the correction (the peak
    pixels' offset plus the correlation peak's; NaN where a dot is missing) and the (M,) int32 Warp
    array of :func:`correlation_correction`'s ``ok``.

    ``r`` and ``g`` are the two images' dots (``"x"`` and ``"root"`` Warp arrays, ``"dotmap"`` an (M, c, c)
    NumPy array: :func:`tracking.identify.identify_near_predictions` keeps them for this correction).

    Examples
    --------
    >>> yy, xx = np.mgrid[-3:4, -3:4]
    >>> spot = np.exp(-(xx**2 + yy**2) / 1.5)[None]  # one dot's map, the same in both images
    >>> def dots(x, root):
    ...     return {"x": wp.array([x], dtype=wp.float64, device="cpu"),
    ...             "root": wp.array([root], dtype=wp.int32, device="cpu"), "dotmap": spot}
    >>> shared, valid = paper_correction_stack(dots(10.0, [10, 5]), dots(12.0, [12, 6]), device="cpu")
    >>> (shared.numpy()[1] - shared.numpy()[0]).round(6).tolist(), valid.numpy().tolist()
    ([2.0, 1.0], [1])
    """
    both = np.flatnonzero(np.isfinite(r["x"].numpy()) & np.isfinite(g["x"].numpy()))
    m = len(r["dotmap"])
    shared = np.full((2 * m, 2), np.nan)
    valid = np.zeros(m, dtype=np.int32)
    if both.size:
        du, dv, ok = correlation_correction(r["dotmap"][both], g["dotmap"][both], max_shift=MAX_SHIFT_PX)
        offset = (g["root"].numpy()[both] - r["root"].numpy()[both]).astype(np.float64)
        shared[both] = 0.0
        shared[m + both, 0] = offset[:, 0] + du
        shared[m + both, 1] = offset[:, 1] + dv
        valid[both] = ok
    return wp.array(shared, dtype=wp.float64, device=device), wp.array(valid, dtype=wp.int32, device=device)
