"""The multigrid pass sequence, written once (correlation.passes): its schedule, the order in which its
walk calls an engine and what it hands each step, and the Warp engine's walk as a pure launch sequence.

The engines' results against each other are in test_device_pass.py, against synthesised truth in
test_multigrid.py.
"""

from dataclasses import replace

import numpy as np
import pytest
import warp as wp
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.benchmarks.bench_correlation import bump_field, synthetic_pair
from synthbos.correlation import CorrelationSettings, correlate_pair, device_pass
from synthbos.correlation.passes import Measured, pass_schedule, run_passes
from synthbos.correlation.rules import SAMPLING_OFFSET
from synthbos.correlation.windows import window_grid


def test_schedule_lays_out_every_iteration_of_every_pass():
    s = CorrelationSettings(window_sizes=(64, 32, 16), overlaps=(0.0, 0.5, 0.75), iterations=(2, 1, 3))
    steps = pass_schedule((200, 160), s)
    assert [(st.pass_index, st.iteration, st.size) for st in steps] == [
        (0, 0, 64), (0, 1, 64), (1, 0, 32), (2, 0, 16), (2, 1, 16), (2, 2, 16)
    ]
    assert [st.index for st in steps] == list(range(6))
    assert [st.deform for st in steps] == [False] + [True] * 5
    assert [st.first_deformed for st in steps] == [False, True, False, False, False, False]
    assert [st.first_of_pass for st in steps] == [True, False, True, True, False, False]
    assert [st.use_coarse for st in steps] == [False, False, True, True, True, True]
    assert [st.confirm for st in steps] == [False, True, False, False, True, True]
    # min_correlation judges the plain correlation and the vectors returned only
    assert [st.judges_correlation for st in steps] == [True, False, False, False, False, True]
    assert [st.last for st in steps] == [False] * 5 + [True]
    for st, (size, overlap) in zip(steps, [(64, 0.0)] * 2 + [(32, 0.5)] + [(16, 0.75)] * 3, strict=True):
        g = window_grid((200, 160), size, overlap)
        assert st.grid.step == g.step
        offset = SAMPLING_OFFSET if st.deform else 0.0
        assert_allclose(st.node[0], g.yc + offset, rtol=0, atol=0)
        assert_allclose(st.node[1], g.xc + offset, rtol=0, atol=0)
    no_confirm = pass_schedule((200, 160), CorrelationSettings(iterations=3, confirm_tolerance=0.0))
    assert not any(st.confirm for st in no_confirm)
    single = pass_schedule((64, 64), CorrelationSettings(window_sizes=(32,), iterations=1))
    assert len(single) == 1 and single[0].last and not single[0].deform and not single[0].first_deformed


class RecordingEngine:
    """An engine whose steps return labelled tokens and record what they were handed."""

    def __init__(self):
        self.calls = []

    def interpolant(self):
        self.calls.append(("interpolant",))

    def windows(self, step, previous, field):
        self.calls.append(("windows", step.index, None if previous is None else previous.index, field))
        return f"windows{step.index}", f"predictor{step.index}"

    def correlate(self, step, windows):
        self.calls.append(("correlate", step.index, windows))
        return f"planes{step.index}"

    def fit_peaks(self, step, planes, predictor, coarse):
        self.calls.append(("fit_peaks", step.index, planes, predictor, coarse))
        return Measured(*(f"{name}{step.index}" for name in Measured._fields))

    def median_test(self, step, measured, raw):
        self.calls.append(("median_test", step.index, measured.u, None if raw is None else raw.u))
        return f"median{step.index}"

    def isolated_test(self, step, flags):
        self.calls.append(("isolated_test", step.index, flags))
        return f"isolated{step.index}"

    def fill(self, step, measured, flags):
        self.calls.append(("fill", step.index, measured.u, flags))
        return f"field{step.index}"


def test_the_walk_hands_each_step_the_method_s_inputs():
    """The predictor of a pass's first iteration is the next iterations' coarse field (passes after the
    first); the previous iteration's measurement confirms (iterations after the first of a pass); every
    step deforms by the field its predecessor filled; the interpolant is made once, before the first
    deformation."""
    steps = pass_schedule((128, 128), CorrelationSettings(window_sizes=(32, 16), iterations=(2, 3)))
    engine = RecordingEngine()
    field, measured, flags = run_passes(engine, steps)
    assert (field, measured.ratio, measured.coef, flags) == ("field4", "ratio4", "coef4", "isolated4")
    expected = []
    for i, coarse, raw in [(0, None, None), (1, None, "u0"), (2, "predictor2", None), (3, "predictor2", "u2"),
                           (4, "predictor2", "u3")]:
        if i == 1:
            expected.append(("interpolant",))
        previous = None if i == 0 else i - 1
        expected += [
            ("windows", i, previous, None if i == 0 else f"field{i - 1}"),
            ("correlate", i, f"windows{i}"),
            ("fit_peaks", i, f"planes{i}", f"predictor{i}", coarse),
            ("median_test", i, f"u{i}", raw),
            ("isolated_test", i, f"median{i}"),
            ("fill", i, f"u{i}", f"isolated{i}"),
        ]
    assert engine.calls == expected


def test_the_walk_without_confirmation_hands_no_previous_measurement():
    steps = pass_schedule((128, 128), CorrelationSettings(iterations=(3, 2), confirm_tolerance=0.0))
    engine = RecordingEngine()
    run_passes(engine, steps)
    raws = [call[3] for call in engine.calls if call[0] == "median_test"]
    assert raws == [None] * 5


def test_warp_engine_walk_is_launches_only(device, monkeypatch):
    """The Warp engine's steps only enqueue launches: no array comes back to the host and nothing waits for
    the device while the schedule is walked (so that a CUDA graph can record the walk), and the walk's
    result is the same at the next pair."""
    field = bump_field((128, 128), amplitude=2.0)
    a, b = synthetic_pair((128, 128), field, seed=3)
    s = CorrelationSettings(backend="warp", device=device, window_sizes=(32, 16), iterations=(2, 2))
    first = correlate_pair(a, b, settings=s)  # plan made, kernels loaded
    plan = device_pass._plan_for(a.shape, first.settings, device)  # the cached plan of that call

    def no_wait(*args, **kwargs):
        raise AssertionError("the walk of the schedule waited for the device")

    with monkeypatch.context() as m:
        m.setattr(wp.array, "numpy", no_wait)
        m.setattr(wp, "synchronize", no_wait)
        m.setattr(wp, "synchronize_device", no_wait)
        m.setattr(wp, "synchronize_stream", no_wait)
        plan._launch_all()
    (u, v), measured, flags = plan.outputs
    wp.synchronize_device(device)
    assert_array_equal(flags.numpy(), first.flags)
    assert_allclose(u.numpy(), first.u, rtol=0, atol=0)
    assert_allclose(measured.ratio.numpy(), first.peak_ratio, rtol=0, atol=0)
    assert np.isfinite(v.numpy()).all()


@pytest.mark.parametrize("window_sizes", [(32,), (64, 32, 16)])
def test_engines_return_the_last_step_of_one_schedule(window_sizes):
    """Both engines' fields sit on the nodes of the schedule's last step."""
    a, b = synthetic_pair((128, 128), bump_field((128, 128)), seed=2)
    s = CorrelationSettings(window_sizes=window_sizes, iterations=1)
    last = pass_schedule(a.shape, s)[-1]
    for backend in ("numpy", "warp"):
        r = correlate_pair(a, b, settings=replace(s, backend=backend))
        assert_array_equal(r.y[:, 0], last.node[0])
        assert_array_equal(r.x[0], last.node[1])
