"""The cheaper scoring returns exactly what the straightforward implementation returned.

Campaign scores are stored numbers checked byte for byte by ``synthbos regress``: the triangulation
cache (``integration.triangulate``), the shared neighbour search of ``scoring.scattered_gradient``, and
the truths remembered per pair (``items``: the truth at a method's points and its gradient at the dots;
``integrate.truth_on_grid``) must not change a bit, and must never serve a pair that differs in anything
they depend on. The references below are the implementations they replaced, kept here only.
"""

import threading
from types import SimpleNamespace

import numpy as np
import pytest
from numpy.testing import assert_array_equal
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import cKDTree
from synthbos.benchmarks import integrate, items, scoring
from synthbos.benchmarks.registry import MethodResult
from synthbos.integration import grid_for_points, scattered_to_grid, triangulate
from threadpoolctl import threadpool_info, threadpool_limits

from synthbos.memo import forget_all


def reference_scattered_to_grid(x, y, values, grid_x, grid_y):
    x, y = np.asarray(x, float), np.asarray(y, float)
    v = np.asarray(values, dtype=np.float64)
    single = v.ndim == 1
    v = v.reshape(len(x), -1)
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(v).all(axis=1)
    interp = LinearNDInterpolator(np.stack([x[ok], y[ok]], axis=1), v[ok], fill_value=np.nan)
    gx, gy = np.meshgrid(np.asarray(grid_x, float), np.asarray(grid_y, float))
    out = interp(gx, gy)
    return out[..., 0] if single else out


def reference_interpolate_truth(dot_xy, dot_disp, points_xy):
    ok = np.all(np.isfinite(dot_xy), axis=1) & np.all(np.isfinite(dot_disp), axis=1)
    interp = LinearNDInterpolator(np.asarray(dot_xy)[ok], np.asarray(dot_disp)[ok], fill_value=np.nan)
    pts = np.asarray(points_xy, dtype=np.float64)
    return interp(pts.reshape(-1, 2)).reshape(*pts.shape[:-1], 2)


def reference_scattered_gradient(xy, disp, *, neighbours=8):
    xy = np.asarray(xy, dtype=np.float64)
    disp = np.asarray(disp, dtype=np.float64)
    ok = np.all(np.isfinite(xy), axis=1) & np.all(np.isfinite(disp), axis=1)
    out = np.full((len(xy), 2, 2), np.nan)
    idx_ok = np.flatnonzero(ok)
    k = min(neighbours + 1, len(idx_ok))
    if k < 3:
        return out
    pts = xy[idx_ok]
    _, nn = cKDTree(pts).query(pts, k=k)
    dx = pts[nn] - pts[:, None, :]
    a = np.concatenate([np.ones((*dx.shape[:2], 1)), dx], axis=2)
    b = disp[idx_ok][nn]
    ata = np.einsum("nki,nkj->nij", a, a)
    atb = np.einsum("nki,nkj->nij", a, b)
    good = np.abs(np.linalg.det(ata)) > 1e-9
    coef = np.full((len(pts), 3, 2), np.nan)
    coef[good] = np.linalg.solve(ata[good], atb[good])
    out[idx_ok] = np.transpose(coef[:, 1:, :], (0, 2, 1))
    return out


def assert_identical(new, old):
    """Same dtype, shape and bytes (NaN where NaN, the sign of zeros included)."""
    new, old = np.asarray(new), np.asarray(old)
    assert new.dtype == old.dtype and new.shape == old.shape
    assert_array_equal(new, old)  # NaN-aware: NaN only where NaN
    assert new.tobytes() == old.tobytes()


