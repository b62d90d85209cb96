"""Each step of a ``track_pair`` run checked against its NumPy reference, on the run's own inputs.

:func:`record_steps` wraps the Warp steps that a run calls (window measurement, model
fit, first-moment step, neighbour tests, registration) so that every call also runs the step's reference
(:mod:`tracking.reference`) on the same arguments, at the moment of the call; :func:`assert_steps_agree`
compares the two results of every call. ``track_pair`` is a stack of one for the stacked tracker: its
neighbour tests and registration are recorded there, and its model fit (``fit_stack``) against the fit
pair by pair (:func:`_fit_pair`) on the NumPy references of its two steps.
"""


import numpy as np
import warp as wp
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.tracking import identify, reference, register, stack
from synthbos.tracking.dotfit import fit_window_half
from synthbos.tracking.settings import MODEL_WIDTH_RANGE, DotStatus, distortion_options, start_width


def _windows_reference(*args, full_maps=True, **kw):
    out = reference.measure_windows_numpy(*args, **kw)
    if not full_maps:
        c = kw["map_half"]
        out["cross"] = out.pop("dotmap")[:, [c, c, c, c - 1, c + 1], [c, c - 1, c + 1, c, c]]
    return out


_FOUND = ("x", "y", "eta", "i0", "flags")


def _fit_pair(images, founds, eta0, saturation, noise, settings):
    """One pair's model fit on the NumPy references (:func:`tracking.reference.fit_dots_numpy` and
    :func:`tracking.reference.moment_shifts_numpy`), rows of one index partners: per image a dict of
    ``params`` (N, 5; NaN where not found), ``ok``, ``shared_xy`` (NaN where not matched) and ``moved``."""
    half, render_half = fit_window_half(eta0)
    eta = np.concatenate([f["eta"][np.isfinite(f["x"])] for f in founds])
    sigma0 = float(start_width(np.median(eta) if eta.size else np.nan, eta0))
    starts = []
    for found in founds:
        idx = np.flatnonzero(np.isfinite(found["x"]))
        # the three-point peak is that of the pixel-broadened dot (variance sigma0^2 + 1/12, same flux)
        peak = found["i0"][idx] * (1.0 + 1.0 / (12.0 * sigma0**2))
        starts.append((idx, np.stack([found["x"][idx], found["y"][idx], peak, np.full(idx.size, sigma0),
                                      np.zeros(idx.size)], axis=1)))  # fmt: skip
    (idx_r, start_r), (idx_g, start_g) = starts
    pos_g = np.full(len(founds[1]["x"]), -1)
    pos_g[idx_g] = np.arange(idx_g.size)
    pair_r = pos_g[idx_r]
    pair = np.full(idx_r.size + idx_g.size, -1)
    has = np.flatnonzero(pair_r >= 0)
    pair[has] = idx_r.size + pair_r[has]
    pair[idx_r.size + pair_r[has]] = has
    frame = np.r_[np.zeros(idx_r.size, np.int64), np.ones(idx_g.size, np.int64)]
    params, ok, shared = reference.fit_dots_numpy(
        images, np.vstack([start_r, start_g]), half=half, render_half=render_half, frame=frame, partner=pair,
        saturation=saturation, iterations=settings.fit_iterations,
        sigma_range=(MODEL_WIDTH_RANGE[0] * eta0, MODEL_WIDTH_RANGE[1] * eta0),
    )  # fmt: skip
    moved = np.zeros(len(params), dtype=bool)
    if settings.distortion != "none":
        d, moved = reference.moment_shifts_numpy(
            images, params, half=render_half, frame=frame, partner=pair, saturation=saturation, noise=noise,
            chi2=settings.distortion_chi2, **distortion_options(settings.distortion),
        )  # fmt: skip
        params[:, :2] += d
        shared[moved] = np.where(np.isfinite(shared[moved]), params[moved, :2], np.nan)
    fits = []
    for (idx, _), found, rows in zip(starts, founds, (slice(0, idx_r.size), slice(idx_r.size, None)), strict=True):
        n = len(found["x"])
        f = {"params": np.full((n, 5), np.nan), "ok": np.zeros(n, dtype=bool), "shared_xy": np.full((n, 2), np.nan),
             "moved": np.zeros(n, dtype=bool)}  # fmt: skip
        for key, value in (("params", params), ("ok", ok), ("shared_xy", shared), ("moved", moved)):
            f[key][idx] = value[rows]
        fits.append(f)
    return fits


def _take_model(found, fit):
    """The model fit's position, width and peak replace the dot's (failed fits keep their last step,
    FIT_FALLBACK; a dot moved to its first moment, DISTORTED)."""
    params = fit["params"]
    has = np.isfinite(params[:, 0])
    for key, col in (("x", 0), ("y", 1), ("eta", 3), ("i0", 2)):
        found[key] = np.where(has, params[:, col], found[key])
    found["flags"][has & ~fit["ok"]] |= DotStatus.FIT_FALLBACK
    found["flags"][has & fit["moved"]] |= DotStatus.DISTORTED


