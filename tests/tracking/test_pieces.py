"""The pieces of the tracker one by one: identification, Eq. 1, centroids, calibration, diameter, matching."""

import numpy as np
import pytest
from _synth import dot_pattern
from numpy.testing import assert_allclose
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import (
    blob_properties,
    blob_score,
    centroid_gaussian3,
    centroid_gaussian4,
    centroid_intensity_weighted,
    centroid_lsq_gaussian,
    correlation_correction,
    dynamic_threshold_identification,
    estimate_dot_diameter,
    estimate_noise,
    fit_soloff,
    match_multiparametric,
    match_nearest,
    render_gaussians,
    segment_windows,
    static_threshold_identification,
    subtract_gaussians,
)
from synthbos.tracking.neighbours import neighbour_fit
from synthbos.tracking.reference import measure_windows_numpy, neighbour_fit_numpy
from synthbos.tracking.windows import measure_windows, median_network

from synthbos import SynthbosError


def _isolated_windows(rng, n, d, *, half=3, spacing=8):
    """n dots in their own (2 half + 1)^2 windows; true positions in window coordinates."""
    side = int(np.ceil(np.sqrt(n)))
    centres = spacing * (np.stack(np.divmod(np.arange(n), side), axis=1)[:, ::-1] + 1.0)
    xy = centres + rng.uniform(-0.5, 0.5, (n, 2))
    img = draw_dots((spacing * (side + 2),) * 2, xy, d)
    c = centres.astype(int)
    from numpy.lib.stride_tricks import sliding_window_view

    w = 2 * half + 1
    win = sliding_window_view(img, (w, w))[c[:, 1] - half, c[:, 0] - half]
    return win, xy - (c - half)


def test_dynamic_threshold_splits_overlapping_dots_static_does_not():
    img = draw_dots((40, 40), [[18.0, 20.0], [20.6, 20.0]], 3.0)
    _, n_static = static_threshold_identification(img, threshold=0.1)
    labels, n_dyn = dynamic_threshold_identification(img, threshold=0.1, n_levels=16)
    props = blob_properties(img, labels)
    assert n_static == 1
    assert n_dyn == 2
    assert_allclose(np.sort(props["x"]), [18, 21], atol=1)


def _dynamic_by_sorting(image, threshold, n_levels):
    """The dynamic threshold segmentation as first written, with scipy's sorting measurements
    (``minimum_position`` for each component's first pixel, ``np.unique`` to number the blobs)."""
    from scipy import ndimage

    eight = np.ones((3, 3), dtype=bool)
    labels, n = ndimage.label(image > threshold, structure=eight)
    for level in np.linspace(threshold, np.percentile(image, 99.9), n_levels + 1)[1:]:
        comp, m = ndimage.label(image > level, structure=eight)
        if m < 2:
            continue
        parent = labels[tuple(np.array(ndimage.minimum_position(comp, comp, np.arange(1, m + 1))).T)]
        counts = np.bincount(parent, minlength=n + 1)
        splits = counts[parent] >= 2
        if not splits.any():
            continue
        seed_of = np.zeros(m + 1, dtype=np.int64)
        seed_of[1:][splits] = np.arange(1, splits.sum() + 1)
        seeds = seed_of[comp]
        in_split = (counts[labels] >= 2) & (labels > 0)
        _, (ri, ci) = ndimage.distance_transform_edt(seeds == 0, return_indices=True)
        nearest = seeds[ri, ci]
        new = np.where(in_split, n + nearest, labels)
        seed_parent = np.r_[0, parent[splits]]
        wrong = in_split & (seed_parent[nearest] != labels)
        new[wrong] = labels[wrong]
        labels = np.unique(new, return_inverse=True)[1].reshape(image.shape) + (new.min() > 0)
        n = int(labels.max())
    return labels, n


