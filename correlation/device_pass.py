"""The Warp engine of the multigrid correlation: host code of :mod:`correlation.pass_kernels`.

:func:`correlate_on_device` runs the passes and iterations of :func:`correlation.correlate_pair`
with every step on device arrays: the two images go up once, the vector field comes back once, and
nothing in between waits for the host. The order of the steps is :func:`correlation.passes.run_passes`',
the one the host engine (:mod:`correlation.host_pass`) follows too; :class:`_Plan` does each step with
Warp launches. Everything that depends only on the geometry (the schedule's window grids, spline
weights of the predictor, buffers) is prepared once per image shape and settings in a :class:`_Plan`
and kept for the next pair; on CUDA devices the plan's launches are recorded into a CUDA graph at the
second pair and replayed after that, on a stream of the plan's own. Where other threads launch on the
device too (a campaign's render threads, inside ``synthbos.device.launching``), the recording waits until
none is launching (``synthbos.device.recording_graph``).

The filling of rejected vectors (``validation.fill_by_interpolation``) starts as
``validation.replace_outliers`` does, with a fixed number of parallel median sweeps
(:data:`PARALLEL_SWEEPS`); a vector still unfilled after them (a hole wider than that many vectors)
is finished by a single-thread kernel that carries on exactly as the NumPy loop does, so both give the
same start; then ``validation.FILL_SWEEPS`` Jacobi sweeps of the Laplace equation, as on the host.

The host engine (:mod:`correlation.host_pass`) is the reference; the two agree to float32 rounding
(3e-5 px on the tests' and the benchmark's pairs, identical flags).
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

from synthbos import SynthbosError
from synthbos.device import recording_graph

from .deform import spline_weights
from .passes import Measured, pass_schedule, run_passes
from .rules import CONFIRM_CORRELATION, EDGE_MARGIN, SAMPLING_OFFSET
from .validation import FILL_SWEEPS
from .windows import window_validity
from .xcorr import rpc_spectral_filter

__all__ = [
    "PARALLEL_SWEEPS",
    "correlate_on_device",
    "device_supports",
    "fill_by_interpolation_on_device",
    "replace_outliers_on_device",
]

#: Parallel replacement sweeps per iteration (each fills one ring of a hole).
PARALLEL_SWEEPS = 4
#: ``validation.replace_outliers``' limit, kept by the single-thread finish.
MAX_SWEEPS = 100
#: Plans kept per process (one per image shape, settings, device and thread).
PLAN_CACHE_SIZE = 4
#: Record each plan's launches into a CUDA graph at its second pair and replay it (CUDA devices);
#: False launches every kernel from Python (for per-kernel profiles).
USE_CUDA_GRAPH = True

_INTERPOLATOR_CODES = {"cubic": 0, "keys": 1, "lanczos": 2}
_METHOD_CODES = {"gaussian": 0, "parabolic": 1, "centroid": 2}

_plans: OrderedDict = OrderedDict()
_plans_lock = threading.Lock()


def _warp():
    import warp as wp

    from synthbos.device import init_warp

    from . import line_kernels, pass_kernels

    init_warp()
    return wp, pass_kernels, line_kernels


def device_supports(settings):
    """Why the device path cannot run these settings, or None when it can.

    The windows' FFTs are Warp tile FFTs along both axes of a square tile: power-of-two window sizes
    of at least 4 px.
    """
    for s in settings.window_sizes:
        if s < 4 or s & (s - 1):
            return f"window size {s} px is not a power of two >= 4 (tile FFT)"
    return None


def _graph_replay(device):
    """Whether plans on this Warp device record and replay a graph (:data:`USE_CUDA_GRAPH`). Other
    threads may launch meanwhile: the recording waits for them (``synthbos.device.recording_graph``)."""
    return USE_CUDA_GRAPH and device.is_cuda


class _Iteration:
    """Buffers of one step of the schedule (:class:`correlation.passes.PassStep`)."""


class _Plan:
    """The Warp engine of :func:`correlation.passes.run_passes` for one image shape and settings.

    Buffers and spline weights are made once, here; each step method only enqueues launches on them and
    returns the buffers that hold its result, so that one walk of the schedule (:meth:`_launch_all`)
    is a fixed sequence of launches that a CUDA graph can record.
    """

    def __init__(self, shape, settings, device):
        wp, k, lk = _warp()
        self.wp, self.k, self.lines = wp, k, lk
        self.device = device
        self.settings = settings
        self.shape = shape
        h, w = shape
        f32, f64 = wp.float32, wp.float64
        zeros = self._zeros
        self.img = [zeros(shape, f32), zeros(shape, f32)]
        self.raw = {}  # input images as given (float32 or float64), by dtype
        self.col_stats = [zeros((w, 4), f64), zeros((w, 4), f64)]
        self.summary = zeros((2, 6), f64)
        self.valid_px = zeros(shape, f32)
        self.valid_is_ones = False
        self.steps = pass_schedule(shape, settings)
        self.prefilter = len(self.steps) > 1 and settings.interpolator == "cubic"
        if self.prefilter:
            self.coef = [zeros(shape, f32), zeros(shape, f32)]
            self.rows_tmp = zeros(shape, f32)
            self.line_rows = zeros((h, w), f64)
            self.line_cols = zeros((w, h), f64)
        else:
            self.coef = self.img
        self.passes = [self._pass_buffers(step) for step in self.steps if step.first_of_pass]
        self.iterations = [
            self._step_buffers(step, previous) for previous, step in zip((None, *self.steps), self.steps, strict=False)
        ]
        self.outputs = None  # what the last walk of the schedule returned: the buffers of the result
        self.graph = None
        self.runs = 0
        # The plan's own stream on a GPU: its uploads, launches and graph, recorded and replayed there
        # whatever stream another thread makes the device's current one meanwhile (Warp's ``numpy()``
        # switches it for its copy); None: the device's current stream (the CPU).
        self.stream = wp.Stream(device) if wp.get_device(device).is_cuda else None
        self.host = {}  # page-locked host copies of what the plan reads back (a GPU), by device array
        self.lock = threading.Lock()
        self._settle()

    def _settle(self):
        """Wait for the buffers just made: Warp zeroes and fills a new device array on the device's current
        stream, not the plan's, and nothing orders the two; a zeroing left in the queue could land after
        the plan's own upload (an image read back constant 0 by a second process driving the same GPU)."""
        if self.stream is not None:
            self.wp.synchronize_device(self.device)

    def _zeros(self, shape, dtype):
        return self.wp.zeros(shape, dtype=dtype, device=self.device)

    def _pass_buffers(self, step):
        """The buffers of one pass, shared by its iterations: planes, peak search, FFT spectral weights."""
        wp, k, s = self.wp, self.k, self.settings
        f32, i32 = wp.float32, wp.int32
        zeros = self._zeros
        g, size = step.grid, step.size
        ny, nx = len(g.yc), len(g.xc)
        rows, cols = len(g.rows), len(g.cols)
        ps = {
            "masked": zeros((ny, nx), i32),
            "zero": zeros((ny, nx), f32),
            "planes": zeros((ny * nx * size, size), f32),
            "norm": zeros(ny * nx, wp.float64),
            "kernel": k.correlate_windows_kernel(size, s.rpc),
        }
        if s.rpc:
            spectral = rpc_spectral_filter((size, size), s.rpc_diameter, half=False) / size**2
        else:
            spectral = np.full((size, size), 1.0 / size**2)
        ps["spectral"] = wp.array(spectral.astype(np.float32), dtype=f32, device=self.device)
        # shifted position (fftshift) of every sample of an unshifted plane, coded row * code + column
        shifted = (np.arange(size) + size // 2) % size
        code = int(k.PLANE_CODE)
        positions = (shifted[:, None] * code + shifted[None, :]).astype(np.int32)
        ps["positions"] = wp.array(positions, dtype=i32, device=self.device)
        # the peak search's weights (``CorrelationSettings.peak_selection``), unshifted like the planes
        select = s.peak_selection(size)
        select = np.ones((size, size)) if select is None else select[np.ix_(shifted, shifted)]
        ps["select"] = wp.array(select.astype(np.float32), dtype=f32, device=self.device)
        ps["peak_at"] = zeros(ny * nx, i32)
        ps["peak_values"] = zeros((ny * nx, 3), f32)
        if step.deform or s.iterations[step.pass_index] > 1:
            ps["def"] = [zeros((rows, cols), f32) for _ in range(3)]  # first, second, weight
            ps["du"] = [zeros((rows, cols), f32), zeros((rows, cols), f32)]
        return ps

    def _step_buffers(self, step, previous):
        """The buffers of one step: its predictor's spline weights from ``previous``'s nodes, its vectors,
        flags and filling scratch."""
        wp = self.wp
        f32, f64, i32 = wp.float32, wp.float64, wp.int32
        zeros = self._zeros
        g, ps = step.grid, self.passes[step.pass_index]
        ny, nx = len(g.yc), len(g.xc)
        rows = len(g.rows)
        it = _Iteration()
        if step.deform:
            q = SAMPLING_OFFSET
            py, px = previous.node
            weights = (
                spline_weights(py, g.rows + q),
                spline_weights(px, g.cols + q),
                spline_weights(py, step.node[0]),
                spline_weights(px, step.node[1]),
            )
            it.w = [wp.array(m.astype(np.float32), dtype=f32, device=self.device) for m in weights]
            it.s_pix = [zeros((rows, len(px)), f32) for _ in range(2)]
            it.s_node = [zeros((ny, len(px)), f32) for _ in range(2)]
            it.p = [zeros((ny, nx), f32), zeros((ny, nx), f32)]
        else:
            it.p = [ps["zero"], ps["zero"]]
        it.u, it.v = zeros((ny, nx), f64), zeros((ny, nx), f64)
        it.ratio, it.coef = zeros((ny, nx), f64), zeros((ny, nx), f64)
        it.flags = [zeros((ny, nx), i32) for _ in range(3)]
        it.ok = zeros((ny, nx), i32)
        it.rep = [[zeros((ny, nx), f64) for _ in range(2)] for _ in range(2)]  # ping-pong (u, v)
        it.todo = [zeros((ny, nx), i32), zeros((ny, nx), i32)]
        it.left = zeros(PARALLEL_SWEEPS, i32)
        it.scratch = zeros(ny * nx, f64)
        return it

    # ------------------------------------------------------- the steps (launches only, no host wait)

    def _launch(self, kernel, dim, inputs, block_dim=256):
        self.wp.launch(kernel, dim=dim, inputs=inputs, device=self.device, block_dim=block_dim, stream=self.stream)

    def _fetch(self, *arrays):
        """NumPy copies of the plan's device ``arrays``, read on the plan's stream: they wait for its own
        work only, not for what other threads queued on the device meanwhile (``numpy()`` reads on the
        legacy stream, which waits for every stream's work)."""
        wp = self.wp
        if self.stream is None:  # the CPU: numpy() is a view of the plan's buffers, which its next run overwrites
            return [a.numpy().copy() for a in arrays]
        hosts = []
        for a in arrays:
            key = (a.ptr, a.shape, a.dtype)
            if key not in self.host:
                self.host[key] = wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=True)
            wp.copy(self.host[key], a, stream=self.stream)
            hosts.append(self.host[key])
        wp.synchronize_stream(self.stream)
        return [h.numpy().copy() for h in hosts]

    def _put(self, dest, host):
        """Copy NumPy array ``host`` (``dest``'s dtype and shape) into ``dest`` on the plan's stream."""
        wp = self.wp
        wp.copy(dest, wp.array(np.ascontiguousarray(host), dtype=dest.dtype, device="cpu"), stream=self.stream)

    def _launch_all(self):
        """Every launch of one pair's passes: one walk of the schedule with this engine."""
        self.outputs = run_passes(self, self.steps)

    def interpolant(self):
        """The cubic B-spline prefilter of both images (Keys and Lanczos sample the images themselves)."""
        h, w, lk = *self.shape, self.lines
        if self.prefilter:
            for img, coef in zip(self.img, self.coef, strict=True):
                self._launch(lk.bspline3_prefilter_lines, h, [img, 1, self.line_rows, self.rows_tmp], lk.LOOP_BLOCK)
                self._launch(lk.bspline3_prefilter_lines, w, [self.rows_tmp, 0, self.line_cols, coef], lk.LOOP_BLOCK)

    def windows(self, step, previous, field):
        """The images to cut the step's windows from (the first, the second, the pixel weights) and their
        origin, and the predictor at the nodes: the images themselves at the first step, else the
        predictor and both deformed images computed from ``field``."""
        k = self.k
        it, ps, g = self.iterations[step.index], self.passes[step.pass_index], step.grid
        if field is None:
            return ([*self.img, self.valid_px], (int(g.rows[0]), int(g.cols[0]))), it.p
        q = SAMPLING_OFFSET
        wy_pix, wx_pix, wy_node, wx_node = it.w
        du, dv = ps["du"]
        first, second, weight = ps["def"]
        self._launch(k.spline_rows, it.s_pix[0].shape, [wy_pix, *field, *it.s_pix])
        self._launch(k.spline_cols, du.shape, [*it.s_pix, wx_pix, du, dv])
        self._launch(k.spline_rows, it.s_node[0].shape, [wy_node, *field, *it.s_node])
        self._launch(k.spline_cols, it.p[0].shape, [*it.s_node, wx_node, *it.p])
        origin = (float(g.rows[0] + q), float(g.cols[0] + q))
        code = _INTERPOLATOR_CODES[self.settings.interpolator]
        self._launch(
            k.deform_pair_weighted,
            du.shape,
            [*self.coef, du, dv, *origin, code, self.valid_px, int(g.rows[0]), int(g.cols[0]), float(EDGE_MARGIN),
             first, second, weight],
        )
        return ([first, second, weight], (0, 0)), it.p

    def correlate(self, step, windows):
        """One tiled launch: every window pair's correlation plane, norm and integer peak; returns the pass's
        buffers that hold them."""
        images, origin = windows
        ps, g = self.passes[step.pass_index], step.grid
        ny, nx = len(g.yc), len(g.xc)
        outputs = [ps["spectral"], ps["positions"], ps["select"], ps["planes"], ps["norm"], ps["peak_at"],
                   ps["peak_values"]]
        self.wp.launch_tiled(
            ps["kernel"],
            dim=[ny * nx],
            inputs=[*images, *origin, g.step, nx, *outputs],
            block_dim=self.k.window_threads(step.size),
            device=self.device,
            stream=self.stream,
        )
        return ps

    def fit_peaks(self, step, planes, predictor, coarse):
        """The peak fit and the tests before the median test (:func:`pass_kernels.fit_peaks`)."""
        s, ps, it, n = self.settings, planes, self.iterations[step.index], step.size
        coarse_uv = coarse if coarse is not None else [ps["zero"], ps["zero"]]
        self._launch(
            self.k.fit_peaks,
            it.u.shape,
            [
                ps["planes"], n, ps["norm"], ps["peak_at"], ps["peak_values"], *predictor,
                _METHOD_CODES[s.subpixel],
                int(not s.rpc),
                s.peak_ratio_threshold(),
                float(s.min_correlation) if step.judges_correlation else -np.inf,
                *coarse_uv,
                int(coarse is not None),
                float(s.max_disagreement * n),
                ps["masked"], it.u, it.v, it.ratio, it.coef, it.flags[0],
            ],
        )
        return Measured(it.u, it.v, it.ratio, it.coef, it.flags[0])

    def median_test(self, step, measured, raw):
        """The normalised median test and the confirmation by ``raw`` (:func:`pass_kernels.median_test`)."""
        s, k, it = self.settings, self.k, self.iterations[step.index]
        confirm_by = measured if raw is None else raw
        self._launch(k.measured_mask, it.ok.shape, [measured.flags, it.ok])
        self._launch(
            k.median_test,
            it.ok.shape,
            [
                measured.u, measured.v, it.ok,
                float(s.median_epsilon), float(s.median_threshold),
                int(raw is not None), float(s.confirm_tolerance), confirm_by.u, confirm_by.v,
                int(not s.rpc), measured.coef, float(CONFIRM_CORRELATION),
                measured.flags, it.flags[1],
            ],
        )
        return it.flags[1]

    def isolated_test(self, step, flags):
        """``ISOLATED`` added (:func:`pass_kernels.isolated_test`)."""
        it = self.iterations[step.index]
        self._launch(self.k.isolated_test, flags.shape, [flags, it.flags[2]])
        return it.flags[2]

    def fill(self, step, measured, flags):
        """The launches of the filling (:func:`_launch_fill`); returns the buffers of the filled field."""
        it = self.iterations[step.index]
        return _launch_fill(
            self.wp, self.k, self.device, measured.u, measured.v, flags, it.rep, it.todo, it.left, it.scratch,
            stream=self.stream,
        )

    def _raw(self, index, dtype):
        wp = self.wp
        key = (index, dtype)
        if key not in self.raw:
            self.raw[key] = wp.zeros(self.shape, dtype=dtype, device=self.device)
            self._settle()
        return self.raw[key]

    def upload(self, images, names, raise_for):
        """Both images up, checked and normalised on the device (``multigrid._checked_image``).

        The one wait for the device before the passes: reading back six numbers per image to raise
        ``raise_for(name, image, nonfinite)`` for images with non-finite pixels or constant ones.
        """
        wp, lk = self.wp, self.lines
        h, w = self.shape
        raws = []
        for idx, arr in enumerate(images):
            # float32 holds every value of these exactly; anything else goes up as float64
            exact32 = arr.dtype in (np.float32, np.uint8, np.int8, np.uint16, np.int16)
            dtype = wp.float32 if exact32 else wp.float64
            raw = self._raw(idx, dtype)
            self._put(raw, np.asarray(arr, dtype=np.float32 if exact32 else np.float64))
            stats, summary = self.col_stats[idx], self.summary[idx]
            self._launch(lk.column_stats, w, [raw, stats], lk.LOOP_BLOCK)
            self._launch(lk.combine_stats, 1, [stats, float(h * w), summary], lk.LOOP_BLOCK)
            self._launch(lk.column_moments, w, [raw, summary, stats], lk.LOOP_BLOCK)
            self._launch(lk.combine_moments, 1, [stats, float(h * w), summary], lk.LOOP_BLOCK)
            raws.append(raw)
        (summary,) = self._fetch(self.summary)
        for arr, name, (_, _, lo, hi, bad, _) in zip(images, names, summary, strict=True):
            if bad > 0 or lo == hi:
                raise raise_for(name, arr, int(bad))
        for idx, raw in enumerate(raws):
            self._launch(lk.normalise_image, self.shape, [raw, self.summary[idx], self.img[idx]], lk.LOOP_BLOCK)

    def run(self, images, valid_px, masked, *, names, raise_for):
        """One pair: upload (:meth:`upload`), pixel weights (None: all 1) and the per-pass masked
        windows, the passes, and the last iteration's field back."""
        wp = self.wp
        self.upload(images, names, raise_for)
        if valid_px is None:
            if not self.valid_is_ones:
                self._put(self.valid_px, np.ones(self.shape, dtype=np.float32))
                self.valid_is_ones = True
        else:
            self._put(self.valid_px, np.asarray(valid_px, dtype=np.float32))
            self.valid_is_ones = False
        for ps, m in zip(self.passes, masked, strict=True):
            self._put(ps["masked"], m.astype(np.int32))
        device = wp.get_device(self.device)
        use_graph = _graph_replay(device)
        if self.graph is None and self.runs > 0 and use_graph:
            with recording_graph(), wp.ScopedCapture(device=device, stream=self.stream) as capture:
                self._launch_all()
            self.graph = capture.graph
        if self.graph is not None and use_graph:
            wp.capture_launch(self.graph, stream=self.stream)
        else:
            self._launch_all()
        self.runs += 1
        (u, v), measured, flags = self.outputs
        u, v, ratio, coef, flags = self._fetch(u, v, measured.ratio, measured.coef, flags)
        return {"u": u, "v": v, "peak_ratio": ratio, "correlation": coef, "flags": flags, "node": self.steps[-1].node}


