"""A campaign's work items: render a pair; process one pair with one method at one noise level and score it.

Each item is a top-level function (it runs in worker processes) that writes one file atomically. A
score item has a device half (:func:`measure_item`: noise and the method on the processing device)
and a host half (:func:`finish_item`: scoring, density integration, the score file), so a campaign
that processes on a GPU can run the halves in different processes (``scheduling.run_pipeline``);
:func:`score_item` runs both.

The host half's costly steps that depend only on the pair, or repeat from item to item (the truth's
Delaunay triangulation, the dots' neighbours for the gradient fits, the LU factors of a least-squares
domain met before, the truth at a method's points and its gradient at the dots, the density truths on an
integration grid), are remembered in each process (``synthbos.memo``, by the contents of every input),
so a worker that scores several items of a pair does them once; the scores are byte-identical either way.
The scoring runs with one BLAS thread (:func:`score_result`).
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
import tomllib

import numpy as np
from synthbos.raytrace import add_noise, load_config, read_pair, render_pair, write_pair
from synthbos.raytrace.camera import camera_from_config
from synthbos.raytrace.pairfile import in_cone_spread_px
from threadpoolctl import ThreadpoolController

from synthbos.device import init_warp
from synthbos.memo import RecentResults

from . import scoring
from .integrate import score_density
from .registry import DENSE, DOTS, GRID, get_method
from .storage import save_scores

__all__ = [
    "by_pair_and_noise",
    "finish_item",
    "finish_items",
    "item_images",
    "measure_item",
    "measure_pair",
    "noisy_pair",
    "nominal_positions",
    "read_pair_cached",
    "render_item",
    "render_only",
    "score_item",
    "score_items",
    "score_pair",
    "score_result",
]


def render_item(config: dict, out: str, device) -> str:
    """Render one pair from ``config`` into the pair file ``out``."""
    write_pair(out, render_only(config, device))
    return out


def render_only(config: dict, device):
    """Render one pair from ``config`` and return it (``raytrace.Pair``), writing nothing."""
    init_warp()  # items may run in fresh worker processes: start Warp there quietly too
    return render_pair(config, device=device)


def nominal_positions(pair) -> np.ndarray:
    """The prior a tracking user has: the camera model's image of the known target dot positions."""
    cam = camera_from_config(load_config(tomllib.loads(pair.attrs["config"])))
    return cam.target_to_pixel(pair.target_xy_m)


def noisy_pair(pair, *, noise_percent: float, seeds=(0, 1), peak=None):
    """The pair's reference and gradient images with seeded sensor noise (``noise_percent`` of the peak)."""
    peak = float(pair.attrs.get("peak_intensity", 1.0)) if peak is None else peak
    ref = add_noise(pair.reference, percent=noise_percent, seed=seeds[0], peak=peak)
    grad = add_noise(pair.gradient, percent=noise_percent, seed=seeds[1], peak=peak)
    return ref, grad


def measure_pair(pair, method: str, *, noise_percent: float, seeds=(0, 1), peak=None, settings=None,
                 device=None, images=None):
    """The device part of an item: add the noise and run one method on its processing ``device``.

    ``images``: the pair's noisy images when already made (``noisy_pair`` with the same arguments).
    Returns the registry's ``MethodResult``; :func:`score_result` scores it on the host.
    """
    m = get_method(method)
    ref, grad = noisy_pair(pair, noise_percent=noise_percent, seeds=seeds, peak=peak) if images is None else images
    prior = nominal_positions(pair) if m.uses_prior else None
    settings = m.settings() if settings is None else settings
    return m.run(ref, grad, prior_xy=prior, settings=settings, device=device)


def score_pair(pair, method: str, *, noise_percent: float, seeds=(0, 1), peak=None, settings=None, device=None):
    """Process one pair with one method at one noise level and return its error arrays.

    :func:`measure_pair` (noise and the method, on ``device``) followed by :func:`score_result`.

    Returns
    -------
    dict of arrays
        See :func:`score_result`.
    """
    res = measure_pair(pair, method, noise_percent=noise_percent, seeds=seeds, peak=peak, settings=settings,
                       device=device)
    return score_result(pair, method, res)


def score_result(pair, method: str, res) -> dict:
    """Score one method's result on a pair against the pair's truth (host work).

    Returns
    -------
    dict of arrays
        ``error`` (displacement error magnitude at each scored point, px), ``true_mag`` (true
        displacement magnitude there, for the threshold split), ``grad_error`` (Frobenius norm of the
        displacement-gradient error), ``threshold`` (half the std of Eq. 4's displacement magnitudes),
        ``measured`` / ``expected`` (for the yield), ``spread`` (the in-cone spread at each scored point, px,
        NaN where the pair holds no ray covariance; see ``scoring``); and the density errors of the method's result
        integrated by ``integrate.DENSITY_SOLVER`` against both truths (``integrate.score_density``).

    Notes
    -----
    The scoring runs with one thread in the BLAS and OpenMP libraries (``threadpoolctl``), as a campaign's
    worker processes run it: its linear algebra is thousands of 2 x 2 and 3 x 3 solves (the barycentric
    transforms of a triangulation, the gradient fits), for which a pool of threads per call only costs
    (``bench_stages`` scored a tracking item in 0.59-1.9 s with two BLAS threads on a busy two-core machine,
    in 0.08 s with one; 2026-11-27, docs/benchmarks.md). The numbers are the same either way.
    """
    with _one_blas_thread():
        return _score_result(pair, method, res)


