"""Each step of a ``track_pair`` run checked against its NumPy reference, on the run's own inputs.

:func:`record_steps` wraps the Warp steps that a run calls (window measurement, model
fit, first-moment step, neighbour tests, registration) so that every call also runs the step's reference
(:mod:`tracking.reference`) on the same arguments, at the moment of the call; :func:`assert_steps_agree`
compares the two results of every call. A run that ``track_pair`` hands to the stacked tracker (a stack of
one) is recorded there: its neighbour tests, and its model fit (``fit_stack``) against the per-pair fit
(``pipeline._fit_models`` and ``_take_model``) on the NumPy references of its two steps.
"""

from unittest import mock

import numpy as np
import warp as wp
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.tracking import identify, pipeline, reference, stack


def _windows_reference(*args, full_maps=True, **kw):
    out = reference.measure_windows_numpy(*args, **kw)
    if not full_maps:
        c = kw["map_half"]
        out["cross"] = out.pop("dotmap")[:, [c, c, c, c - 1, c + 1], [c, c - 1, c + 1, c, c]]
    return out


_FOUND = ("x", "y", "eta", "i0", "flags")


def _without_device(ref):
    return lambda *args, device=None, **kw: ref(*args, **kw)


def _fit_stack_reference(refs, grads, r, g, *, eta0, sat_frames, noise_frames, settings, **_):
    """What ``fit_stack`` computes, pair by pair: the per-pair fit with the NumPy references of the model
    fit and the first-moment step; the fitted rows' fields and the common-shape positions."""
    n = r["x"].shape[0] // refs.shape[0]
    sat, noise = sat_frames.numpy().reshape(-1, 2), noise_frames.numpy().reshape(-1, 2)
    out = {f"{k}_{which}": [] for k in _FOUND for which in "rg"}
    shared = [[], []]
    with (
        mock.patch.object(pipeline, "fit_dots", _without_device(reference.fit_dots_numpy)),
        mock.patch.object(pipeline, "moment_shifts", _without_device(reference.moment_shifts_numpy)),
    ):
        for b in range(refs.shape[0]):
            rows = slice(b * n, (b + 1) * n)
            founds = [{k: found[k].numpy()[rows].copy() for k in _FOUND} for found in (r, g)]
            fits = pipeline._fit_models(
                (refs.numpy()[b], grads.numpy()[b]), founds, np.arange(n), float(eta0[b]),
                sat[b], noise[b], settings, None,
            )  # fmt: skip
            for found, fit, which in zip(founds, fits, "rg", strict=True):
                pipeline._take_model(found, fit)
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
    "fit_dots": (pipeline, "fit_dots", reference.fit_dots_numpy),
    "moment_shifts": (pipeline, "moment_shifts", reference.moment_shifts_numpy),
    "neighbour_outliers_stack": (pipeline, "neighbour_outliers_stack", reference.neighbour_outliers_numpy),
    "confirmed_by_neighbours_stack": (
        pipeline,
        "confirmed_by_neighbours_stack",
        reference.confirmed_by_neighbours_numpy,
    ),
    "registration_offsets": (pipeline, "registration_offsets", reference.registration_offsets_numpy),
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


def record_steps(monkeypatch):
    """``{step: list of (warp result, reference result)}``, filled as the pipeline runs."""
    calls = {name: [] for name in STEPS}
    for name, (caller, attr, ref) in STEPS.items():
        warp_step = getattr(caller, attr)

        def both(*args, device=None, _warp=warp_step, _ref=ref, _calls=calls[name], _name=name, **kw):
            expected = _ref(*args, **kw)  # before the pipeline changes any input in place
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