def _launch_replacement(wp, k, device, u, v, flags, rep, todo, left, scratch, stream=None):
    """Launches of ``validation.replace_outliers(u, v, flags != 0)`` on ``stream`` (None: the device's
    current one); returns the arrays holding the result.

    ``rep``: two pairs of (ny, nx) float64 arrays and ``todo`` two int32 arrays (ping-pong),
    ``left``: PARALLEL_SWEEPS int32, ``scratch``: ny nx float64.
    """
    shape = u.shape
    (ua, va), (ub, vb) = rep
    ta, tb = todo
    wp.launch(k.start_replacement, dim=shape, inputs=[u, v, flags, ua, va, ta, left], device=device, stream=stream)
    src, dst = (ua, va, ta), (ub, vb, tb)
    for sweep in range(PARALLEL_SWEEPS):
        wp.launch(k.replacement_sweep, dim=shape, inputs=[*src, *dst, left, sweep], device=device, stream=stream)
        src, dst = dst, src
    wp.launch(k.finish_replacement, dim=1, inputs=[*src, left, PARALLEL_SWEEPS, MAX_SWEEPS, scratch], device=device,
              stream=stream)
    return src[0], src[1]


def _launch_fill(wp, k, device, u, v, flags, rep, todo, left, scratch, sweeps=FILL_SWEEPS, stream=None):
    """Launches of ``validation.fill_by_interpolation(u, v, flags != 0)`` (arguments of
    :func:`_launch_replacement`); returns the arrays holding the result."""
    ru, _ = _launch_replacement(wp, k, device, u, v, flags, rep, todo, left, scratch, stream=stream)
    (ua, va), (ub, vb) = rep
    src, dst = ((ua, va), (ub, vb)) if ru is ua else ((ub, vb), (ua, va))
    for _ in range(sweeps):
        wp.launch(k.laplace_sweep, dim=u.shape, inputs=[*src, flags, *dst], device=device, stream=stream)
        src, dst = dst, src
    return src