@functools.cache
def _blas_controller() -> ThreadpoolController:
    """The process's BLAS and OpenMP libraries (those loaded once this module and its imports are)."""
    return ThreadpoolController()


_blas_lock = threading.Lock()
_blas_hold = {"users": 0, "limiter": None}  # scorings in progress in this process, and their limiter


@contextlib.contextmanager
def _one_blas_thread():
    """One BLAS/OpenMP thread while any thread of the process scores; the setting before is back once the
    last one is done (the libraries keep one setting per process, so concurrent scorings share it)."""
    with _blas_lock:
        if _blas_hold["users"] == 0:
            _blas_hold["limiter"] = _blas_controller().limit(limits=1)
        _blas_hold["users"] += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_hold["users"] -= 1
            if _blas_hold["users"] == 0:
                _blas_hold["limiter"].restore_original_limits()
                _blas_hold["limiter"] = None


def _score_result(pair, method: str, res) -> dict:
    """:func:`score_result`, in the calling thread's BLAS set-up."""
    m = get_method(method)
    valid = pair.valid & np.all(np.isfinite(pair.displacement_px), axis=1)
    threshold = scoring.split_threshold(pair.theory_px[valid])
    spread = _spread(pair)
    uv = res.uv
    if m.kind == GRID or (m.kind == DOTS and not m.uses_prior):  # the truth interpolated to its points
        truth, spread = _truth_at_points(pair.reference_px[valid], pair.displacement_px[valid], spread[valid], res.xy)
        keep = np.all(np.isfinite(truth), axis=1)
        measured = keep & res.valid
    else:  # at the rendered dots: tracked (one row per prior dot), or sampled from a dense field
        if m.kind == DENSE:
            ny, nx = res.grid_shape
            field = np.where(res.valid[:, None], res.uv, np.nan).reshape(ny, nx, 2)
            uv = scoring.sample_field(field, pair.reference_px)
        truth = pair.displacement_px
        keep = valid
        measured = valid & np.all(np.isfinite(uv), axis=1)
        if m.kind == DOTS:
            measured &= res.valid
    if m.kind == GRID:
        ny, nx = res.grid_shape
        gx, gy = res.xy[:, 0].reshape(ny, nx), res.xy[:, 1].reshape(ny, nx)
        g_meas = scoring.grid_gradient(res.uv[:, 0].reshape(ny, nx), res.uv[:, 1].reshape(ny, nx), gx, gy)
        g_true = scoring.grid_gradient(truth[:, 0].reshape(ny, nx), truth[:, 1].reshape(ny, nx), gx, gy)
        g_meas, g_true = g_meas.reshape(-1, 2, 2), g_true.reshape(-1, 2, 2)
    else:
        points = res.xy if m.kind == DOTS and not m.uses_prior else pair.reference_px
        at = np.where(measured[:, None], points, np.nan)
        # each field is fitted as on its own (``scattered_gradient``): the truth's fit, the same for every
        # item of a pair that measured the same dots, is remembered
        g_meas = scoring.scattered_gradient(at, uv)
        g_true = _true_gradients.get([at, truth], lambda: _read_only(scoring.scattered_gradient(at, truth)))
    err = scoring.vector_errors(uv, truth)
    grad_err = np.sqrt(np.sum((g_meas - g_true) ** 2, axis=(1, 2)))
    return score_density(pair, res) | {
        "error": np.where(measured, err, np.nan)[keep],
        "true_mag": np.hypot(truth[:, 0], truth[:, 1])[keep],
        "grad_error": np.where(measured, grad_err, np.nan)[keep],
        "threshold": np.float64(threshold),
        "spread": spread[keep],
        "measured": np.int64(measured[keep].sum()),
        "expected": np.int64(keep.sum()),
    }


#: The truth's displacement gradient at the dots, by dot positions and true displacements (the pair's, at
#: the dots an item measured: the same for most items of a pair).
_true_gradients = RecentResults(8)
#: The truth and the in-cone spread at a method's points (a correlation grid: the same for every item of a pair).
_truths_at_points = RecentResults(8)


def _truth_at_points(dot_xy, dot_disp, dot_spread, points_xy):
    """The dots' displacements and in-cone spreads interpolated to ``points_xy`` (``scoring.interpolate_truth``
    and ``scoring.interpolate_dots``), remembered by the contents of all four (read-only arrays)."""
    def compute():
        truth = scoring.interpolate_truth(dot_xy, dot_disp, points_xy)
        return _read_only(truth), _read_only(scoring.interpolate_dots(dot_xy, dot_spread, points_xy))

    return _truths_at_points.get([dot_xy, dot_disp, dot_spread, points_xy], compute)


