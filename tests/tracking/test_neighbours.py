"""The stacked neighbour tests (tracking.neighbours, *_stack) against their references' rounds, pair by pair
(with the fit of one pair, ``neighbour_fit``, whose values are the kernel's to the bit)."""

import dataclasses
import functools

import numpy as np
import pytest
import warp as wp
from _synth import smooth_displacement
from synthbos.tracking.neighbours import (
    confirmed_by_neighbours_stack,
    neighbour_fit,
    neighbour_fit_stack,
    neighbour_outliers_stack,
)
from synthbos.tracking.reference import confirmed_by_neighbours_numpy, neighbour_outliers_numpy
from synthbos.tracking.settings import TrackingSettings

SETTINGS = TrackingSettings()  # k = 12, threshold = 3, epsilon = 0.2, tolerance = 1.5


def _options(settings, *, confirm=False):
    opts = {"k": settings.outlier_neighbours, "threshold": settings.outlier_threshold}
    opts["epsilon"] = settings.outlier_epsilon
    if confirm:
        opts["tolerance"] = settings.predictor_tolerance
    return opts


def _batch(rng, sides, counts=None, *, spare=40):
    """Pairs of random scattered dots (20 per 32x32 px over a ``side`` px square, or ``counts[b]`` dots),
    at random rows of (B, N) arrays (the other rows NaN): positions and gradient-image positions (a smooth
    field, noise and 3 % wrong vectors of 2 to 5 px), and the mask of the dots' rows."""
    sizes = [
        round(20 * s * s / 1024) if counts is None or counts[b] is None else counts[b] for b, s in enumerate(sides)
    ]
    n = max(sizes) + spare
    xy = np.full((len(sides), n, 2), np.nan)
    xyg = np.full((len(sides), n, 2), np.nan)
    present = np.zeros((len(sides), n), dtype=bool)
    for b, (side, m) in enumerate(zip(sides, sizes, strict=True)):
        p = rng.uniform(0.0, side, (m, 2))
        d = smooth_displacement(p, (side, side)) + 0.05 * rng.standard_normal((m, 2))
        wrong = rng.random(m) < 0.03
        angle = rng.uniform(0.0, 2 * np.pi, wrong.sum())
        d[wrong] += rng.uniform(2.0, 5.0, wrong.sum())[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        rows = rng.choice(n, m, replace=False)
        xy[b, rows], xyg[b, rows], present[b, rows] = p, p + d, True
    return xy, xyg, present


def _host_outliers(xy, uv, valid, settings, device):
    """The reference's two rounds of the outlier test of each pair's valid dots, at their rows."""
    fit = functools.partial(neighbour_fit, device=device)
    return neighbour_outliers_numpy(xy, uv, valid, **_options(settings), fit=fit)


def _host_confirmed(xy, xyg, good, query, settings, device):
    """The reference's test of each pair's queried dots against its good dots' fit."""
    fit = functools.partial(neighbour_fit, device=device)
    return confirmed_by_neighbours_numpy(xy, xyg - xy, good, query, **_options(settings, confirm=True), fit=fit)


def _first_round(xy, uv, settings, device):
    """The first round of ``_neighbour_outliers`` alone (to check that the tests reach the second)."""
    fit, spread = neighbour_fit(xy, uv, xy, np.arange(len(xy)), k=settings.outlier_neighbours, device=device)
    d = uv - fit
    return np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2) > settings.outlier_threshold * (spread + settings.outlier_epsilon)


@pytest.mark.parametrize("exclude_self", [True, False])
def test_fit_is_the_hosts_to_the_bit(device, exclude_self):
    """The batched fit's values and spreads are those of ``neighbour_fit`` called pair by pair, exactly
    (same grid, same neighbours, same operations); NaN where not fitted and in pairs with k points."""
    rng = np.random.default_rng(4)
    k = 12
    xy, xyg, present = _batch(rng, [160, 96, 128, 64, 200], [None, None, None, k, None])
    xy[4, present[4]] = np.round(xy[4, present[4]] / 4.0)  # pair 4 on a grid: ties
    uv = xyg - xy
    points = present & (rng.random(present.shape) < 0.8)
    points[3] = present[3]  # k points: no fit
    queries = present & (rng.random(present.shape) < 0.7)
    value, spread = neighbour_fit_stack(xy, uv, points, queries, k=k, exclude_self=exclude_self, device=device)
    value, spread = value.numpy(), spread.numpy()
    for b in range(len(points)):
        p, q = np.flatnonzero(points[b]), np.flatnonzero(queries[b])
        assert np.isnan(value[b, ~queries[b]]).all() and np.isnan(spread[b, ~queries[b]]).all()
        if len(p) <= k:
            assert np.isnan(value[b]).all() and np.isnan(spread[b]).all()
            continue
        where = np.full(points.shape[1], -1)
        if exclude_self:
            where[p] = np.arange(len(p))
        a = neighbour_fit(xy[b, p], uv[b, p], xy[b, q], where[q], k=k, device=device)
        np.testing.assert_array_equal(value[b, q], a[0])
        np.testing.assert_array_equal(spread[b, q], a[1])


