"""The scoring of the harness on cases with known answers."""

import numpy as np
from numpy.testing import assert_allclose
from synthbos.benchmarks import scoring
from synthbos.benchmarks.regress import compare_to_baseline


def test_cdf_and_percentiles_of_known_errors():
    errors = np.arange(1, 101, dtype=float)  # 1..100
    x, y = scoring.empirical_cdf(np.concatenate([errors, [np.nan]]))
    assert_allclose(x, errors)
    assert_allclose(y, errors / 100)
    p = scoring.error_percentiles(errors)
    assert_allclose([p[50], p[90], p[99]], [50.5, 90.1, 99.01])
    # Exponential errors: the p-th percentile is -scale ln(1 - p/100).
    rng = np.random.default_rng(0)
    e = rng.exponential(0.02, 200_000)
    p = scoring.error_percentiles(e)
    for q in scoring.PERCENTILES:
        assert_allclose(p[q], -0.02 * np.log(1 - q / 100), rtol=0.02)
    assert np.isnan(scoring.error_percentiles([np.nan])[50])


def test_thinned_cdf_keeps_exact_probabilities_and_stays_within_one_step():
    rng = np.random.default_rng(3)
    e = rng.lognormal(-4.0, 1.5, 250_000)
    x_full, y_full = scoring.empirical_cdf(e)
    x, y = scoring.empirical_cdf(e, max_points=1000)
    assert 1000 <= len(x) <= 1080
    assert x[0] == x_full[0] and x[-1] == x_full[-1]  # the extremes are kept
    assert_allclose(x[-64:], x_full[-64:])  # and the largest errors, one by one
    # every kept point is a point of the full curve, with its exact probability
    k = np.searchsorted(x_full, x, side="right") - 1
    assert_allclose(y, y_full[k])
    # the thinned step curve, read at every error, is within 1/1000 of the full one
    drawn = y[np.searchsorted(x, x_full, side="right") - 1]
    assert np.max(y_full - drawn) <= 1.0 / 1000 + 1e-12
    # small samples are not thinned
    assert len(scoring.empirical_cdf(e[:500], max_points=1000)[0]) == 500


def test_vector_error_is_the_magnitude_of_the_difference():
    assert_allclose(scoring.vector_errors([[3.0, 4.0], [1.0, 1.0]], [[0.0, 0.0], [1.0, 2.0]]), [5.0, 1.0])


def test_threshold_is_half_the_std_of_theoretical_magnitudes_and_splits():
    rng = np.random.default_rng(1)
    mags = rng.uniform(0, 2, 100_000)
    ang = rng.uniform(0, 2 * np.pi, mags.size)
    theory = np.stack([mags * np.cos(ang), mags * np.sin(ang)], axis=1)
    t = scoring.split_threshold(theory)
    assert_allclose(t, 0.5 * 2 / np.sqrt(12), rtol=0.01)  # std of U(0, 2) is 2 / sqrt(12)
    from synthbos.benchmarks.tables import split_masks

    masks = split_masks({"true_mag": np.array([0.1, 0.5, 0.2886, 0.3]), "threshold": np.full(4, t)})
    np.testing.assert_array_equal(masks["below"], [True, False, t > 0.2886, False])
    np.testing.assert_array_equal(masks["above"], ~masks["below"])


def test_gradient_errors_of_a_known_linear_field():
    # u = 0.01 x + 0.002 y, v = -0.003 x + 0.004 y: the gradient is constant.
    grad = np.array([[0.01, 0.002], [-0.003, 0.004]])
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 200, size=(400, 2))
    disp = xy @ grad.T
    g = scoring.scattered_gradient(xy, disp)
    assert_allclose(g, np.broadcast_to(grad, g.shape), atol=1e-12)
    y, x = np.mgrid[8:200:16, 8:200:16].astype(float)
    gg = scoring.grid_gradient(grad[0, 0] * x + grad[0, 1] * y, grad[1, 0] * x + grad[1, 1] * y, x, y)
    inner = gg[1:-1, 1:-1]
    assert_allclose(inner, np.broadcast_to(grad, inner.shape), atol=1e-12)
    assert np.isnan(gg[0, 0, 0, 1]) and np.isnan(gg[0, 0, 1, 1])  # no neighbour above the first row
    # A measured field off by a known gradient perturbation: the error is its Frobenius norm.
    delta = np.array([[0.001, 0.0], [0.0, -0.002]])
    g2 = scoring.scattered_gradient(xy, xy @ (grad + delta).T)
    assert_allclose(np.sqrt(((g2 - g) ** 2).sum(axis=(1, 2))), np.sqrt(0.001**2 + 0.002**2), rtol=1e-8)


def test_truth_interpolation_is_exact_for_linear_fields_and_nan_outside():
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 100, size=(300, 2))
    disp = np.stack([0.1 + 0.01 * xy[:, 0], -0.2 + 0.005 * xy[:, 1]], axis=1)
    pts = np.array([[50.0, 50.0], [20.0, 70.0], [-10.0, 50.0]])
    t = scoring.interpolate_truth(xy, disp, pts)
    assert_allclose(t[:2], np.stack([0.1 + 0.01 * pts[:2, 0], -0.2 + 0.005 * pts[:2, 1]], axis=1), atol=1e-12)
    assert np.isnan(t[2]).all()


def test_cramer_rao_bound():
    # Pixel integration and the unknown peak, width and background put a 3 px dot's position bound
    # above the sampled Gaussian's sqrt(2 / pi) = 0.80 sigma_n / I0; a displacement is sqrt(2) times it.
    per_axis = scoring.cramer_rao_displacement(5.0) / (np.sqrt(2) * 0.05)
    assert 0.85 < per_axis < 1.0
    assert_allclose(scoring.cramer_rao_displacement(1.0) * 5, scoring.cramer_rao_displacement(5.0), rtol=1e-9)
    assert scoring.cramer_rao_displacement(0.0) == 0.0


def test_regression_comparison_names_what_got_worse():
    base = [{"method": "tracking", "noise_percent": 3.0, "split": "above", "quantity": "displacement",
             "p50": 0.01, "p68": 0.02, "p90": 0.03, "p95": 0.04, "p99": 0.05, "yield": 1.0}]
    same = [dict(base[0])]
    assert compare_to_baseline(same, base) == []
    worse = [dict(base[0], p90=0.04, **{"yield": 0.98})]
    problems = compare_to_baseline(worse, base)
    assert len(problems) == 2
    assert "tracking noise 3% above threshold displacement p90" in problems[0]
    assert "yield" in problems[1]
    better = [dict(base[0], p90=0.02)]
    assert compare_to_baseline(better, base) == []