def test_dynamic_threshold_and_blob_peaks_match_the_sorting_definition():
    """The sort-free segmentation (first pixels by a backwards assignment, blob numbers by a table) and
    blob peaks (a per-blob maximum) are those of scipy's sorting measurements, on a dense noisy pattern."""
    from scipy import ndimage

    rng = np.random.default_rng(7)
    shape = (160, 192)
    img = draw_dots(shape, dot_pattern(rng, shape, per_32x32=25, min_distance=2.0), 3.0)
    img += 0.03 * rng.standard_normal(shape)
    labels, n = dynamic_threshold_identification(img, threshold=0.12, n_levels=8)
    want, n_want = _dynamic_by_sorting(img, 0.12, 8)
    assert n > 1.2 * ndimage.label(img > 0.12, structure=np.ones((3, 3)))[1]  # it split many blobs
    assert n == n_want
    np.testing.assert_array_equal(labels, want)
    props = blob_properties(img, labels)
    peak_rc = np.array(ndimage.maximum_position(img, labels, np.arange(1, n + 1)))
    np.testing.assert_array_equal(props["y"], peak_rc[:, 0])
    np.testing.assert_array_equal(props["x"], peak_rc[:, 1])
    assert_allclose(props["peak"], img[peak_rc[:, 0], peak_rc[:, 1]], rtol=0, atol=0)
    assert_allclose(props["area"], np.bincount(labels.ravel())[1:])


def test_blob_peak_ties_go_to_the_last_pixel():
    img = np.zeros((6, 6))
    img[2, 1:4] = [5.0, 5.0, 3.0]
    img[4, 4] = 1.0
    labels = (img > 0).astype(int) + (img == 1.0)
    props = blob_properties(img, labels)
    assert_allclose(props["x"], [2, 4])
    assert_allclose(props["y"], [2, 4])
    assert_allclose(props["peak"], [5.0, 1.0])


def test_segment_windows_splits_overlap_and_labels_by_peak():
    img = draw_dots((9, 9), [[3.0, 4.0], [5.6, 4.2]], 3.0)
    lab = segment_windows(img[None], np.array([0.05]))[0].reshape(9, 9)
    roots = np.unique(lab[lab >= 0])
    assert len(roots) == 2
    assert set(roots) == {4 * 9 + 3, 4 * 9 + 6}


def test_blob_score_is_eq1():
    area = np.array([[9.0, 3.0, np.nan]])
    peak = np.array([[0.8, 0.4, np.nan]])
    dist = np.array([[0.5, 2.0, np.nan]])
    s = blob_score(area, peak, dist)
    assert_allclose(s[0, :2], [(1 + 1 + (1 - 0.25)) / 3, (3 / 9 + 0.5 + 0) / 3])
    assert np.isnan(s[0, 2])


@pytest.mark.parametrize(
    ("fn", "bound"),
    [(centroid_gaussian3, 0.005), (centroid_gaussian4, 0.02), (centroid_lsq_gaussian, 0.005)],
)
def test_gaussian_centroids_are_accurate_on_3px_dots(fn, bound):
    rng = np.random.default_rng(1)
    win, truth = _isolated_windows(rng, 400, 3.0)
    x, y, eta, _, ok = fn(win)
    err = np.hypot(x - truth[:, 0], y - truth[:, 1])
    print(f"{fn.__name__}: rms error {np.sqrt(np.mean(err**2)):.5f} px (bound {bound})")
    assert ok.all()
    assert np.sqrt(np.mean(err**2)) < bound, f"{fn.__name__} rms error {np.sqrt(np.mean(err**2)):.5f} px"
    assert_allclose(np.median(4 * eta), 3.2, atol=0.25)  # pixel-integrated 3 px dots look ~3.2 px wide


def test_intensity_weighted_centroid_is_close():
    rng = np.random.default_rng(2)
    win, truth = _isolated_windows(rng, 400, 3.0)
    x, y, ok = centroid_intensity_weighted(win)
    err = np.hypot(x - truth[:, 0], y - truth[:, 1])
    assert ok.all()
    assert np.sqrt(np.mean(err**2)) < 0.02


def test_gaussian3_has_no_peak_locking_at_3px():
    """Histogram of fractional positions of the estimates vs. that of the true (uniform) positions."""
    rng = np.random.default_rng(3)
    n = 40000
    win, truth = _isolated_windows(rng, n, 3.0)
    x, y, *_ = centroid_gaussian3(win)
    bins = np.linspace(0, 1, 11)
    frac_est = np.concatenate([x - np.floor(x), y - np.floor(y)])
    frac_true = np.concatenate([truth[:, 0] - np.floor(truth[:, 0]), truth[:, 1] - np.floor(truth[:, 1])])
    h_est, _ = np.histogram(frac_est, bins)
    h_true, _ = np.histogram(frac_true, bins)
    expected = 2 * n / 10
    flatness = (h_est.max() - h_est.min()) / expected
    shift = np.abs(h_est - h_true).max() / expected
    chi2 = np.sum((h_est - expected) ** 2 / expected)
    print(
        f"gaussian3 peak-locking: (max-min)/mean of 10 bins {flatness:.4f} "
        f"(truth {np.ptp(h_true) / expected:.4f}), max bin change vs truth {shift:.4f}, "
        f"chi2 {chi2:.1f} (9 dof)"
    )
    # Poisson spread of 8000 per bin is ~1.1%; peak-locking would pile estimates up near 0 and 1.
    assert shift < 0.01, f"bins moved by up to {shift:.4f} of their mean"
    assert flatness < 0.06, f"histogram flatness {flatness:.4f}"
    assert chi2 < 30.0, f"chi2 {chi2:.1f} with 9 dof"