def test_degenerate_boxes(device):
    """Pairs whose box has no area (dots on a line: a grid of 4097 x 1 cells; all at one place; a sliver):
    the same fits and flags as the host's."""
    rng = np.random.default_rng(6)
    n = 600
    xy = np.zeros((3, n, 2))
    xy[0, :, 0], xy[0, :, 1] = rng.uniform(0.0, 500.0, n), 7.0
    xy[1] = 3.25
    xy[2, :, 0], xy[2, :, 1] = rng.uniform(0.0, 1e-3, n), rng.uniform(0.0, 900.0, n)
    uv = 0.05 * rng.standard_normal((3, n, 2))
    uv[:, ::40] += 3.0
    valid = np.ones((3, n), dtype=bool)
    value, spread = neighbour_fit_stack(xy, uv, valid, valid, k=12, exclude_self=True, device=device)
    bad = neighbour_outliers_stack(xy, uv, valid, **_options(SETTINGS), device=device).numpy()
    for b in range(3):
        a = neighbour_fit(xy[b], uv[b], xy[b], np.arange(n), k=12, device=device)
        np.testing.assert_array_equal(value.numpy()[b], a[0])
        np.testing.assert_array_equal(spread.numpy()[b], a[1])
    assert (bad == _host_outliers(xy, uv, valid, SETTINGS, device)).all() and bad.sum() > 0


def test_outliers_match_the_host_pair_by_pair(device):
    """Eight pairs of different sizes: large ones, one with no valid dot, ones with k + 2, k + 3 and k + 4
    valid dots (below, at and just past the test's minimum); the flags are the host's exactly, and the
    second round changes some of them."""
    rng = np.random.default_rng(3)
    k = SETTINGS.outlier_neighbours
    xy, xyg, present = _batch(
        rng, [256, 128, 192, 64, 160, 64, 64, 224], [None, None, None, 0, None, k + 2, k + 3, k + 4]
    )
    uv = xyg - xy
    valid = present & (rng.random(present.shape) < 0.9)
    valid[5:8] = present[5:8]  # exactly k + 2, k + 3, k + 4 valid dots
    bad = neighbour_outliers_stack(xy, uv, valid, **_options(SETTINGS), device=device)
    assert isinstance(bad, wp.array) and bad.dtype == wp.int32 and bad.shape == valid.shape
    bad = bad.numpy()
    expected = _host_outliers(xy, uv, valid, SETTINGS, device)
    # the reference with its own fit (a k-d tree) flags the same dots
    assert (neighbour_outliers_numpy(xy, uv, valid, **_options(SETTINGS)) == expected).all()
    assert set(np.unique(bad)) <= {0, 1}
    for b in range(len(valid)):
        assert (bad[b] == expected[b]).all(), f"pair {b}: {np.flatnonzero(bad[b] != expected[b])}"
    assert expected[[0, 1, 2, 4]].sum(axis=1).min() > 0  # outliers found in every large pair
    assert not expected[[3, 5, 6]].any()
    # the second round kept some dots that the first flagged
    redone = 0
    for b in (0, 1, 2, 4):
        s = np.flatnonzero(valid[b])
        redone += (_first_round(xy[b, s], uv[b, s], SETTINGS, device) != expected[b, s]).sum()
    assert redone > 0


def test_confirmed_match_the_host_pair_by_pair(device):
    """Good and queried dots drawn at random (disjoint as in ``track_pair``, and overlapping); pairs with
    no query, with no good dot, with k + 3 and k + 4 good dots; queries outside the good dots' box."""
    rng = np.random.default_rng(8)
    k = SETTINGS.outlier_neighbours
    xy, xyg, present = _batch(rng, [192, 128, 256, 96, 64, 64, 160], [None, None, None, None, None, 2 * k, 2 * k])
    good = present & (rng.random(present.shape) < 0.75)
    query = present & ~good & (rng.random(present.shape) < 0.8)
    query[1] = False  # no query
    good[3] = False  # no good dot
    for b, m in ((5, k + 3), (6, k + 4)):
        rows = np.flatnonzero(present[b])
        good[b] = False
        good[b, rows[:m]] = True
        query[b] = False
        query[b, rows[m:]] = True
    # pair 2: queries far outside the good dots (the box spans both)
    rows = np.flatnonzero(present[2])
    good[2, rows] = xy[2, rows, 0] < 128.0
    query[2, rows] = ~good[2, rows]
    uv = xyg - xy
    for overlap in (False, True):
        q = query.copy()
        if overlap:  # some good dots queried too (but not in pairs 1, 3 and 5)
            q[[0, 2, 4, 6]] |= good[[0, 2, 4, 6]] & (rng.random((4, good.shape[1])) < 0.2)
        ok = confirmed_by_neighbours_stack(xy, uv, good, q, **_options(SETTINGS, confirm=True), device=device)
        assert isinstance(ok, wp.array) and ok.dtype == wp.int32
        ok = ok.numpy()
        expected = _host_confirmed(xy, xyg, good, q, SETTINGS, device)
        for b in range(len(good)):
            assert (ok[b] == expected[b]).all(), f"pair {b}: {np.flatnonzero(ok[b] != expected[b])}"
        assert expected[[0, 2, 4, 6]].sum(axis=1).min() > 0
        assert (~expected[q]).sum() > 0  # some queries not confirmed
        assert not expected[[1, 3, 5]].any()


