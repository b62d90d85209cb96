"""Dot tracking of a stack of image pairs on one device: the method's one orchestration.

:func:`track_pairs` tracks a stack of B pairs of one shape: the images go up once, every kernel launch
covers the dots of all pairs, and the table comes back once. Each pair gets what it gets alone: the same
frame statistics, identification rounds, blob claims, predictor, wide second search, model fit,
correction, predictor check, edge cut, outlier test and table, each pair with its own noise, saturation,
background, dot diameter and median peak. :func:`tracking.track_pair` is a stack of one.

The variants are options inside the steps they change, not second pipelines:

- **with a prior** (``_dots_from_prior``): every prior row is looked for around its prior in the reference
  image and around its predicted position in the gradient image, then in the wide window where missed;
- **without one**, standard tracking (``_dots_without_prior``): each image's dots are identified on their
  own (:meth:`tracking.identify.StackIdentification.standard`) and paired (:func:`tracking.match.pair_dots`),
  and the pairs are laid out in rows as a prior's (:func:`tracking.match.paired_rows`), so that every
  later step is the same; the registration check (MISREGISTERED, :func:`tracking.register.misregistered`)
  is standard tracking's own;
- **the estimators**: ``centroid`` other than "model" takes identification's host engine (its centroid
  fits, :func:`tracking.identify.kernels_measure`) and keeps its positions (``fit_stack(take=False)``);
  the paper's ``correction`` correlates the dot maps that engine keeps
  (:func:`tracking.correction.paper_correction_stack`);
- **masks** (:mod:`tracking.mask`): the fill in the upload, the noise of the pixels kept, the predictor's
  masked correlation, MASKED in the table; a **mapping** is applied to the prior by ``track_pair``.

On the CPU three steps run their host engines, chosen by device inside the step: the frame statistics
(:func:`_host_statistics`), identification (``identify_near_predictions`` pair by pair) and the predictor
(``predict_displacement``, pocketfft), each faster there than its kernels; there a pair's table is the
same to the bit alone or in any stack. On a GPU every step runs its kernels (the predictor's float32
correlation differs from pocketfft's by rounding). The model fit sorts its rows once into raster order on
the device, so that neighbouring threads read neighbouring pixels; its fixed-point model images make the
result independent of that order.

Where a step depends on data (a pair's identification ending early, its predictor's pyramid ending at
a coarser pass, the wide search of the dots the first one missed), the stack runs the step for every
pair and leaves the pairs it no longer concerns untouched, so the number of launches does not depend on
B. The host waits for the device a few times per stack (the image checks, the predictor's pass schedule,
the count of missed dots, the largest peak of each pair for the fit's fixed-point scales), never per
pair.

This module only orchestrates; each step lives in its room: the frame statistics in
:mod:`tracking.frame_stats`, identification in :mod:`tracking.identify` (``StackIdentification``),
the predictor in :mod:`tracking.predict` (``predict_displacement_stack``), the wide search in
:mod:`tracking.wide_search`, the pairing of standard tracking in :mod:`tracking.match`, the model fit in
:mod:`tracking.dotfit` (``fit_stack``), the paper's correction in :mod:`tracking.correction`, the
neighbour tests in :mod:`tracking.neighbours`, the registration check in :mod:`tracking.register` and the
table in :mod:`tracking.table`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from synthbos import SynthbosError
from synthbos.device import init_warp

from . import claim_kernels as ck
from . import identify_kernels as ik
from .correction import paper_correction_stack
from .diameter import estimate_dot_diameter
from .dotfit import fit_stack, fit_window_half
from .frame_stats import fill_level, frame_statistics, saturation_level
from .identify import StackIdentification, estimate_noise
from .mask import check_mask, mask_reach, masked_fill
from .match import pair_dots, paired_rows
from .neighbours import confirmed_by_neighbours_stack, neighbour_outliers_stack
from .predict import pooling_block, predict_displacement, predict_displacement_stack, predictor_passes
from .register import misregistered
from .settings import (
    TRACK_DTYPE,
    TrackingSettings,
    prior_inside,
    window_sizes,
)
from .table import HostTable, edge_cut, masked_rows, predictor_check, table_rows
from .wide_search import wide_search_stack
from .workspace import hold_freed_memory

__all__ = ["pairs_per_call", "track_pairs"]

#: Device memory that :func:`track_pairs` takes per pair beyond its two images, per pixel and per prior
#: dot: 77-85 B/px was measured on an H200 (2026-11-22; 256 to 1024 px images, 1,280 to 20,480 dots,
#: 25 to 400 pairs), and about 120 B per dot; these leave a margin.
BYTES_PER_PIXEL = 96
BYTES_PER_DOT = 512
#: The share of a GPU's free memory that one turn of :func:`track_pairs` may fill: more pairs are
#: tracked in turns (:func:`pairs_per_call`).
MEMORY_SHARE = 0.8



def _stack_shape(a, name):
    """The (B, H, W) shape of an image stack (a Warp array or anything NumPy takes), checked 3-D."""
    shape = tuple(a.shape) if isinstance(a, wp.array) else np.shape(a)
    if len(shape) != 3:
        raise SynthbosError(f"{name} images must be a (pairs, height, width) stack, got shape {shape}")
    return shape


def pairs_per_call(shape, dots, device, *, on_device=True):
    """How many pairs of ``shape`` (H, W) with ``dots`` prior dots :func:`track_pairs` tracks at once on
    ``device``: all on the CPU (None); on a GPU as many as fill ``MEMORY_SHARE`` of its free memory at
    ``BYTES_PER_PIXEL`` and ``BYTES_PER_DOT`` each (plus the images' upload unless ``on_device``), at
    least one."""
    dev = wp.get_device(device)
    if not dev.is_cuda:
        return None
    h, w = shape
    per_pair = BYTES_PER_PIXEL * h * w + BYTES_PER_DOT * dots + (0 if on_device else 2 * 8 * h * w)
    return max(1, int(MEMORY_SHARE * dev.free_memory) // per_pair)


def _upload(a, name, device, excluded=None):
    """A (B, H, W) float64 Warp array on ``device`` from a stack :func:`_stack_shape` checked (a Warp
    array or anything NumPy takes), the pixels ``excluded`` ((B, H, W) bool or None) filled
    (:func:`tracking.mask.masked_fill`; a pair with non-finite pixels is left to the image check)."""
    if isinstance(a, wp.array):
        if excluded is None and a.dtype == wp.float64 and str(a.device) == str(wp.get_device(device)):
            return a
        a = a.numpy()
    a = np.asarray(a)
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise SynthbosError(f"{name} images must hold real numbers, got dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.float64)
    if excluded is not None:
        a = np.stack([masked_fill(im, m) if np.isfinite(im).all() else im for im, m in zip(a, excluded, strict=True)])
    # on the CPU the stack is read where it lies (no copy; the tracker never writes its images)
    return wp.array(a, dtype=wp.float64, device=device, copy=not wp.get_device(device).is_cpu)


class _Pairs:
    """Per-pair geometry of one group of pairs (pairs of one group share every integer size)."""

    def __init__(self, d, settings):
        self.d = d
        self.eta0, self.half_r, self.half_g, self.map_half = window_sizes(d, settings)
        self.fit_half, self.render_half = fit_window_half(self.eta0)

    def key(self):
        return (self.half_r, self.half_g, self.map_half, self.fit_half, self.render_half)


def _image_of(first, b, name):
    """How an error names image ``name`` of pair ``first + b`` (``first`` None: the only pair).

    Examples
    --------
    >>> _image_of(None, 0, "reference"), _image_of(8, 2, "gradient")
    ('the reference image', "pair 10's gradient image")
    """
    return f"the {name} image" if first is None else f"pair {first + b}'s {name} image"


def _frame_statistics(images, name, settings, device, first, excluded=None, launched=None):
    """Per pair (host arrays of B values): noise, fill, saturation level (capped at 1e300 as the window
    kernel takes it) and dot diameter, computed on the device (on the CPU by :func:`_host_statistics`);
    the image checks (the pairs named from ``first``; None: the only pair). With a mask (``excluded``), the
    noise of the pixels kept, by the host (the device's sort takes no mask). On a GPU, ``launched`` is the
    device's :func:`tracking.frame_stats.frame_statistics` of ``images``, launched ahead: both stacks'
    are launched before either is read, so that the device does not wait for the host in between."""
    if wp.get_device(device).is_cpu:
        diameter = name == "reference" and settings.diameter is None
        st = _host_statistics(images.numpy(), diameter=diameter, excluded=excluded)
    else:
        st = {k: v.numpy() for k, v in launched.items()}
        if excluded is not None:
            host = images.numpy()
            st["noise"] = np.array([estimate_noise(im, excluded=m) for im, m in zip(host, excluded, strict=True)])
    for b, why in enumerate(st["bad"]):
        if why == 1:
            raise SynthbosError(f"{_image_of(first, b, name)} contains non-finite pixels (NaN or inf)")
        if why == 2:
            raise SynthbosError(f"{_image_of(first, b, name)} is all zero")
    sat = st["saturation"] if settings.saturation_level is None else np.full(len(st["bad"]), settings.saturation_level)
    return {"noise": st["noise"], "fill": st["fill"], "sat": np.minimum(sat, 1e300), "diameter": st["diameter"]}


def _host_statistics(images, *, diameter, excluded=None):
    """The frame statistics' host engine, for the CPU: the host functions frame by frame
    (8 ms against the device sorts' 52 ms on the 1024 x 1024 benchmark pair); the diameter only where it
    is asked for (NaN otherwise); the noise of the pixels not ``excluded`` ((F, H, W) bool or None). ``bad``:
    1 for non-finite pixels, 2 for an all-zero frame."""
    n = len(images)
    st = {k: np.full(n, np.nan) for k in ("noise", "fill", "saturation", "diameter")}
    st["bad"] = np.zeros(n, dtype=np.int32)
    for f, image in enumerate(images):
        lo, hi = image.min(), image.max()
        if not (np.isfinite(lo) and np.isfinite(hi)):
            st["bad"][f] = 1
            continue
        if lo == 0 and hi == 0:
            st["bad"][f] = 2
            continue
        st["noise"][f] = estimate_noise(image, excluded=None if excluded is None else excluded[f])
        st["fill"][f] = fill_level(image)
        st["saturation"][f] = saturation_level(image, None, hi)
        if diameter:
            st["diameter"][f] = estimate_dot_diameter(image)
    return st


def track_pairs(
    references, gradients, *, prior_xy=None, mask=None, settings: TrackingSettings | None = None, device=None
):
    """Track every dot from the reference to the gradient image of each of B pairs.

    Parameters
    ----------
    references, gradients : (B, H, W) arrays or Warp arrays
        The image pairs (any real dtype; Warp float64 arrays on ``device`` are used without a copy).
    prior_xy : (N, 2) or (B, N, 2) array, optional
        Predicted reference-image positions of the pattern's dots (x = column, y = row), one set for all
        pairs or one per pair. Without it, standard tracking: each pair's dots are identified in both
        images and paired.
    mask : (H, W) or (B, H, W) bool array, optional
        Pixels to exclude (True), one mask for all pairs or one per pair, as ``track_pair``'s ``mask``:
        filled with the median of the others, left out of the noise and of the predictor's correlation,
        and a dot within a dot radius of them is MASKED (:mod:`tracking.mask`).
    settings : TrackingSettings, optional
        Defaults to ``TrackingSettings()``.
    device : str or None, optional
        Warp device ("cpu", "cuda:0"); Warp's default when None.

    Returns
    -------
    (B, N) numpy structured array of dtype ``TRACK_DTYPE``, or without a prior a list of B such arrays
        Row ``[b, i]`` is ``track_pair(references[b], gradients[b], prior_xy=prior[b], mask=mask[b],
        settings=settings)``'s row i; without a prior, one row per dot identified in pair b's reference
        image.

    Raises
    ------
    synthbos.SynthbosError
        Stacks of different shapes or not 3-D, images all zero or with non-finite pixels (the pair is
        named), a prior of the wrong shape or entirely outside the image, a mask of the wrong shape or type
        or one that excludes every pixel.

    Notes
    -----
    On a GPU, the pairs are tracked in turns of as many as its free memory holds
    (:func:`pairs_per_call`, some 28 MB per 512 x 512 pair of 5,120 dots); each turn uploads its own
    images when they come as NumPy stacks. With a mask, the images are filled on the host and the
    predictor runs its host engine (the tile correlation takes no mask).
    """
    settings = TrackingSettings() if settings is None else settings
    init_warp()
    device = str(wp.get_device(device))
    hold_freed_memory(device)
    shape_r, shape_g = _stack_shape(references, "reference"), _stack_shape(gradients, "gradient")
    if shape_r != shape_g:
        raise SynthbosError(f"reference and gradient stacks differ in shape: {shape_r} and {shape_g}")
    B, H, W = shape_r
    if B == 0:
        return np.zeros((0, 0), dtype=TRACK_DTYPE) if prior_xy is not None else []
    if min(H, W) < 8:
        raise SynthbosError(f"images are too small ({H}x{W}), need at least 8x8")
    prior = None if prior_xy is None else _checked_prior(prior_xy, B, (H, W))
    excluded = _stack_mask(mask, B, (H, W))
    on_device = all(isinstance(a, wp.array) and a.device == wp.get_device(device) for a in (references, gradients))
    dots = (H * W) // STANDARD_PX_PER_DOT if prior is None else prior.shape[-2]
    turn = pairs_per_call((H, W), dots, device, on_device=on_device) or B
    turns = [(a, min(a + turn, B)) for a in range(0, B, turn)]
    tables = [
        _track_turn(references[a:b] if turn < B else references, gradients[a:b] if turn < B else gradients,
                    prior if prior is None or prior.ndim == 2 else prior[a:b],
                    None if excluded is None else excluded[a:b], settings, device, a if B > 1 else None)
        for a, b in turns
    ]  # fmt: skip
    if prior is None:
        return [t for tables_of_turn in tables for t in tables_of_turn]
    return tables[0] if len(tables) == 1 else np.concatenate(tables)


#: Pixels per dot at the densest pattern standard tracking is sized for: how many dots a pair without a
#: prior is taken to hold when its share of a GPU's memory is reckoned (:func:`pairs_per_call`).
STANDARD_PX_PER_DOT = 16


def _checked_prior(prior_xy, pairs, shape):
    """The (N, 2) or (B, N, 2) float64 prior, checked: its shape, and some dots of every pair inside."""
    prior = np.asarray(prior_xy, dtype=np.float64)
    shared = prior.ndim == 2  # one prior for all pairs: checked and uploaded once, repeated on the device
    if not (prior.ndim in (2, 3) and prior.shape[-1] == 2 and (shared or prior.shape[0] == pairs)):
        raise SynthbosError(f"prior positions must be an Nx2 or {pairs}xNx2 array, got shape {prior.shape}")
    inside = prior_inside(prior, shape)
    if not inside.any(axis=-1).all():
        which = "" if shared else f" of pair {int(np.flatnonzero(~inside.any(axis=1))[0])}"
        raise SynthbosError(f"no prior dot{which} lies inside the {shape[0]}x{shape[1]} image")
    return prior


def _stack_mask(mask, pairs, shape):
    """The (B, H, W) bool mask of every pair (:func:`tracking.mask.check_mask` each), or None."""
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.ndim == 2:
        return np.broadcast_to(check_mask(m, shape), (pairs, *shape))
    if m.ndim != 3 or m.shape[0] != pairs:
        raise SynthbosError(f"mask must be an HxW or {pairs}xHxW array, got shape {m.shape}")
    return np.stack([check_mask(one, shape) for one in m])


def _track_turn(references, gradients, prior, excluded, settings, device, first):
    """:func:`track_pairs` of pairs ``first ...`` (the pairs its errors name; None: the only pair), checked,
    in one turn: the (B, N) table, or without a prior the list of B tables."""
    refs = _upload(references, "reference", device, excluded)
    grads = _upload(gradients, "gradient", device, excluded)
    B = refs.shape[0]
    launched = [None, None]
    if wp.get_device(device).is_cuda:
        launched = [frame_statistics(a, device=device) for a in (refs, grads)]
    st_r = _frame_statistics(refs, "reference", settings, device, first, excluded, launched[0])
    st_g = _frame_statistics(grads, "gradient", settings, device, first, excluded, launched[1])
    d = np.full(B, float(settings.diameter)) if settings.diameter is not None else st_r["diameter"]
    bad = ~(np.isfinite(d) & (d > 0))
    if bad.any():
        raise SynthbosError(
            f"cannot estimate the dot diameter from {_image_of(first, int(np.flatnonzero(bad)[0]), 'reference')}; "
            "give it in settings"
        )
    shared = {di: _Pairs(di, settings) for di in set(d.tolist())}  # (once per diameter: usually one for all)
    geometry = [shared[di] for di in d.tolist()]
    groups: dict = {}
    for b, g in enumerate(geometry):
        groups.setdefault(g.key(), []).append(b)
    if len(groups) == 1:  # (the usual case: one diameter for all)
        return _track_group(refs, grads, prior, excluded, st_r, st_g, geometry, settings, device)
    out = np.zeros((B, prior.shape[-2]), dtype=TRACK_DTYPE) if prior is not None else [None] * B
    for members in groups.values():
        sel = np.array(members)
        tables = _track_group(
            _pairs_of(refs, sel),
            _pairs_of(grads, sel),
            prior if prior is None or prior.ndim == 2 else prior[sel],
            None if excluded is None else excluded[sel],
            {k: (v[sel] if isinstance(v, np.ndarray) else v) for k, v in st_r.items()},
            {k: (v[sel] if isinstance(v, np.ndarray) else v) for k, v in st_g.items()},
            [geometry[b] for b in sel],
            settings,
            device,
        )
        for k, b in enumerate(sel):
            out[b] = tables[k]
    return out


def _pairs_of(stack, sel):
    """The pairs ``sel`` of a (B, H, W) Warp stack (the stack itself when it holds no others)."""
    if len(sel) == stack.shape[0]:
        return stack
    return wp.array(stack.numpy()[sel], dtype=wp.float64, device=stack.device)


class _Stack:
    """What every step of one group's tracking reads: the images, the settings, the device, the per-pair
    statistics (as Warp arrays) and the identification."""

    def __init__(self, refs, grads, excluded, st_r, st_g, geometry, settings, device, per_frame):
        self.refs, self.grads, self.excluded = refs, grads, excluded
        self.geometry, self.settings, self.device = geometry, settings, device
        self.B, self.H, self.W = refs.shape
        s = settings
        self.stats = {
            "noise": [self.arr(st["noise"], wp.float64) for st in (st_r, st_g)],
            "fill": [self.arr(st["fill"], wp.float64) for st in (st_r, st_g)],
            "sat": [self.arr(st["sat"], wp.float64) for st in (st_r, st_g)],
            "floor": [self.arr(s.noise_threshold * st["noise"], wp.float64) for st in (st_r, st_g)],
            "sat_frames": self.arr(np.stack([st_r["sat"], st_g["sat"]], axis=1).ravel(), wp.float64),
            "noise_frames": self.arr(np.stack([st_r["noise"], st_g["noise"]], axis=1).ravel(), wp.float64),
        }
        self.ident = StackIdentification(refs, self.stats, geometry, s, per_frame=per_frame, device=device)

    def arr(self, a, dtype):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=self.device)


def _track_group(refs, grads, prior, excluded, st_r, st_g, geometry, settings, device):
    """The method's steps for one group of pairs: the (B, N) table, or without a prior the list of B."""
    B, H, W = refs.shape
    s = settings
    host_table = None
    if prior is not None and wp.get_device(device).is_cuda:
        host_table = HostTable(B * prior.shape[-2])
    st = _Stack(refs, grads, excluded, st_r, st_g, geometry, s, device, 0 if prior is None else prior.shape[-2])
    if prior is None:
        r, g, uv_pred, quality, counts = _dots_without_prior(st)
        rows_prior = None
    else:
        r, g, uv_pred, quality, rows_prior = _dots_from_prior(st, prior)
    N = r["x"].shape[0] // B
    use_pred = s.predictor == "correlation"
    shared = None
    if s.centroid == "model" or s.correction == "model":
        shared = fit_stack(
            refs, grads, r, g, eta0=st.ident.eta0_host, sat_frames=st.stats["sat_frames"],
            noise_frames=st.stats["noise_frames"], fit_half=geometry[0].fit_half, render_half=geometry[0].render_half,
            settings=s, device=device, take=s.centroid == "model",
        )  # fmt: skip
    correction = (shared, None) if s.correction == "model" else paper_correction_stack(r, g, device=device)
    near = None if excluded is None else st.arr(
        np.stack([mask_reach(m, pair.d) for m, pair in zip(excluded, geometry, strict=True)]).astype(np.int32),
        wp.int32,
    )
    hidden = masked_rows(near, rows_prior, r, g, per_frame=N, device=device)
    status, xy, uv, good, query = predictor_check(r, g, uv_pred, quality, hidden, use_pred=use_pred,
                                                  with_prior=prior is not None, settings=s, device=device)  # fmt: skip
    confirmed = _confirmed(xy, uv, good, query, B, N, s, device)
    diameter = st.arr([pair.d for pair in geometry], wp.float64)
    matched = edge_cut(confirmed, query, status, r, g, per_frame=N, shape=(H, W), diameter=diameter, device=device)
    outlier = _outliers(xy, uv, matched, B, N, s, device)
    refused = None
    if prior is None and np.isfinite(s.registration_tolerance):
        refused = _misregistered(st, xy, uv, matched, outlier, correction)
    table = table_rows(
        r, g, matched, outlier, correction, uv_pred, quality, status, use_pred=use_pred, settings=s, per_frame=N,
        device=device, misregistered=refused, with_prior=prior is not None,
    )  # fmt: skip
    if prior is None:
        rows = table.numpy().view(TRACK_DTYPE).reshape(B, N)
        return [rows[b, :n].copy() for b, n in enumerate(counts)]
    if host_table is not None:
        return host_table.fetch(table).reshape(B, N)
    return table.numpy().view(TRACK_DTYPE).reshape(B, N)


def _dots_from_prior(st, prior):
    """Both images' dots of every prior row: identification around the prior in the reference images and
    around the predicted positions in the gradient images, then the wide second search of those missed
    (:mod:`tracking.wide_search`). Returns the dots ``r`` and ``g``, the predictor's displacement and
    significance, and the prior's rows on the device."""
    B, N = st.B, prior.shape[-2]
    M = B * N
    s, device, ident = st.settings, st.device, st.ident
    if prior.ndim == 2:  # one set for all pairs, repeated on the device
        one = st.arr(prior, wp.vec2d)
        on_device = wp.empty(M, dtype=wp.vec2d, device=device)
        wp.launch(ck.repeat_rows, dim=M, inputs=[one, N, on_device], device=device)
    else:
        on_device = st.arr(prior.reshape(M, 2), wp.vec2d)
    all_ids = wp.empty(M, dtype=wp.int32, device=device)
    wp.launch(ck.row_numbers, dim=M, inputs=[all_ids], device=device)
    r = ident.identify(st.refs, 0, on_device, all_ids, M, wide=False)
    base = wp.empty(M, dtype=wp.vec2d, device=device)
    wp.launch(ik.reference_or_prior, dim=M, inputs=[r["x"], r["y"], on_device, base], device=device)
    if s.predictor != "correlation":
        g = ident.identify(st.grads, 1, base, all_ids, M, wide=True)
        uv_pred = wp.empty(M, dtype=wp.vec2d, device=device)
        quality = wp.empty(M, dtype=wp.float64, device=device)
        return r, g, uv_pred, quality, on_device
    uv_pred, quality = _predict(st.refs, st.grads, base, B, N, s, device, st.excluded)
    pred_g = wp.empty(M, dtype=wp.vec2d, device=device)
    wp.launch(ik.predicted_position, dim=M, inputs=[base, uv_pred, pred_g], device=device)
    g = ident.identify(st.grads, 1, pred_g, all_ids, M, wide=False)
    wide_search_stack(
        lambda ids, n_ids: ident.identify(st.grads, 1, pred_g, ids, n_ids, wide=True),
        r,
        g,
        pred_g,
        per_frame=N,
        pairs=B,
        window=2 * st.geometry[0].half_g + 1,
        board=ident.board,
        device=device,
    )
    return r, g, uv_pred, quality, on_device


def _dots_without_prior(st):
    """Standard tracking: each pair's dots identified in both images on their own (on the host:
    :meth:`tracking.identify.StackIdentification.standard`), the reference dots' displacements predicted,
    and the dots paired (:func:`tracking.match.pair_dots`), laid out in rows as a prior's
    (:func:`tracking.match.paired_rows`). Returns ``r``, ``g``, the predictor's displacement and
    significance, and each pair's count of reference dots (its table's rows)."""
    s, device, B = st.settings, st.device, st.B
    ref_np, grad_np = st.refs.numpy(), st.grads.numpy()
    found_r = st.ident.standard(ref_np, 0, st.excluded)
    found_g = st.ident.standard(grad_np, 1, st.excluded)
    counts = [len(f["x"]) for f in found_r]
    n = max(max(counts), 1)
    ref_xy = np.full((B, n, 2), np.nan)
    for b, f in enumerate(found_r):
        ref_xy[b, : counts[b]] = np.stack([f["x"], f["y"]], axis=1)
    uv = np.full((B, n, 2), np.nan)
    q = np.full((B, n), np.nan)
    if s.predictor == "correlation":
        uv_w, q_w = _predict(st.refs, st.grads, st.arr(ref_xy.reshape(-1, 2), wp.vec2d), B, n, s, device, st.excluded)
        uv, q = uv_w.numpy().reshape(B, n, 2), q_w.numpy().reshape(B, n)
    partners = [
        pair_dots(ref_xy[b, : counts[b]] + np.nan_to_num(uv[b, : counts[b]]), found_r[b], found_g[b], s)
        for b in range(B)
    ]
    rows = max(max(c + len(g["x"]) - int(np.count_nonzero(p >= 0)) for c, g, p in zip(counts, found_g, partners,
                                                                                        strict=True)), 1)  # fmt: skip
    laid = [paired_rows(fr, fg, p, rows) for fr, fg, p in zip(found_r, found_g, partners, strict=True)]
    r = _rows_on_device(st, [a for a, _ in laid])
    g = _rows_on_device(st, [b for _, b in laid])
    uv_rows = np.full((B, rows, 2), np.nan)
    q_rows = np.full((B, rows), np.nan)
    for b, c in enumerate(counts):
        uv_rows[b, :c], q_rows[b, :c] = uv[b, :c], q[b, :c]
    return r, g, st.arr(uv_rows.reshape(-1, 2), wp.vec2d), st.arr(q_rows.ravel(), wp.float64), counts


def _rows_on_device(st, pairs):
    """Per-pair row dicts (:func:`tracking.match.paired_rows`) as one stack's dots on the device, the
    identification's types (the dot maps stay on the host)."""
    out = {}
    for key in pairs[0]:
        a = np.concatenate([p[key] for p in pairs])
        if key == "dotmap":
            out[key] = a
        elif a.dtype.kind == "f":
            out[key] = st.arr(a, wp.float64)
        else:
            out[key] = st.arr(a.astype(np.int32), wp.int32)
    return out


def _misregistered(st, xy, uv, matched, outlier, correction):
    """The registration check of standard tracking (:func:`tracking.register.misregistered`) for the rows
    still matched after the outlier test: an (M,) int32 Warp array, 1 where MISREGISTERED."""
    s, B = st.settings, st.B
    shared = correction[0]
    keep = (matched.numpy() != 0) & (outlier.numpy() == 0)
    M = len(keep)
    N = M // B
    sh = shared.numpy()
    uv_cc = sh[M:] - sh[:M]
    xy_h, uv_h = xy.numpy(), uv.numpy()
    uv_cc = np.where(np.isfinite(uv_cc).all(axis=1)[:, None], uv_cc, uv_h)
    out = np.zeros(M, dtype=np.int32)
    ref_np, grad_np = st.refs.numpy(), st.grads.numpy()
    for b in range(B):
        rows = b * N + np.flatnonzero(keep[b * N : (b + 1) * N])
        if rows.size:
            out[rows] = misregistered(
                ref_np[b], grad_np[b], xy_h[rows], uv_cc[rows], uv_h[rows], half=st.geometry[0].half_r,
                k=s.outlier_neighbours, tolerance=s.registration_tolerance, device=st.device,
            )  # fmt: skip
    return st.arr(out, wp.int32)


def _predict(refs, grads, base, B, N, settings, device, excluded=None):
    """The correlation predictor of every pair (:func:`tracking.predict.predict_displacement_stack`), at ``base``.

    Pairs whose pass schedule differs (it depends on the number of dots inside the image) are run in
    groups; usually all pairs share one. On the CPU, or with a mask (``excluded``), the host engine.
    """
    if wp.get_device(device).is_cpu or excluded is not None:
        return _predict_on_host(refs, grads, base, B, N, settings, device, excluded)
    H, W = refs.shape[1:]
    count = wp.zeros(B, dtype=wp.int32, device=device)
    wp.launch(ik.count_inside, dim=B * N, inputs=[base, N, H, W, count], device=device)
    plans = _pass_plans(count.numpy(), (H, W), settings.predictor_windows)
    xy = base.reshape((B, N))
    if len(plans) == 1:
        ((sizes, density, _),) = plans.values()
        uv, q = predict_displacement_stack(refs, grads, xy, sizes=sizes, density=density, device=device)
        return uv.reshape((B * N,)), q.reshape((B * N,))
    uv = np.empty((B, N, 2))
    q = np.empty((B, N))
    host_xy = xy.numpy()
    for sizes, density, members in plans.values():
        sel = np.array(members)
        uv_sel, q_sel = predict_displacement_stack(
            _pairs_of(refs, sel), _pairs_of(grads, sel), host_xy[sel], sizes=sizes, density=density, device=device
        )
        uv[sel], q[sel] = uv_sel.numpy(), q_sel.numpy()
    return (
        wp.array(uv.reshape(-1, 2), dtype=wp.vec2d, device=device),
        wp.array(q.ravel(), dtype=wp.float64, device=device),
    )


def _pass_plans(inside, shape, windows):
    """The predictor's pass schedules of pairs with ``inside`` dots inside their ``shape`` (H, W) images:
    ``{key: (sizes, density, pairs)}``, one entry per distinct schedule (its tile sizes and pooling blocks,
    :func:`tracking.predict.predictor_passes`), with the density of the fewest dots that give it and its
    pairs in order. Each distinct count is worked out once: a stack's pairs mostly share one.

    Examples
    --------
    >>> plans = _pass_plans(np.array([5120, 5120, 40, 5120]), (512, 512), (64, 32, 16, 16))
    >>> [(sizes, pairs) for sizes, _, pairs in plans.values()]
    [([64], [2]), ([64, 32, 16, 16], [0, 1, 3])]
    """
    plans, keys = {}, []
    counts, which = np.unique(inside, return_inverse=True)
    for n_in in counts:
        sizes, density = predictor_passes(shape, int(n_in), windows)
        keys.append((tuple(sizes), tuple(pooling_block(density, z) for z in sizes)))
        plans.setdefault(keys[-1], (sizes, density, []))
    for b, c in enumerate(which.tolist()):
        plans[keys[c]][2].append(b)
    return plans


def _predict_on_host(refs, grads, base, B, N, settings, device, excluded=None):
    """The predictor's host engine, for the CPU and for masks: :func:`tracking.predict.predict_displacement`
    pair by pair (its pocketfft correlation takes an eighth of the time of the tile kernels on the CPU;
    the Warp arrays are read where they lie), the pixels ``excluded`` left out."""
    xy = base.numpy().reshape(B, N, 2)
    uv = np.empty((B, N, 2))
    q = np.empty((B, N))
    ref_np, grad_np = refs.numpy(), grads.numpy()
    for b in range(B):
        uv[b], q[b] = predict_displacement(
            ref_np[b], grad_np[b], xy[b], window_sizes=settings.predictor_windows,
            mask=None if excluded is None else excluded[b], device=device,
        )  # fmt: skip
    return (
        wp.array(uv.reshape(-1, 2), dtype=wp.vec2d, device=device),
        wp.array(q.ravel(), dtype=wp.float64, device=device),
    )


def _confirmed(xy, uv, good, query, B, N, settings, device):
    """``_confirmed_by_neighbours`` of every pair (:mod:`tracking.neighbours`)."""
    ok = confirmed_by_neighbours_stack(
        xy.reshape((B, N)),
        uv.reshape((B, N)),
        good.reshape((B, N)),
        query.reshape((B, N)),
        k=settings.outlier_neighbours,
        threshold=settings.outlier_threshold,
        epsilon=settings.outlier_epsilon,
        tolerance=settings.predictor_tolerance,
        device=device,
    )
    return ok.reshape((B * N,))


def _outliers(xy, uv, matched, B, N, settings, device):
    """``_neighbour_outliers`` of every pair's matched dots (:mod:`tracking.neighbours`)."""
    bad = neighbour_outliers_stack(
        xy.reshape((B, N)),
        uv.reshape((B, N)),
        matched.reshape((B, N)),
        k=settings.outlier_neighbours,
        threshold=settings.outlier_threshold,
        epsilon=settings.outlier_epsilon,
        device=device,
    )
    return bad.reshape((B * N,))