def _read_only(a: np.ndarray) -> np.ndarray:
    """``a``, marked read-only: it is remembered and shared by the items that ask for it again."""
    a.flags.writeable = False
    return a


def _spread(pair) -> np.ndarray:
    """Each dot's in-cone spread (px, ``in_cone_spread_px``); NaN for a pair (or pair-like object) without
    ray covariances."""
    if getattr(pair, "ray_covariance_px2", None) is None:
        return np.full(len(pair.valid), np.nan)
    return in_cone_spread_px(pair)


def score_item(pair_path: str, method: str, noise: float, seeds, out: str, overrides: dict, device=None) -> str:
    """Score one (pair, method, noise) item into ``out`` (.npz), processing on ``device``."""
    init_warp()
    m = get_method(method)
    pair = read_pair(pair_path)
    res = measure_pair(pair, method, noise_percent=noise, seeds=seeds, settings=m.settings(overrides),
                       device=device)
    return finish_item(pair_path, method, res, out, device, pair=pair)


def score_items(*items) -> list[str]:
    """Several :func:`score_item` argument tuples in turn, in this process: the items of one pair at one
    noise level (a CPU campaign's task) share the noisy images and one tracker run, which tracking and
    tracking-cc both read (``synthbos.memo``); apart, each process would track the pair again."""
    return [score_item(*args) for args in items]


def by_pair_and_noise(items) -> list[tuple]:
    """:func:`score_item` argument tuples grouped by (pair file, noise level), in their order: the tasks of
    :func:`score_items`.

    Examples
    --------
    >>> by_pair_and_noise([("a.h5", "tracking", 0.0), ("a.h5", "tracking-cc", 0.0), ("a.h5", "tracking", 1.0)])
    [(('a.h5', 'tracking', 0.0), ('a.h5', 'tracking-cc', 0.0)), (('a.h5', 'tracking', 1.0),)]
    """
    groups: dict[tuple, list] = {}
    for args in items:
        groups.setdefault((args[0], args[2]), []).append(args)
    return [tuple(g) for g in groups.values()]


def measure_item(pair, pair_path: str, method: str, noise: float, seeds, out: str, overrides: dict,
                 device=None, *, images=None, settings=None):
    """The device half of :func:`score_item` on an already read ``pair``: the arguments of :func:`finish_item`.

    ``images``: the item's noisy images when already made (:func:`item_images`); ``settings``: its
    method's settings when already made (:func:`prepared_inputs`), else from ``overrides``.
    """
    m = get_method(method)
    res = measure_pair(pair, method, noise_percent=noise, seeds=seeds,
                       settings=m.settings(overrides) if settings is None else settings, device=device, images=images)
    return pair_path, method, res, out, device


def item_images(pair, args):
    """The noisy images a score item (:func:`measure_item` arguments without the pair) is measured on."""
    return noisy_pair(pair, noise_percent=args[2], seeds=args[3])


def prepared_inputs(pair, run, measured=()):
    """The noisy images of ``run`` (score items measured on the same images), and the settings of those of
    its ``measured`` items whose method reads something from the reference image (``Method.prepare``),
    with that read, by ``id`` of the item: the host work that :func:`measure_item` would do first, done
    ahead."""
    images = item_images(pair, run[0])
    settings = {}
    for args in measured:
        m = get_method(args[1])
        if m.prepare is not None:
            settings[id(args)] = m.prepare(images[0], m.settings(args[5]), args[-1])
    return images, settings


def read_pair_cached(path: str):
    """``read_pair``, remembering the last few files read (by path, size and modification time)."""
    st = os.stat(path)
    return _read_pair_cached(str(path), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=4)
def _read_pair_cached(path: str, size: int, mtime_ns: int):
    return read_pair(path)


def finish_item(pair_path: str, method: str, res, out: str, device=None, *, pair=None) -> str:
    """The host half of :func:`score_item`: score the result ``res`` and write ``out`` (.npz).

    ``pair`` is the pair read from ``pair_path`` (read here when None). The score file records the
    processing device (``process_device``).
    """
    pair = read_pair_cached(pair_path) if pair is None else pair
    scores = score_result(pair, method, res)
    scores["process_device"] = np.array(str(device) if device is not None else "default")
    save_scores(out, scores)
    return out


def process_items(hosts, items) -> list[str]:
    """In a worker: :func:`finish_items` for ``hosts``, then measure and finish each score item of
    ``items`` (:func:`measure_item` arguments without the pair), on the same noisy images of one pair."""
    done = finish_items(hosts)
    for args in items:
        done.append(finish_item(*measure_item(read_pair_cached(args[0]), *args)))
    return done


def finish_items(hosts) -> list[str]:
    """:func:`finish_item` for several items in turn (``hosts``: their :func:`measure_item` tuples).

    Items on the same noisy images of a pair, scored in one process, share the work they have in
    common (``synthbos.memo``): the pair's triangulation and, for ``tracking`` and ``tracking-cc``,
    that of the dots they both measured.
    """
    return [finish_item(*host) for host in hosts]
