"""Issue 25's zero-noise targets on rendered turbulent pairs: the default trackers against the mean landing
positions the renderer records (``benchmarks/bench_distortion.py``), on patterns the benchmark does not use
(its seed is 0)."""

import numpy as np
import pytest
from synthbos.benchmarks.bench_distortion import DEFAULT_STEP, METHODS, TARGETS, case_config, measure_case
from synthbos.raytrace import render_pair


def _case(snapshot=None, *, linear=None, seed):
    pair = render_pair(case_config(size=256, rays=1000, f_number=11.0, snapshot=snapshot, linear=linear, seed=seed),
                       device="cpu")  # fmt: skip
    return measure_case(pair, noise_percent=0.0, device="cpu", steps=(DEFAULT_STEP,))


def _assert_targets(row):
    for method in METHODS:
        r = row[f"{method}/{DEFAULT_STEP}"]
        assert r["p90"] <= TARGETS["p90"], (method, r)
        assert r["p99"] <= TARGETS["p99"], (method, r)
        assert r["yield"] >= TARGETS["yield"], (method, r)
        assert r["density"] <= TARGETS["density_ratio"] * row["floor"], (method, r, row["floor"])


def test_default_trackers_meet_the_zero_noise_targets_on_snapshot_1():
    """Snapshot 1, the hardest (sharp interfaces, crowded spread dots), 256 px, 1,000 rays, f/11, zero
    noise: tracking and tracking-cc p90 <= 0.010 px, p99 <= 0.030 px, every true dot measured, density
    within 1.5 x its floor (measured: p90 0.0054-0.0069 px, p99 0.019-0.024 px on three patterns; the
    elliptical step alone 0.028-0.037 and 0.096-0.118 px)."""
    _assert_targets(_case(1, seed=7))


@pytest.mark.slow
@pytest.mark.parametrize("snapshot", [0, 2, 3, 4])
def test_default_trackers_meet_the_zero_noise_targets(snapshot):
    _assert_targets(_case(snapshot, seed=11))


@pytest.mark.slow
def test_linear_gradient_stays_exact():
    """A linear density gradient distorts no dot: p90 < 0.001 px."""
    row = _case(linear=(20.0, 10.0), seed=11)
    for method in METHODS:
        assert row[f"{method}/{DEFAULT_STEP}"]["p90"] < TARGETS["linear_p90"]
        assert np.isfinite(row[f"{method}/{DEFAULT_STEP}"]["p99"])
