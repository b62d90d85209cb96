"""The Warp path of correlate_pair (backend="warp") against the NumPy reference path, on every device.

Pairs: integrated Gaussian dots of 3 px, 20 per 32x32 px, no noise (as test_multigrid), shifted by
uniform, bump-shaped and turbulent fields. Both paths must give the same vectors to 1e-4 px and the
same flags; the CUDA cases run where Warp sees a GPU (tests/conftest.py).
"""

from dataclasses import replace

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.benchmarks.bench_correlation import bump_field, random_phase_field, synthetic_pair
from synthbos.correlation import CorrelationSettings, correlate_pair, count_vectors, device_pass
from synthbos.correlation.deform import bspline3_coefficients
from synthbos.correlation.device_pass import (
    PARALLEL_SWEEPS,
    fill_by_interpolation_on_device,
    replace_outliers_on_device,
)
from synthbos.correlation.validation import fill_by_interpolation, replace_outliers

from synthbos import SynthbosError

TOLERANCE_PX = 1e-4


def both_paths(a, b, settings, device, mask=None):
    ref = correlate_pair(a, b, settings=replace(settings, backend="numpy"), mask=mask)
    dev = correlate_pair(a, b, settings=replace(settings, backend="warp", device=device), mask=mask)
    return ref, dev


def assert_same_field(ref, dev, tolerance=TOLERANCE_PX):
    assert_array_equal(dev.x, ref.x)
    assert_array_equal(dev.y, ref.y)
    du = np.nanmax(np.abs(dev.u - ref.u)) if np.isfinite(ref.u).any() else 0.0
    dv = np.nanmax(np.abs(dev.v - ref.v)) if np.isfinite(ref.v).any() else 0.0
    print(f"max |du| {du:.2e} px, |dv| {dv:.2e} px, counts {count_vectors(ref.flags)}")
    assert_array_equal(dev.flags, ref.flags)
    assert_array_equal(np.isnan(dev.u), np.isnan(ref.u))
    assert_allclose(dev.u, ref.u, atol=tolerance, rtol=0)
    assert_allclose(dev.v, ref.v, atol=tolerance, rtol=0)
    assert_allclose(dev.peak_ratio, ref.peak_ratio, rtol=1e-3)


CASES = {
    "default": {},
    "keys (1,1)": {"interpolator": "keys", "iterations": (1, 1)},
    "lanczos, parabolic, overlap": {"interpolator": "lanczos", "subpixel": "parabolic", "overlaps": 0.5},
    "three passes, centroid": {"window_sizes": (64, 32, 16), "subpixel": "centroid"},
    "replace all": {"confirm_tolerance": 0.0},
}


@pytest.mark.parametrize("case", list(CASES))
def test_warp_path_matches_numpy_bump(case, device):
    field = bump_field((256, 256), amplitude=2.5)
    a, b = synthetic_pair((256, 256), field, seed=5)
    ref, dev = both_paths(a, b, CorrelationSettings(**CASES[case]), device)
    assert_same_field(ref, dev)


def test_a_result_keeps_its_values_when_the_cached_plan_runs_again(device):
    """The Warp path reuses its plan for the next pair of the same size: the first result's arrays are
    its own (on the CPU device a Warp array's .numpy() is a view of the plan's buffer)."""
    field = bump_field((128, 128), amplitude=2.0)
    a, b = synthetic_pair((128, 128), field, seed=5)
    settings = CorrelationSettings(backend="warp", device=device)
    first = correlate_pair(a, b, settings=settings)
    kept = {k: np.array(getattr(first, k), copy=True) for k in ("u", "v", "flags")}
    mask = np.zeros(a.shape, bool)
    mask[40:100, 10:70] = True  # another result from the same plan: masked windows, other flags
    second = correlate_pair(a, b, settings=settings, mask=mask)
    assert not np.array_equal(second.flags, kept["flags"])
    for k, before in kept.items():
        assert_array_equal(getattr(first, k), before, err_msg=k)


def test_warp_path_matches_numpy_turbulent_with_failures(device):
    """A rough field, a noisy patch and an image edge: failed, replaced and confirmed vectors alike."""
    field = random_phase_field((256, 256), seed=3, max_displacement=4.0)
    a, b = synthetic_pair((256, 256), field, seed=4)
    b = b.copy()
    b[100:140, 30:90] = np.random.default_rng(1).random((40, 60)) * b.max()
    ref, dev = both_paths(a, b, CorrelationSettings(), device)
    c = count_vectors(ref.flags)
    assert c["failed"] + c["replaced"] >= 5, c
    assert_same_field(ref, dev)