def test_soloff_fits_cubic_distortion():
    rng = np.random.default_rng(4)
    t = rng.uniform(-50, 50, (200, 2))
    u, v = t[:, 0] / 50, t[:, 1] / 50
    img = np.stack([300 + 4 * t[:, 0] + 2 * u**2 - 3 * u * v**2, 200 + 4 * t[:, 1] + 1.5 * u**3 + v * u], axis=1)
    m = fit_soloff(t, img, order=3)
    assert m.rms < 1e-8
    assert_allclose(m(t[:5]), img[:5], atol=1e-8)
    with pytest.raises(SynthbosError):
        fit_soloff(t[:5], img[:5])
    with pytest.raises(SynthbosError):
        fit_soloff(t, img[:, :1])


def test_dot_diameter_from_autocorrelation():
    rng = np.random.default_rng(5)
    for d in (3.0, 5.0):
        xy = dot_pattern(rng, (256, 256), per_32x32=8, min_distance=d)
        img = draw_dots((256, 256), xy, d) + 0.02 * rng.standard_normal((256, 256))
        est = estimate_dot_diameter(img)
        expect = 4 * np.sqrt((d / 4) ** 2 + 1 / 12)  # the pixel's own width adds in quadrature
        print(f"d = {d}: estimated {est:.3f}, expected {expect:.3f}")
        # Pixel integration widens the dots, the random pattern's own correlation narrows the peak: the
        # estimate (used to size the windows) lands within 10 % of the drawn diameter.
        assert abs(est / d - 1) < 0.1, f"estimated {est:.3f} for d = {d}"


def test_noise_estimate():
    rng = np.random.default_rng(6)
    xy = dot_pattern(rng, (256, 256))
    for sigma in (0.01, 0.03, 0.05):
        img = draw_dots((256, 256), xy, 3.0) + sigma * rng.standard_normal((256, 256))
        est = estimate_noise(img)
        print(f"noise {sigma}: estimated {est:.4f}")
        # Dense 3 px dots (tails on over half the pixels) bias it up; it only sets detection floors.
        assert 0.9 * sigma < est < 1.7 * sigma, f"noise {sigma}: estimated {est:.4f}"


def test_residual_removes_dots():
    xy = np.array([[10.3, 12.7], [20.0, 20.5]])
    model = render_gaussians((32, 32), xy, [1.0, 0.5], [0.75, 0.75])
    res = subtract_gaussians(model, xy, [1.0, 0.5], [0.75, 0.75])
    assert np.abs(res).max() < 1e-12
    assert_allclose(model[13, 10], np.exp(-(0.3**2 + 0.3**2) / (2 * 0.75**2)), rtol=1e-12)


def test_correlation_correction_recovers_shift():
    rng = np.random.default_rng(7)
    n = 200
    shift = rng.uniform(-0.5, 0.5, (n, 2))
    a = np.stack([draw_dots((5, 5), [[2.0, 2.0]], 3.0)] * n)
    b = np.stack([draw_dots((5, 5), [[2.0 + s[0], 2.0 + s[1]]], 3.0) for s in shift])
    u, v, ok = correlation_correction(a, b, max_shift=2)
    assert ok.all()
    assert_allclose(u, shift[:, 0], atol=0.03)
    assert_allclose(v, shift[:, 1], atol=0.03)


def test_matching_nearest_and_multiparametric():
    rng = np.random.default_rng(8)
    ref = rng.uniform(0, 100, (50, 2))
    perm = rng.permutation(50)
    grad = ref[perm] + rng.normal(0, 0.2, (50, 2))
    idx = match_nearest(ref, grad, radius=1.0)
    assert_allclose(perm[idx], np.arange(50))
    # A decoy brighter-and-larger dot closer than the true partner: the multi-parametric match avoids it.
    r = np.array([[10.0, 10.0]])
    g = np.array([[10.9, 10.0], [10.5, 10.0]])
    assert match_nearest(r, g, radius=2.0)[0] == 1
    j = match_multiparametric(r, g, [1.0], [1.0, 3.0], [3.0], [3.0, 8.0], radius=2.0)
    assert j[0] == 0
    assert match_nearest(r, np.array([[15.0, 10.0]]), radius=2.0)[0] == -1