def synthetic_pair(seed=0, size=192, pitch=7.2):
    """A rendered-like pair: dots on a jittered lattice (the paper's 20 dots per 32 x 32 px), a smooth
    displacement field, per-dot density truths, a few invalid dots and a lost one."""
    rng = np.random.default_rng(seed)
    c = np.arange(pitch / 2, size, pitch)
    xy = np.stack(np.meshgrid(c, c), -1).reshape(-1, 2) + rng.uniform(-2.0, 2.0, (len(c) ** 2, 2))
    r2 = np.sum((xy - size / 2) ** 2, axis=1) / (0.2 * size) ** 2
    bump = np.exp(-r2)
    disp = 0.4 * bump[:, None] * (xy - size / 2) / (0.2 * size)
    valid = rng.random(len(xy)) > 0.02
    disp[~valid & (rng.random(len(xy)) > 0.5)] = np.nan
    xy[7] = np.nan
    attrs = dict(magnification=0.1173, pixel_pitch_m=1e-5, z_d_m=0.25, z_stop_m=1.0, volume_depth_m=0.01,
                 gladstone_dale_m3_per_kg=2.25e-4, n0=1.000276, principal_point_x_px=size / 2 - 0.5,
                 principal_point_y_px=size / 2 - 0.5, volume_centre_x_m=0.0, volume_centre_y_m=0.0,
                 ambient_density_kg_m3=1.225, peak_intensity=1.0)
    return SimpleNamespace(
        reference_px=xy, displacement_px=disp, theory_px=disp * 1.01, valid=valid,
        density_cone_kg_m3=1.225 - 0.06 * bump * (1 + 0.01 * rng.standard_normal(len(xy))),
        density_chief_kg_m3=1.225 - 0.06 * bump, attrs=attrs, reference=np.zeros((size, size), np.float32))


def tracked(pair, name, seed=1):
    """A tracking result on ``pair``: noisy positions and displacements, a few lost dots."""
    rng = np.random.default_rng(seed)
    n = len(pair.reference_px)
    xy = pair.reference_px + 0.05 * rng.standard_normal((n, 2))
    uv = pair.displacement_px + 0.03 * rng.standard_normal((n, 2))
    lost = rng.random(n) < 0.03
    uv[lost] = np.nan
    valid = ~lost & np.all(np.isfinite(uv), axis=1)
    table = {"u": uv[:, 0], "v": uv[:, 1], "u_cc": uv[:, 0] + 0.01, "v_cc": uv[:, 1], "x": xy[:, 0], "y": xy[:, 1]}
    return MethodResult(name, xy, uv, None, table, {}, valid)


def correlated(pair, seed=2, step=12.0):
    """A correlation result on ``pair``: window centres on a grid, interpolated truth plus noise."""
    rng = np.random.default_rng(seed)
    size = pair.reference.shape[0]
    c = np.arange(step, size - step + 1, step)
    gx, gy = np.meshgrid(c, c)
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
    uv = reference_interpolate_truth(pair.reference_px[pair.valid], pair.displacement_px[pair.valid], xy)
    uv = uv + 0.02 * rng.standard_normal(uv.shape)
    valid = np.all(np.isfinite(uv), axis=1) & (rng.random(len(xy)) > 0.05)
    table = {"peak_ratio": 1.5 + rng.random(gx.shape)}
    return MethodResult("correlation", xy, uv, gx.shape, table, {}, valid)


def test_scattered_to_grid_and_truth_interpolation_match_the_uncached_ones():
    pair = synthetic_pair()
    ok = pair.valid & np.all(np.isfinite(pair.reference_px), axis=1)
    x, y = pair.reference_px[ok, 0], pair.reference_px[ok, 1]
    gx, gy = grid_for_points(x, y)
    values = np.stack([pair.density_cone_kg_m3[ok], pair.density_chief_kg_m3[ok]], 1)
    old = reference_scattered_to_grid(x, y, values, gx, gy)
    for _ in range(3):  # the first call triangulates, the next ones reuse the triangulation
        assert_identical(scattered_to_grid(x, y, values, gx, gy), old)
    # other values at the same points, a single column, and a NaN value (a smaller point set)
    v1 = pair.density_chief_kg_m3[ok].copy()
    assert_identical(scattered_to_grid(x, y, v1, gx, gy), reference_scattered_to_grid(x, y, v1, gx, gy))
    v1[3] = np.nan
    assert_identical(scattered_to_grid(x, y, v1, gx, gy), reference_scattered_to_grid(x, y, v1, gx, gy))
    at = np.stack(np.meshgrid(np.linspace(-5, 200, 23), np.linspace(-5, 200, 19)), -1)
    old = reference_interpolate_truth(pair.reference_px, pair.displacement_px, at)
    for _ in range(2):
        assert_identical(scoring.interpolate_truth(pair.reference_px, pair.displacement_px, at), old)


def test_triangulate_remembers_by_contents_and_forgets_the_oldest():
    pts = synthetic_pair().reference_px[8:]
    tri = triangulate(pts)
    assert triangulate(pts.copy()) is tri  # equal points, another array
    moved = pts.copy()
    moved[0, 0] += 1e-9
    assert triangulate(moved) is not tri
    for k in range(10):
        triangulate(pts + k + 1.0)
    assert triangulate(pts) is not tri
    assert_array_equal(triangulate(pts).simplices, tri.simplices)