def replace_outliers_on_device(u, v, invalid, *, device="cpu"):
    """``validation.replace_outliers(u, v, invalid)`` with the kernels of the Warp path.

    Parameters
    ----------
    u, v : (ny, nx) arrays
    invalid : (ny, nx) bool array
    device : str
        Warp device.

    Returns
    -------
    u, v : (ny, nx) float64 arrays
    """
    return _on_device(_launch_replacement, u, v, invalid, device)


def fill_by_interpolation_on_device(u, v, invalid, *, device="cpu"):
    """``validation.fill_by_interpolation(u, v, invalid)`` with the kernels of the Warp path.

    Parameters
    ----------
    u, v : (ny, nx) arrays
    invalid : (ny, nx) bool array
    device : str
        Warp device.

    Returns
    -------
    u, v : (ny, nx) float64 arrays
    """
    return _on_device(_launch_fill, u, v, invalid, device)


def _on_device(launch, u, v, invalid, device):
    """``launch`` (:func:`_launch_replacement` or :func:`_launch_fill`) on arrays copied to ``device``."""
    wp, k, _ = _warp()
    shape = np.shape(u)

    def arr(a, dtype):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device)

    def zeros(s, dtype):
        return wp.zeros(s, dtype=dtype, device=device)

    flags = arr(np.asarray(invalid, dtype=np.int32), wp.int32)
    rep = [[zeros(shape, wp.float64) for _ in range(2)] for _ in range(2)]
    todo = [zeros(shape, wp.int32) for _ in range(2)]
    ru, rv = launch(
        wp,
        k,
        device,
        arr(np.asarray(u, dtype=np.float64), wp.float64),
        arr(np.asarray(v, dtype=np.float64), wp.float64),
        flags,
        rep,
        todo,
        zeros(PARALLEL_SWEEPS, wp.int32),
        zeros(int(np.prod(shape)), wp.float64),
    )
    return ru.numpy(), rv.numpy()