def test_window_kernel_matches_numpy_reference(device):
    rng = np.random.default_rng(9)
    xy = dot_pattern(rng, (128, 128), per_32x32=15)
    img = draw_dots((128, 128), xy, 3.0) + 0.03 * rng.standard_normal((128, 128))
    pred = np.vstack([xy + rng.normal(0, 0.3, xy.shape), [[1.0, 1.0], [126.6, 0.2]]])  # two at the edge
    for half, use_min in ((3, False), (3, True), (5, True)):  # 7 x 7: measure_small_window
        origin = np.rint(pred).astype(np.int64) - half
        kw = dict(
            half=half,
            map_half=2,
            radius=2.5,
            threshold_fraction=0.1,
            noise_floor=0.06,
            weights=(0.5, 0.3, 0.2),
            use_minimum=use_min,
            saturation=0.7,
            fill=0.01,
        )
        a = measure_windows_numpy(img, origin, pred, **kw)
        b = measure_windows(img, origin, pred, device=device, **kw)
        for key in a:
            assert_allclose(b[key], a[key], rtol=0, atol=1e-12, err_msg=key)
        # only the maps' centre cross (what the three-point fit reads): peak, left, right, up, down
        c = measure_windows(img, origin, pred, device=device, full_maps=False, **kw)
        centre = a["dotmap"][:, [2, 2, 2, 1, 3], [2, 1, 3, 2, 2]]
        assert "dotmap" not in c
        assert_allclose(c["cross"], centre, rtol=0, atol=1e-12)
        for key in ("chosen", "nblobs", "nsat", "bg", "peak", "dist"):
            assert_allclose(c[key], a[key], rtol=0, atol=1e-12, err_msg=key)