def test_scattered_gradient_of_two_fields_matches_two_separate_fits():
    pair = synthetic_pair()
    res = tracked(pair, "tracking")
    measured = pair.valid & res.valid & np.all(np.isfinite(pair.displacement_px), axis=1)
    at = np.where(measured[:, None], pair.reference_px, np.nan)
    g_meas, g_true = scoring.scattered_gradient(at, np.stack([res.uv, pair.displacement_px]))
    assert_identical(g_meas, reference_scattered_gradient(at, res.uv))
    assert_identical(g_true, reference_scattered_gradient(at, pair.displacement_px))
    # fields missing at different dots: each is fitted on its own dots, as before
    both = scoring.scattered_gradient(pair.reference_px, np.stack([res.uv, pair.displacement_px]))
    assert_identical(both[0], reference_scattered_gradient(pair.reference_px, res.uv))
    assert_identical(both[1], reference_scattered_gradient(pair.reference_px, pair.displacement_px))
    assert_identical(scoring.scattered_gradient(at, res.uv), reference_scattered_gradient(at, res.uv))
    few = np.full_like(at, np.nan)
    few[:2] = at[:2]
    assert_identical(scoring.scattered_gradient(few, res.uv), reference_scattered_gradient(few, res.uv))


@pytest.mark.parametrize("method", ["correlation", "tracking", "tracking-cc"])
def test_score_result_is_unchanged(method, monkeypatch):
    pair = synthetic_pair()
    res = correlated(pair) if method == "correlation" else tracked(pair, method)
    new = [items.score_result(pair, method, res) for _ in range(2)]  # cold, then warm caches
    monkeypatch.setattr(integrate, "scattered_to_grid", reference_scattered_to_grid)
    monkeypatch.setattr(scoring, "interpolate_truth", reference_interpolate_truth)
    monkeypatch.setattr(scoring, "scattered_gradient", lambda xy, disp: (
        reference_scattered_gradient(xy, disp) if np.ndim(disp) == 2
        else np.stack([reference_scattered_gradient(xy, d) for d in disp])))
    forget_all()
    old = items.score_result(pair, method, res)
    assert old["density_error_cone"].size > 100 and np.isfinite(old["grad_error"]).sum() > 100
    for scores in new:
        assert scores.keys() == old.keys()
        for key in old:
            assert_identical(scores[key], old[key])


def with_covariances(pair, seed=3):
    """``pair`` with ray covariances (reference and gradient image), so that its dots have in-cone spreads."""
    rng = np.random.default_rng(seed)
    n = len(pair.reference_px)
    ref = np.stack([np.full(n, 0.01), np.full(n, 0.01), np.zeros(n)], axis=1)
    grad = ref + np.stack([rng.uniform(0, 0.2, n), rng.uniform(0, 0.2, n), rng.uniform(-0.01, 0.01, n)], axis=1)
    return SimpleNamespace(**vars(pair), ray_covariance_reference_px2=ref, ray_covariance_px2=grad)


def changed(pair, name, dot, delta):
    """A copy of ``pair`` whose array ``name`` has ``delta`` added at row ``dot`` (the others shared)."""
    arr = getattr(pair, name).copy()
    arr[dot] += delta
    return SimpleNamespace(**{**vars(pair), name: arr})


@pytest.mark.parametrize("method", ["correlation", "tracking"])
def test_remembered_truths_are_never_served_for_a_changed_pair(method):
    """Score a pair (its truths remembered), then the same pair with one dot's position, displacement,
    density truth or ray covariance changed: every score equals a score from cold caches, and differs
    from the first pair's where that input enters."""
    forget_all()
    pair = with_covariances(synthetic_pair())
    res = correlated(pair) if method == "correlation" else tracked(pair, method)
    first = items.score_result(pair, method, res)
    dot = int(np.argmin(np.sum((np.nan_to_num(pair.reference_px, nan=-1e9) - 96.0) ** 2, axis=1)))  # mid-image
    assert pair.valid[dot] and np.isfinite(pair.displacement_px[dot]).all()
    changes = {"reference_px": ([0.3, -0.2], "grad_error" if method == "tracking" else "error"),
               "displacement_px": ([0.2, 0.1], "error"),
               "density_cone_kg_m3": (0.01, "density_truth_cone"),
               "density_chief_kg_m3": (0.01, "density_truth_chief"),
               "ray_covariance_px2": ([0.3, 0.3, 0.0], "spread")}
    for name, (delta, moved) in changes.items():
        other = changed(pair, name, dot, delta)
        items.score_result(pair, method, res)  # the first pair's truths are the latest remembered
        warm = items.score_result(other, method, res)
        forget_all()
        cold = items.score_result(other, method, res)
        for key in cold:
            assert_identical(warm[key], cold[key])
        a, b = np.asarray(first[moved]), np.asarray(warm[moved])
        assert a.shape != b.shape or not np.array_equal(a, b, equal_nan=True), (name, moved)


