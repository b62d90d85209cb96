"""Each step of a ``track_pair`` run checked against its NumPy reference, on the run's own inputs.

:func:`record_steps` wraps the Warp steps that a run calls (window measurement, model
fit, first-moment step, neighbour tests, registration) so that every call also runs the step's reference
(:mod:`tracking.reference`) on the same arguments, at the moment of the call; :func:`assert_steps_agree`
compares the two results of every call.
"""

import numpy as np
import warp as wp
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.tracking import identify, pipeline, reference


def _windows_reference(*args, full_maps=True, **kw):
    out = reference.measure_windows_numpy(*args, **kw)
    if not full_maps:
        c = kw["map_half"]
        out["cross"] = out.pop("dotmap")[:, [c, c, c, c - 1, c + 1], [c, c - 1, c + 1, c, c]]
    return out


#: step -> (the module that calls it, its reference)
STEPS = {
    "measure_windows": (identify, _windows_reference),
    "fit_dots": (pipeline, reference.fit_dots_numpy),
    "moment_shifts": (pipeline, reference.moment_shifts_numpy),
    "neighbour_outliers_stack": (pipeline, reference.neighbour_outliers_numpy),
    "confirmed_by_neighbours_stack": (pipeline, reference.confirmed_by_neighbours_numpy),
    "registration_offsets": (pipeline, reference.registration_offsets_numpy),
}


def _copy(result):
    if isinstance(result, wp.array):  # a stacked step's (B, N) flags
        return (result.numpy().copy(),)
    if isinstance(result, dict):
        return {k: np.array(v) for k, v in result.items()}
    return tuple(np.array(v) for v in result)


def record_steps(monkeypatch):
    """``{step: list of (warp result, reference result)}``, filled as the pipeline runs."""
    calls = {name: [] for name in STEPS}
    for name, (caller, ref) in STEPS.items():
        warp_step = getattr(caller, name)

        def both(*args, device=None, _warp=warp_step, _ref=ref, _calls=calls[name], **kw):
            expected = _ref(*args, **kw)  # before the pipeline changes any input in place
            if isinstance(expected, np.ndarray):
                expected = (expected,)
            got = _warp(*args, device=device, **kw)
            _calls.append((_copy(got), expected))  # a step may reuse its output arrays on the next call
            return got

        monkeypatch.setattr(caller, name, both)
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