@pytest.mark.parametrize("k", [12, 10, 7])
def test_ties_on_an_exact_grid(device, k):
    """Dots on an integer grid (and a few at the very same place): many neighbours at equal distances,
    resolved as the host resolves them (the lower index first), so the fits, and the flags, are the same.
    The field is a plane with a few wrong vectors and a rounding-level wobble."""
    rng = np.random.default_rng(20 + k)
    settings = dataclasses.replace(SETTINGS, outlier_neighbours=k)
    pairs, n = 5, 420
    xy = np.full((pairs, n, 2), np.nan)
    present = np.zeros((pairs, n), dtype=bool)
    for b in range(pairs):
        step = (1.0, 2.0, 4.0, 0.5, 3.0)[b]
        gx, gy = np.meshgrid(np.arange(20) * step, np.arange(18) * step)
        p = np.stack([gx.ravel(), gy.ravel()], axis=1)
        p = np.concatenate([p, p[rng.choice(len(p), 12, replace=False)]])  # duplicates
        rows = rng.choice(n, len(p), replace=False)
        xy[b, rows], present[b, rows] = p, True
    uv = np.stack([0.1 + 0.02 * xy[..., 0], -0.3 + 0.01 * xy[..., 1] - 0.015 * xy[..., 0]], axis=-1)
    uv += np.where(rng.random(present.shape) < 0.5, 1e-3, 0.0)[..., None]
    wrong = present & (rng.random(present.shape) < 0.04)
    uv[wrong] += rng.choice([-1.0, 1.0], (wrong.sum(), 2)) * rng.uniform(2.0, 5.0, (wrong.sum(), 2))
    xyg = xy + uv
    uv = xyg - xy
    valid = present & (rng.random(present.shape) < 0.95)
    bad = neighbour_outliers_stack(xy, uv, valid, **_options(settings), device=device).numpy()
    expected = _host_outliers(xy, uv, valid, settings, device)
    assert (bad == expected).all(), np.argwhere(bad != expected)
    assert expected.sum() > 0
    good = valid & ~wrong & (rng.random(valid.shape) < 0.85)
    query = present & ~good
    ok = confirmed_by_neighbours_stack(xy, uv, good, query, **_options(settings, confirm=True), device=device)
    expected = _host_confirmed(xy, xyg, good, query, settings, device)
    assert (ok.numpy() == expected).all()
    assert 0 < expected.sum() < query.sum()


def test_device_arrays_in_and_disabled_test(device):
    """Warp arrays in (the device taken from them), the same flags as from NumPy; an infinite threshold
    flags nothing; an empty batch gives an empty result."""
    rng = np.random.default_rng(1)
    xy, xyg, present = _batch(rng, [128, 96, 128])
    uv = xyg - xy
    valid = present & (rng.random(present.shape) < 0.9)
    opts = _options(SETTINGS)
    a = neighbour_outliers_stack(xy, uv, valid, **opts, device=device).numpy()
    args = [wp.array(v, dtype=wp.vec2d, device=device) for v in (xy, uv)]
    b = neighbour_outliers_stack(*args, wp.array(valid.astype(np.int32), device=device), **opts)
    assert str(b.device) == str(wp.get_device(device))
    assert (b.numpy() == a).all() and a.sum() > 0
    off = neighbour_outliers_stack(xy, uv, valid, **{**opts, "threshold": np.inf}, device=device)
    assert not off.numpy().any()
    good, query = valid & (rng.random(valid.shape) < 0.8), valid
    c = confirmed_by_neighbours_stack(
        xy, uv, good, query, **{**_options(SETTINGS, confirm=True), "threshold": np.inf}, device=device
    )
    assert not c.numpy().any()
    empty = neighbour_outliers_stack(np.zeros((0, 5, 2)), np.zeros((0, 5, 2)), np.zeros((0, 5)), **opts, device=device)
    assert empty.shape == (0, 5)