def test_warp_path_matches_numpy_with_mask(device):
    field = bump_field((256, 256))
    a, b = synthetic_pair((256, 256), field, seed=6)
    mask = np.zeros(a.shape, dtype=bool)
    mask[40:120, 150:256] = True
    mask[200:, :20] = True
    ref, dev = both_paths(a, b, CorrelationSettings(), device, mask=mask)
    assert np.isnan(ref.u).any()
    assert_same_field(ref, dev)


def test_warp_path_rpc_close_to_numpy(device):
    """RPC whitens the spectrum: its DC bin, zero but for rounding (the windows' means are subtracted),
    becomes a unit value of rounding's sign, which offsets the plane by +-1/N^2 differently on the two
    paths (zeroing that bin in both makes them agree to 2e-5 px). Weak peaks (edge windows) move by up
    to 0.05 px, the others by less than 2e-3 px."""
    field = bump_field((256, 256))
    a, b = synthetic_pair((256, 256), field, seed=7)
    ref, dev = both_paths(a, b, CorrelationSettings(rpc=True), device)
    assert_array_equal(dev.flags, ref.flags)
    assert np.all(np.isnan(dev.correlation))
    diff = np.hypot(dev.u - ref.u, dev.v - ref.v)
    print(f"RPC: max |difference| {diff.max():.2e} px, 95th percentile {np.percentile(diff, 95):.2e} px")
    assert diff.max() < 0.1
    assert np.percentile(diff, 95) < 2e-3


def test_warp_path_replays_its_graph_for_the_next_pairs(device, monkeypatch):
    """The second pair records the plan's launches into a graph (CUDA; here on every device), later
    pairs replay it: each still gets its own field."""
    monkeypatch.setattr(device_pass, "_graph_replay", lambda dev: True)
    s = CorrelationSettings(backend="warp", device=device, window_sizes=(64, 32, 16), iterations=(2, 1, 2))
    for seed, shift in ((8, (0.4, -1.1)), (9, (-2.2, 0.7)), (10, (1.6, 2.9))):

        def field(x, y, sh=shift):
            return np.full_like(x, sh[0]), np.full_like(y, sh[1])

        a, b = synthetic_pair((128, 160), field, seed=seed)
        r = correlate_pair(a, b, settings=s)
        assert_allclose(np.median(r.u), shift[0], atol=0.02)
        assert_allclose(np.median(r.v), shift[1], atol=0.02)
        assert_same_field(correlate_pair(a, b, settings=replace(s, backend="numpy")), r)
    plans = [p for p in device_pass._plans.values() if p.settings == replace(s, pattern="random")]  # as resolved
    assert len(plans) == 1 and plans[0].graph is not None and plans[0].runs == 3


def test_graph_recorded_and_replayed_while_another_thread_launches(device, monkeypatch):
    """A campaign's render threads launch while the correlation records and replays its plan's graph
    (``synthbos.device.launching``): every pair's field is the one the same pair gives alone."""
    import threading

    import warp as wp
    from synthbos.correlation.pass_kernels import laplace_sweep

    from synthbos.device import launching

    monkeypatch.setattr(device_pass, "_graph_replay", lambda dev: True)
    s = CorrelationSettings(backend="warp", device=device, window_sizes=(32, 16), iterations=(1, 2))
    pairs = [synthetic_pair((96, 128), lambda x, y, k=k: (np.full_like(x, 0.3 * k), np.full_like(y, -0.2 * k)), seed=k)
             for k in range(4)]
    alone = [correlate_pair(a, b, settings=replace(s, backend="numpy")) for a, b in pairs]
    stop = threading.Event()
    launches = [0]

    def render():  # another thread's kernels on the same device, as a campaign's render threads
        z = [wp.zeros((64, 64), dtype=wp.float64, device=device) for _ in range(5)]
        flags = wp.zeros((64, 64), dtype=wp.int32, device=device)
        while not stop.is_set():
            with launching():
                wp.launch(laplace_sweep, dim=(64, 64), inputs=[z[0], z[1], flags, z[2], z[3]], device=device)
                z[4].numpy()
                launches[0] += 1

    t = threading.Thread(target=render)
    t.start()
    try:
        side_by_side = [correlate_pair(a, b, settings=s) for a, b in pairs]
    finally:
        stop.set()
        t.join(10)
    assert launches[0] > 0
    for ref, dev in zip(alone, side_by_side, strict=True):
        assert_same_field(ref, dev)
    plans = [p for p in device_pass._plans.values() if p.settings == replace(s, pattern="random")]
    assert len(plans) == 1 and plans[0].graph is not None and plans[0].runs == 4


