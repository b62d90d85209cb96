"""The shared normalised median test (correlation.median_test): the Warp funcs against their NumPy twins,
to the bit, and both against outliers planted in drawn fields."""

import numpy as np
import warp as wp
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.correlation.median_test import (
    median_scale,
    median_scale_wp,
    median_sorted_wp,
    median_wp,
    nan_median,
    normalised_residual,
    normalised_residual_wp,
    residual_limit,
    residual_limit_wp,
    sort_wp,
    vec8d,
)

EPSILON = 0.1
THRESHOLD = 2.0


@wp.kernel
def _median_test_kernel(
    values: wp.array2d(dtype=wp.float64),
    counts: wp.array(dtype=wp.int32),
    centre: wp.array(dtype=wp.float64),
    epsilon: wp.float64,
    threshold: wp.float64,
    out: wp.array2d(dtype=wp.float64),
):
    """Row i: median (unsorted and sorted input), median and scale, normalised residual and limit."""
    i = wp.tid()
    v = vec8d()
    for a in range(8):
        v[a] = values[i, a]
    n = counts[i]
    ms = median_scale_wp(v, n)
    out[i, 0] = median_wp(v, n)
    out[i, 1] = median_sorted_wp(sort_wp(v, n), n)
    out[i, 2] = ms[0]
    out[i, 3] = ms[1]
    out[i, 4] = normalised_residual_wp(wp.abs(centre[i] - ms[0]), ms[1], epsilon)
    out[i, 5] = residual_limit_wp(ms[1], epsilon, threshold)


def _stacks(rng, n=4000):
    """Rows of up to eight neighbours (the first ``count`` set, NaN after), with repeated values, zeros of
    both signs and rows of none; a centre value per row, every tenth an outlier."""
    count = rng.integers(0, 9, n)
    scale = 10.0 ** rng.integers(1, 4, (n, 1))  # coarse values: ties among the neighbours
    values = np.round(rng.normal(0.0, 1.0, (n, 8)) * scale) / scale
    values[rng.random((n, 8)) < 0.05] = -0.0
    values[np.arange(8)[None, :] >= count[:, None]] = np.nan
    centre = rng.normal(0.0, 1.0, n)
    centre[::10] += rng.choice([-1.0, 1.0], n // 10) * rng.uniform(8.0, 20.0, n // 10)
    return values, count, centre


def test_warp_funcs_equal_numpy_to_the_bit(device):
    values, count, centre = _stacks(np.random.default_rng(1))
    out = wp.empty((len(count), 6), dtype=wp.float64, device=device)
    wp.launch(
        _median_test_kernel,
        dim=len(count),
        inputs=[
            wp.array(np.nan_to_num(values, nan=0.0), dtype=wp.float64, device=device),  # beyond count: ignored
            wp.array(count.astype(np.int32), dtype=wp.int32, device=device),
            wp.array(centre, dtype=wp.float64, device=device),
            EPSILON,
            THRESHOLD,
            out,
        ],
        device=device,
    )
    got = out.numpy()
    med, scale, n = median_scale(values)
    assert_array_equal(n, count)
    assert_array_equal(nan_median(values)[0], med)
    for col, want in enumerate(
        [
            med,
            med,
            med,
            scale,
            normalised_residual(np.abs(centre - med), scale, epsilon=EPSILON),
            residual_limit(scale, epsilon=EPSILON, threshold=THRESHOLD),
        ]
    ):
        assert_array_equal(got[:, col], want, err_msg=f"column {col}")
    assert np.isnan(got[count == 0, :4]).all()


def test_numpy_median_is_the_median_of_the_finite_values():
    rng = np.random.default_rng(2)
    values, count, _ = _stacks(rng)
    values[rng.random(values.shape) < 0.05] = np.inf  # left out, as NaN
    some = count > 0
    med, n = nan_median(values)
    finite = np.where(np.isfinite(values), values, np.nan)
    assert_array_equal(n, np.isfinite(values).sum(axis=1))
    assert_allclose(med[n > 0], np.nanmedian(finite[n > 0], axis=1), rtol=0, atol=1e-15)
    assert np.isnan(med[n == 0]).all() and some.any()
    # along another axis: the same medians
    assert_array_equal(nan_median(values.T, axis=0)[0], med)


def test_planted_outliers_are_flagged_and_nothing_else():
    """A smooth drawn field with spikes: the neighbours' median and scale from the 3x3 stack (the
    correlation's idiom, without its edge continuation, so judged inside the border ring: there a
    one-sided median is off by the gradient) flag the spikes by the quotient and, for the same
    threshold, by the limit."""
    rng = np.random.default_rng(3)
    ny, nx = 40, 50
    y, x = np.mgrid[0:ny, 0:nx]
    u = 2.0 * np.sin(2 * np.pi * x / nx) * np.cos(2 * np.pi * y / ny) + rng.normal(0.0, 0.02, (ny, nx))
    spikes = np.zeros((ny, nx), dtype=bool)
    spikes[rng.integers(1, ny - 1, 30), rng.integers(1, nx - 1, 30)] = True
    # isolated spikes only: no two within one node of each other
    spikes &= ~np.any([np.roll(np.roll(spikes, dy, 0), dx, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                       if dy or dx], axis=0)  # fmt: skip
    u[spikes] += rng.choice([-1.0, 1.0], spikes.sum()) * rng.uniform(3.0, 6.0, spikes.sum())
    padded = np.pad(u, 1, constant_values=np.nan)
    stack = np.stack([padded[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                      if dy or dx], axis=-1)  # fmt: skip
    med, scale, count = median_scale(stack)
    deviation = np.abs(u - med)
    by_quotient = normalised_residual(deviation, scale, epsilon=EPSILON) > THRESHOLD
    by_limit = deviation > residual_limit(scale, epsilon=EPSILON, threshold=THRESHOLD)
    assert spikes.sum() >= 15
    inner = (slice(1, -1), slice(1, -1))
    assert_array_equal(by_quotient[inner], spikes[inner])
    assert_array_equal(by_limit[inner], spikes[inner])
    assert_array_equal(count[1:-1, 1:-1], 8)
    assert count[0, 0] == 3 and count[0, 5] == 5