def test_truth_on_grid_gives_each_caller_its_own_arrays():
    """The density truths on a grid are remembered; a caller that writes into its copy changes nothing
    for the next, and another grid is interpolated afresh."""
    forget_all()
    pair = synthetic_pair()
    grid = integrate.gradient_grid(tracked(pair, "tracking"), integrate.geometry_from_pair(pair))
    cone, chief = integrate.truth_on_grid(pair, grid)
    keep = cone.copy(), chief.copy()
    cone[:] = 0.0
    chief[:] = 0.0
    again = integrate.truth_on_grid(pair, grid)
    assert_identical(again[0], keep[0])
    assert_identical(again[1], keep[1])
    ok = pair.valid & np.all(np.isfinite(pair.reference_px), axis=1)
    shifted = SimpleNamespace(**{**vars(grid), "x_px": grid.x_px + 0.5})
    expect = reference_scattered_to_grid(pair.reference_px[ok, 0], pair.reference_px[ok, 1],
                                         pair.density_cone_kg_m3[ok], shifted.x_px, shifted.y_px)
    assert_identical(integrate.truth_on_grid(pair, shifted)[0], expect)


def test_score_result_runs_with_one_blas_thread(monkeypatch):
    """Inside the scoring every BLAS / OpenMP library of the process runs one thread; the caller's
    setting is back afterwards."""
    seen = []
    real = scoring.split_threshold

    def spy(theory_px):
        seen.append([lib["num_threads"] for lib in threadpool_info()])
        return real(theory_px)

    monkeypatch.setattr(scoring, "split_threshold", spy)
    pair = synthetic_pair()
    with threadpool_limits(limits=2):
        before = [lib["num_threads"] for lib in threadpool_info()]
        items.score_result(pair, "tracking", tracked(pair, "tracking"))
        after = [lib["num_threads"] for lib in threadpool_info()]
    assert len(seen) == 1 and seen[0] and all(n == 1 for n in seen[0])
    assert after == before


def test_concurrent_scorings_all_run_with_one_thread_and_restore_the_setting(monkeypatch):
    """Two threads score at once, the first leaving while the second is still inside: the second keeps one
    BLAS thread to its end, and the setting before both is back after the last."""
    first_in, second_in, first_done = threading.Event(), threading.Event(), threading.Event()
    seen, errors = {}, []
    real = scoring.split_threshold

    def spy(theory_px):
        name = threading.current_thread().name
        if name == "first":
            first_in.set()
            assert second_in.wait(30)  # the second is inside too before the first goes on
        else:
            second_in.set()
            assert first_done.wait(30)  # the first has left
        seen[name] = [lib["num_threads"] for lib in threadpool_info()]
        return real(theory_px)

    monkeypatch.setattr(scoring, "split_threshold", spy)
    pair = synthetic_pair()
    res = tracked(pair, "tracking")

    def score():
        try:
            items.score_result(pair, "tracking", res)
        except Exception as err:  # reported below, in the test's thread
            errors.append(err)

    # the process's own setting (a limit set by this thread would bind the others' settings, OpenBLAS 0.3.30)
    before = [lib["num_threads"] for lib in threadpool_info()]
    first = threading.Thread(target=score, name="first")
    second = threading.Thread(target=score, name="second")
    first.start()
    assert first_in.wait(30)
    second.start()
    first.join(60)
    first_done.set()
    second.join(60)
    after = [lib["num_threads"] for lib in threadpool_info()]
    assert not errors and not first.is_alive() and not second.is_alive()
    assert seen["second"] and all(n == 1 for n in seen["first"] + seen["second"])
    assert after == before