def test_prefilter_matches_scipy(device):
    """The device's cubic B-spline prefilter gives the coefficients of scipy.ndimage's (bspline3_coefficients)."""
    rng = np.random.default_rng(0)
    img = rng.random((37, 53)).astype(np.float32)
    from synthbos.correlation.device_pass import _warp

    wp, _, k = _warp()
    src = wp.array(img, dtype=wp.float32, device=device)
    tmp = wp.zeros(img.shape, dtype=wp.float32, device=device)
    out = wp.zeros(img.shape, dtype=wp.float32, device=device)
    rows = wp.zeros((37, 53), dtype=wp.float64, device=device)
    cols = wp.zeros((53, 37), dtype=wp.float64, device=device)
    wp.launch(k.bspline3_prefilter_lines, dim=37, inputs=[src, 1, rows, tmp], device=device, block_dim=k.LOOP_BLOCK)
    wp.launch(k.bspline3_prefilter_lines, dim=53, inputs=[tmp, 0, cols, out], device=device, block_dim=k.LOOP_BLOCK)
    assert_allclose(out.numpy(), bspline3_coefficients(img), atol=2e-6, rtol=0)


@pytest.mark.parametrize("hole", [2, 2 * PARALLEL_SWEEPS + 3])
def test_replacement_matches_numpy(hole, device):
    """Holes filled ring by ring: within the parallel sweeps, and wider ones finished on one thread."""
    rng = np.random.default_rng(hole)
    u, v = rng.normal(size=(2, 20, 24))
    invalid = rng.random((20, 24)) < 0.1
    invalid[3 : 3 + hole, 5 : 5 + hole] = True
    ru, rv = replace_outliers(u, v, invalid)
    du, dv = replace_outliers_on_device(u, v, invalid, device=device)
    assert_allclose(du, ru, rtol=0, atol=1e-12)
    assert_allclose(dv, rv, rtol=0, atol=1e-12)
    # nothing valid: zero everywhere
    zu, zv = replace_outliers_on_device(u, v, np.ones_like(invalid), device=device)
    assert np.all(zu == 0) and np.all(zv == 0)


@pytest.mark.parametrize("hole", [1, 2 * PARALLEL_SWEEPS + 3])
def test_fill_by_interpolation_matches_numpy(hole, device):
    """The median start and the Jacobi sweeps of the Laplace fill, on holes inside and at the grid's edge."""
    rng = np.random.default_rng(10 + hole)
    u, v = rng.normal(size=(2, 21, 17))
    invalid = rng.random((21, 17)) < 0.15
    invalid[2 : 2 + hole, 4 : 4 + hole] = True
    invalid[-3:, -2:] = True  # a corner hole
    ru, rv = fill_by_interpolation(u, v, invalid)
    du, dv = fill_by_interpolation_on_device(u, v, invalid, device=device)
    assert np.abs(ru - replace_outliers(u, v, invalid)[0]).max() > 0.01  # the sweeps did something
    assert_allclose(du, ru, rtol=0, atol=1e-12)
    assert_allclose(dv, rv, rtol=0, atol=1e-12)
    assert_array_equal(du[~invalid], u[~invalid])


def test_backend_selection():
    assert not CorrelationSettings().uses_warp()
    assert CorrelationSettings(device="cuda:0").uses_warp()
    assert not CorrelationSettings(device="cuda:0", backend="numpy").uses_warp()
    assert not CorrelationSettings(device="cuda:0", window_sizes=(24, 12)).uses_warp()
    assert CorrelationSettings(backend="warp").uses_warp()
    assert CorrelationSettings().as_dict()["backend"] == "auto"
    with pytest.raises(SynthbosError, match="backend"):
        CorrelationSettings(backend="gpu")
    a, b = synthetic_pair((96, 96), bump_field((96, 96)), seed=1)
    with pytest.raises(SynthbosError, match="power of two"):
        correlate_pair(a, b, settings=CorrelationSettings(backend="warp", window_sizes=(24, 12)))


def test_warp_path_checks_and_normalises_images_on_the_device(device):
    """Images of any real or integer dtype normalised on the device as on the host; the same errors."""
    a, b = synthetic_pair((128, 128), bump_field((128, 128)), seed=2)
    s = CorrelationSettings(backend="warp", device=device)
    scale = 200 / max(a.max(), b.max())
    for dtype in (np.uint8, np.uint16, np.int32, np.float32, np.float64):
        ai, bi = (a * scale + 10).astype(dtype), (b * scale + 10).astype(dtype)
        ref = correlate_pair(ai, bi, settings=replace(s, backend="numpy"))
        assert_same_field(ref, correlate_pair(ai, bi, settings=s))
    bad = a.copy()
    bad[3, 4] = np.nan
    bad[5, 6] = np.inf
    with pytest.raises(SynthbosError, match="reference image has 2 non-finite pixels"):
        correlate_pair(bad, b, settings=s)
    with pytest.raises(SynthbosError, match=r"gradient image is constant \(value 3\)"):
        correlate_pair(a, np.full_like(b, 3.0), settings=s)