def _plan_for(shape, settings, device):
    key = (str(device), tuple(shape), settings, threading.get_ident())
    with _plans_lock:
        plan = _plans.pop(key, None)
        if plan is None:
            plan = _Plan(tuple(shape), settings, str(device))
        _plans[key] = plan
        while len(_plans) > PLAN_CACHE_SIZE:
            _plans.popitem(last=False)
    return plan


def _default_error(name, arr, nonfinite):
    what = f"{nonfinite} non-finite pixels" if nonfinite else "constant"
    return SynthbosError(f"{name} is not an image to correlate: {what}")


def correlate_on_device(
    a, b, *, settings, valid_px=None, masked=None, device="cpu", raise_for=_default_error
):
    """The passes and iterations of :func:`correlation.correlate_pair` on one Warp device.

    Parameters
    ----------
    a, b : (H, W) real or integer arrays
        The reference and gradient images as given (checked for dtype and shape); they are brought
        to zero mean and unit variance on the device.
    settings : CorrelationSettings
    valid_px : (H, W) float32 array of 0 and 1, optional
        1 on pixels that take part in the correlation (no mask: all).
    masked : list of (ny, nx) bool arrays, optional
        Per pass, the windows more than half masked (default: from ``valid_px``,
        :func:`correlation.windows.window_validity`).
    device : str
        Warp device.
    raise_for : callable
        ``raise_for(name, image, nonfinite)`` gives the exception to raise for an image with
        non-finite pixels (``nonfinite`` > 0) or a constant one.

    Returns
    -------
    dict
        ``u``, ``v`` (filled field), ``peak_ratio``, ``correlation``, ``flags`` of the last
        iteration on its grid, ``node`` (its row and column coordinates) and ``masked`` (its windows
        more than half masked), as :func:`correlation.host_pass.correlate_on_host`.
    """
    reason = device_supports(settings)
    if reason is not None:
        raise SynthbosError(f"the Warp correlation cannot run these settings: {reason}")
    shape = np.shape(a)
    plan = _plan_for(shape, settings, device)
    if masked is None:
        masked = [window_validity(valid_px, step.grid)[1] for step in plan.steps if step.first_of_pass]
    with plan.lock:
        out = plan.run(
            (np.asarray(a), np.asarray(b)),
            valid_px,
            masked,
            names=("reference image", "gradient image"),
            raise_for=raise_for,
        )
    out["masked"] = masked[-1]
    return out