def test_neighbour_fit_kernel_matches_numpy_reference(device):
    """The cell-grid kernel finds the same k nearest neighbours as the k-d tree and fits the same planes,
    with and without the query among the points, for queries inside and outside the points' box."""
    rng = np.random.default_rng(12)
    xy = dot_pattern(rng, (256, 256), per_32x32=15)
    uv = np.stack([0.01 * xy[:, 0] - 0.02 * xy[:, 1], 0.005 * xy[:, 1]], axis=1) + 0.05 * rng.standard_normal(xy.shape)
    for k in (12, 7):
        a = neighbour_fit_numpy(xy, uv, xy, np.arange(len(xy)), k=k)
        b = neighbour_fit(xy, uv, xy, np.arange(len(xy)), k=k, device=device)
        for x, y in zip(a, b, strict=True):
            assert_allclose(y, x, rtol=0, atol=1e-12)
    sub = rng.choice(len(xy), len(xy) // 3, replace=False)
    query = rng.uniform(-40.0, 300.0, (200, 2))
    a = neighbour_fit_numpy(xy[sub], uv[sub], query, np.full(len(query), -1), k=12)
    b = neighbour_fit(xy[sub], uv[sub], query, np.full(len(query), -1), k=12, device=device)
    for x, y in zip(a, b, strict=True):
        assert_allclose(y, x, rtol=0, atol=1e-12)
    # a plane is fitted exactly (but for the tiny ridge): the value is the field at the query, the spread zero
    plane = np.stack([0.3 + 0.01 * xy[:, 0], -0.2 + 0.02 * xy[:, 1] - 0.01 * xy[:, 0]], axis=1)
    query = query[((query > 0) & (query < 256)).all(axis=1)]  # beyond the points the ridge's bias grows
    value, spread = neighbour_fit(xy, plane, query, np.full(len(query), -1), k=12, device=device)
    truth = np.stack([0.3 + 0.01 * query[:, 0], -0.2 + 0.02 * query[:, 1] - 0.01 * query[:, 0]], axis=1)
    assert_allclose(value, truth, atol=1e-5)
    assert_allclose(spread, 0.0, atol=1e-6)


def test_neighbour_fit_kernel_matches_numpy_on_clustered_points(device):
    """Dense clusters in a sparse field: cells holding dozens of points, and queries whose k nearest lie
    beyond the first block of cells (the search starts again on larger blocks); odd and even k."""
    rng = np.random.default_rng(5)
    centres = rng.uniform(0.0, 500.0, (6, 2))
    xy = np.concatenate([c + 3.0 * rng.standard_normal((150, 2)) for c in centres] + [rng.uniform(0.0, 500.0, (60, 2))])
    uv = np.stack([np.sin(xy[:, 0] / 80.0), 0.002 * xy[:, 1]], axis=1) + 0.05 * rng.standard_normal(xy.shape)
    for k in (12, 5, 20):
        a = neighbour_fit_numpy(xy, uv, xy, np.arange(len(xy)), k=k, return_neighbours=True)
        b = neighbour_fit(xy, uv, xy, np.arange(len(xy)), k=k, return_neighbours=True, device=device)
        assert_allclose(b[0], a[0], rtol=0, atol=1e-12)
        assert_allclose(b[1], a[1], rtol=0, atol=1e-12)
        assert (np.sort(b[2], axis=1) == np.sort(a[2], axis=1)).all()


@pytest.mark.parametrize("n", [4, 7, 8, 12, 13, 24, 40, 56])
def test_median_network_puts_the_middle_two_in_place(n):
    """The edge median's compare-exchange network (ties and all: few distinct values) against a sort."""
    rng = np.random.default_rng(n)
    net = median_network(n)
    assert (net[:, 0] < net[:, 1]).all() and net.max() < n
    v = rng.integers(0, 4, (3000, n)).astype(float)
    v[:1000] = rng.standard_normal((1000, n))
    for a, b in net:
        lo, hi = np.minimum(v[:, a], v[:, b]), np.maximum(v[:, a], v[:, b])
        v[:, a], v[:, b] = lo, hi
    srt = np.sort(v, axis=1)
    np.testing.assert_array_equal(v[:, n // 2 - 1 : n // 2 + 1], srt[:, n // 2 - 1 : n // 2 + 1])


def test_estimate_noise_quartile_is_numpys_percentile():
    """The partial-sort lower quartile gives NumPy's percentile, bit for bit (ties, odd sizes, NaN)."""
    from synthbos.tracking.identify import _lower_quartile

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 4, 5, 7, 100, 1001, 4096):
        for values in (rng.standard_normal(n), np.round(rng.standard_normal(n), 1), np.ones(n)):
            assert _lower_quartile(values.copy()) == np.percentile(values, 25)
    v = rng.standard_normal(50)
    v[7] = np.nan
    assert np.isnan(_lower_quartile(v.copy()))


def test_dot_diameter_sums_the_autocorrelation_of_the_zero_padded_image():
    """The four lags summed directly are the zero-padded FFT auto-correlation's (section 2.2 of the
    paper), on a non-square image with a gradient in its background."""
    rng = np.random.default_rng(6)
    xy = dot_pattern(rng, (120, 200), per_32x32=10, min_distance=3.0)
    img = draw_dots((120, 200), xy, 3.0) + 0.05 * rng.standard_normal((120, 200)) + np.linspace(0, 0.3, 200)
    z = img - img.mean()
    f = np.fft.rfft2(z, s=(240, 400))
    ac = np.fft.irfft2(np.abs(f) ** 2, s=(240, 400))
    r1, r2 = 0.5 * (ac[0, 1] + ac[1, 0]), 0.5 * (ac[0, 2] + ac[2, 0])
    expect = 4.0 * np.sqrt(3.0 / (2.0 * np.log(r1 / r2))) / np.sqrt(2.0)
    assert_allclose(estimate_dot_diameter(img), expect, rtol=1e-12)
    assert np.isnan(estimate_dot_diameter(np.ones((16, 16))))


def test_no_windows_give_empty_results(device):
    img = draw_dots((32, 32), np.array([[16.0, 16.0]]), 3.0)
    kw = dict(half=3, map_half=2, radius=2.5, threshold_fraction=0.1, noise_floor=0.06, weights=(1, 1, 1))
    none = np.zeros((0, 2), dtype=np.int64)
    for full_maps, maps, shape in ((True, "dotmap", (0, 5, 5)), (False, "cross", (0, 5))):
        b = measure_windows(img, none, none.astype(float), full_maps=full_maps, device=device, **kw)
        assert set(b) == {"chosen", "nblobs", "nsat", "bg", "peak", "dist", maps}
        assert b[maps].shape == shape and b[maps].dtype == np.float64
        for key in ("chosen", "nblobs", "nsat"):
            assert b[key].shape == (0,) and b[key].dtype == np.int64, key
        for key in ("bg", "peak", "dist"):
            assert b[key].shape == (0,) and b[key].dtype == np.float64, key