def _fit_stack_reference(refs, grads, r, g, *, eta0, sat_frames, noise_frames, settings, take=True, **_):
    """What ``fit_stack`` computes, pair by pair (:func:`_fit_pair`): the fitted rows' fields (replaced
    only with ``take``) and the common-shape positions."""
    refs, grads = np.asarray(refs), np.asarray(grads)  # (on the host: record_steps' _host)
    n = r["x"].shape[0] // refs.shape[0]
    sat, noise = np.asarray(sat_frames).reshape(-1, 2), np.asarray(noise_frames).reshape(-1, 2)
    out = {f"{k}_{which}": [] for k in _FOUND for which in "rg"}
    shared = [[], []]
    for b in range(refs.shape[0]):
        rows = slice(b * n, (b + 1) * n)
        founds = [{k: found[k].numpy()[rows].copy() for k in _FOUND} for found in (r, g)]
        fits = _fit_pair((refs[b], grads[b]), founds, float(eta0[b]), sat[b], noise[b], settings)
        for found, fit, which in zip(founds, fits, "rg", strict=True):
            if take:
                _take_model(found, fit)
            for k in _FOUND:
                out[f"{k}_{which}"].append(found[k])
        shared[0].append(fits[0]["shared_xy"])
        shared[1].append(fits[1]["shared_xy"])
    out = {k: np.concatenate(v) for k, v in out.items()}
    out["shared"] = np.concatenate(shared[0] + shared[1])
    return out


def _fit_stack_result(result, refs, grads, r, g, **_):
    """``fit_stack``'s result as :func:`_fit_stack_reference` gives it (its fields are changed in place)."""
    out = {f"{k}_{which}": found[k].numpy().copy() for k in _FOUND for which, found in (("r", r), ("g", g))}
    out["shared"] = result.numpy().copy()
    return out


#: step -> (the module that calls it, the name it calls, its reference)
STEPS = {
    "measure_windows": (identify, "measure_windows", _windows_reference),
    "registration_offsets": (register, "registration_offsets", reference.registration_offsets_numpy),
    "stack.fit_stack": (stack, "fit_stack", _fit_stack_reference),
    "stack.neighbour_outliers_stack": (stack, "neighbour_outliers_stack", reference.neighbour_outliers_numpy),
    "stack.confirmed_by_neighbours_stack": (
        stack,
        "confirmed_by_neighbours_stack",
        reference.confirmed_by_neighbours_numpy,
    ),
}
#: how a step's result is recorded, where not as it is returned
_RESULTS = {"stack.fit_stack": _fit_stack_result}


def _copy(result):
    if isinstance(result, wp.array):  # a stacked step's (B, N) flags
        return (result.numpy().copy(),)
    if isinstance(result, dict):
        return {k: np.array(v) for k, v in result.items()}
    return tuple(np.array(v) for v in result)


def _host(a):
    """A Warp array as a NumPy array (the references take host arrays; on a GPU the steps get device ones)."""
    return a.numpy() if isinstance(a, wp.array) else a


def record_steps(monkeypatch):
    """``{step: list of (warp result, reference result)}``, filled as the pipeline runs."""
    calls = {name: [] for name in STEPS}
    for name, (caller, attr, ref) in STEPS.items():
        warp_step = getattr(caller, attr)

        def both(*args, device=None, _warp=warp_step, _ref=ref, _calls=calls[name], _name=name, **kw):
            # before the pipeline changes any input in place
            expected = _ref(*(_host(a) for a in args), **{k: _host(v) for k, v in kw.items()})
            if isinstance(expected, np.ndarray):
                expected = (expected,)
            got = _warp(*args, device=device, **kw)
            # (copied: a step may reuse its output arrays on the next call)
            _calls.append((_RESULTS[_name](got, *args, **kw) if _name in _RESULTS else _copy(got), expected))
            return got

        monkeypatch.setattr(caller, attr, both)
    return calls


def _pairs(got, expected):
    if isinstance(got, dict):
        assert set(got) == set(expected)
        return [(got[k], expected[k]) for k in sorted(got)]
    return list(zip(got, expected, strict=True))


def assert_steps_agree(calls, *, atol=1e-10):
    """Every recorded call's Warp result equals its reference's (booleans and integers exactly)."""
    for name, results in calls.items():
        for got, expected in results:
            for g, e in _pairs(got, expected):
                g, e = np.asarray(g), np.asarray(e)
                if g.dtype.kind in "biu":
                    assert_array_equal(g, e, err_msg=name)
                else:
                    assert_allclose(g, e, rtol=0, atol=atol, equal_nan=True, err_msg=name)
