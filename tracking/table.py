"""The table: a stack of pairs' status bits and their rows of ``TRACK_DTYPE``, on one Warp device.

The last steps of :func:`tracking.stack.track_pairs`: :func:`predictor_check` sets the found bits and
the predictor's mismatch and weakness, and says which dots vouch for their neighbours and which
mismatches the neighbours may overrule (:func:`tracking.neighbours.confirmed_by_neighbours_stack`);
:func:`edge_cut` keeps the mismatches the neighbours confirm and cuts the dots whose disk leaves the
image differently in the two images; :func:`table_rows` writes each row with the outlier test's verdict
(:func:`tracking.neighbours.neighbour_outliers_stack`) and the registration's, the displacements and the
correction. :class:`HostTable` copies the table back. The kernels are in :mod:`tracking.table_kernels`;
the status bits and rule constants in :mod:`tracking.settings`.
"""

from __future__ import annotations

import mmap
import threading

import numpy as np
import warp as wp

from synthbos.device import copy_to_host

from . import table_kernels as tk
from .settings import TRACK_DTYPE, DotStatus

__all__ = ["HostTable", "edge_cut", "gradient_bits", "masked_rows", "predictor_check", "table_rows"]


def _launch(kernel, dim, inputs, device):
    if dim:
        wp.launch(kernel, dim=dim, inputs=inputs, device=device)


def gradient_bits(with_prior: bool) -> int:
    """The flags of a row's gradient-image dot that join its status: all but OUTSIDE_IMAGE with a prior
    (the dot was looked for at the prior's row), only DISTORTED without one (the dot was paired).

    Examples
    --------
    >>> gradient_bits(False) == DotStatus.DISTORTED
    True
    """
    return ~int(DotStatus.OUTSIDE_IMAGE) if with_prior else int(DotStatus.DISTORTED)


def masked_rows(near, prior, r, g, *, per_frame, device):
    """The (M,) int32 Warp array of the dots a mask hides (MASKED): those whose reference, gradient or
    prior position (``prior`` None: no prior) lies on their pair's ``near`` ((B, H, W) int32 Warp array,
    ``mask.mask_reach``); all 0 without one (``near`` None)."""
    m = r["x"].shape[0]
    if near is None:
        return wp.zeros(m, dtype=wp.int32, device=device)
    hidden = wp.empty(m, dtype=wp.int32, device=device)
    _launch(tk.masked_rows, m, [near, per_frame, prior, r["x"], r["y"], g["x"], g["y"], hidden], device)
    return hidden


def predictor_check(r, g, uv_pred, quality, hidden, *, use_pred, with_prior=True, settings, device):
    """Status bits up to the predictor's check, for the M dots of a stack (flat).

    Parameters
    ----------
    r, g : dict of (M,) Warp arrays
        The reference and gradient images' dots (``"x"``, ``"y"``, ``"flags"``: NaN where not found).
    uv_pred : (M,) wp.vec2d Warp array
        The predicted displacements (read only with ``use_pred``).
    quality : (M,) float64 Warp array
        Their significance (likewise).
    hidden : (M,) int32 Warp array
        The dots a mask hides (:func:`masked_rows`): MASKED, never matched.
    use_pred : bool, keyword-only
        Whether the correlation predictor ran.
    with_prior : bool, keyword-only
        Whether the rows are a prior's (:func:`gradient_bits`).
    settings : TrackingSettings, keyword-only
        ``predictor_tolerance`` and ``predictor_min_correlation``.
    device : warp.context.Device or str, keyword-only

    Returns
    -------
    status : (M,) int32 Warp array
        The bits so far.
    xy, uv : (M,) wp.vec2d Warp arrays
        Reference positions and displacements.
    good, query : (M,) int32 Warp arrays
        The dots that vouch for their neighbours, and those whose mismatch the neighbours may overrule.
    """
    m = r["x"].shape[0]
    status = wp.empty(m, dtype=wp.int32, device=device)
    xy = wp.empty(m, dtype=wp.vec2d, device=device)
    uv = wp.empty(m, dtype=wp.vec2d, device=device)
    good = wp.empty(m, dtype=wp.int32, device=device)
    query = wp.empty(m, dtype=wp.int32, device=device)
    _launch(
        tk.first_status,
        m,
        [
            r["x"], r["y"], r["flags"], g["x"], g["y"], g["flags"], gradient_bits(with_prior), uv_pred, quality,
            int(use_pred),
            float(settings.predictor_tolerance), float(settings.predictor_min_correlation), hidden, status, xy, uv,
            good, query,
        ],
        device,
    )  # fmt: skip
    return status, xy, uv, good, query


def edge_cut(confirmed, query, status, r, g, *, per_frame, shape, diameter, device):
    """Keep the mismatches the neighbours confirm, then cut the dots at the edge (``EDGE_CUT_PX``), in
    ``status``; return the (M,) int32 Warp array of the dots matched so far (those the outlier test takes).
    ``diameter`` is the (B,) dot diameter of each pair, ``shape`` the images' (H, W)."""
    m = status.shape[0]
    h, w = shape
    matched = wp.empty(m, dtype=wp.int32, device=device)
    _launch(
        tk.second_status,
        m,
        [confirmed, query, per_frame, h, w, diameter, r["x"], r["y"], g["x"], g["y"], status, matched],
        device,
    )
    return matched


def table_rows(r, g, matched, outlier, correction, uv_pred, quality, status, *, use_pred, settings, per_frame,
               device, misregistered=None, with_prior=True):  # fmt: skip
    """The (M,) ``TrackRow`` Warp array of the table: the outlier test's verdict, the registration's
    (``misregistered``, (M,) int32 or None), MATCHED, the displacements and the correction
    (``correction``: ``(shared, valid)``, the (2 M, 2) positions whose difference it is, reference rows
    first, and the (M,) int32 verdict where the correction gives one, else None: valid where finite);
    ``per_frame`` is the dots per pair, ``with_prior`` whether they are a prior's rows (``dot_id``)."""
    m = status.shape[0]
    shared, valid = correction
    table = wp.empty(m, dtype=tk.TrackRow, device=device)
    _launch(
        tk.write_table,
        m,
        [
            r["x"], r["y"], r["eta"], r["i0"], r["iteration"], g["x"], g["y"], g["iteration"], matched, outlier,
            misregistered, shared, valid, m, uv_pred, quality, int(use_pred), float(settings.cc_threshold), status,
            per_frame, int(with_prior), table,
        ],
        device,
    )  # fmt: skip
    return table


class HostTable:
    """The (M,) ``TRACK_DTYPE`` array that the device's table is copied into, its pages touched by a host
    thread as soon as it is made, while the device works: first-touch page faults on the ~230 MB of a
    400-pair stack cost tens of milliseconds, and the host only waits for the device meanwhile. The copy
    goes through page-locked buffers made once (``synthbos.device.copy_to_host``): a page-locked table
    would copy faster still but takes longer to allocate and to free than the copy saves."""

    def __init__(self, rows):
        self.out = np.empty(rows, dtype=TRACK_DTYPE)
        self.toucher = threading.Thread(target=_touch_pages, args=(self.out.view(np.uint8),), daemon=True)
        self.toucher.start()

    def fetch(self, table):
        """Copy the device's (M,) ``TrackRow`` table into :attr:`out` and return it."""
        self.toucher.join()
        return copy_to_host(table, self.out)


def _touch_pages(flat):
    flat[:: mmap.PAGESIZE] = 0
