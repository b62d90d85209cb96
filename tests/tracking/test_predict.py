"""The stacked, device-resident correlation predictor against the host one, pair by pair.

Every pair of a batch must give what :func:`predict_displacement` gives for it alone, to float32
rounding of the correlations (the batch correlates by Warp's tile FFT or directly, the host by SciPy's
pocketfft); a rounding difference can at times flip a whole-pixel rounding of the deformation, which
moves the prediction of a few dots by a few hundredths of a pixel.
"""

import numpy as np
import pytest
import warp as wp
from _synth import dot_pattern, smooth_displacement
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import predict
from synthbos.tracking import predict_fft_kernels as fk
from synthbos.tracking import predict_kernels as pk
from synthbos.tracking.predict import dots_inside, predict_displacement, predict_displacement_stack, predictor_passes
from synthbos.tracking.predict_tiles import correlate_tiles, uses_tile_fft

D = 3.0
NOISE = 0.01


def _field(kind, xy, shape):
    if kind == "still":  # the first pass already changes little: the pyramid ends there
        return np.zeros_like(xy)
    if kind == "uniform":
        return np.tile([1.3, -0.6], (len(xy), 1))
    if kind == "vortex":
        return smooth_displacement(xy, shape, 1.5)
    if kind == "large":
        return np.tile([10.0, -4.0], (len(xy), 1))
    if kind == "strong":  # varies by 0.2 px per px: the pyramid goes on to the 16 px passes
        return smooth_displacement(xy, shape, 0.2 * shape[0] / (2 * np.pi)) + np.array([1.0, 0.5])
    raise ValueError(kind)


def _pairs(seed, shape, kinds, *, per_32x32=20.0):
    """Image pairs of Gaussian dots (the same number in each), the gradient image's dots moved by the
    field of each kind ("unrelated": a gradient image of other dots); two NaN positions per pair."""
    rng = np.random.default_rng(seed)
    refs, grads, xys = [], [], []
    for kind in kinds:
        xy = dot_pattern(rng, shape, per_32x32=per_32x32, min_distance=D)
        moved = dot_pattern(rng, shape, per_32x32=per_32x32, min_distance=D) if kind == "unrelated" else None
        if moved is None:
            moved = xy + _field(kind, xy, shape)
        refs.append(draw_dots(shape, xy, D) + NOISE * rng.standard_normal(shape))
        grads.append(draw_dots(shape, moved, D) + NOISE * rng.standard_normal(shape))
        xys.append(np.concatenate([xy, np.full((2, 2), np.nan)]))
    return np.stack(refs), np.stack(grads), np.stack(xys)


def _passes_run(monkeypatch):
    """Counts the passes of each host call (one normalised median test per pass)."""
    calls = []
    replace = predict._replace_outliers

    def counted(*args, **kwargs):
        calls.append(1)
        return replace(*args, **kwargs)

    monkeypatch.setattr(predict, "_replace_outliers", counted)
    return calls


def _compare(refs, grads, xy, device, *, window_sizes=predict.PREDICTOR_WINDOWS, calls=None, label="", upload=True):
    """Run the batch (on Warp arrays, or with ``upload`` False on the NumPy arrays) and the host pair by
    pair; assert agreement; return the pass schedule and the host's pass counts."""
    shape = refs.shape[1:]
    sizes, density = predictor_passes(shape, dots_inside(xy[0], shape), window_sizes)
    for b in range(len(xy)):  # the pairs of a batch share the pass schedule
        assert predictor_passes(shape, dots_inside(xy[b], shape), window_sizes) == (sizes, density)
    args = (refs, grads, xy)
    if upload:
        args = (
            wp.array(a, dtype=t, device=device) for a, t in zip(args, (wp.float64, wp.float64, wp.vec2d), strict=True)
        )
    uv, quality = predict_displacement_stack(
        *args,
        sizes=sizes,
        density=density,
        device=device,
    )
    assert uv.shape == xy.shape[:2] and quality.shape == xy.shape[:2]
    uv, quality = uv.numpy(), quality.numpy()
    passes = []
    for b in range(len(xy)):
        before = len(calls) if calls is not None else 0
        uv0, q0 = predict_displacement(refs[b], grads[b], xy[b], window_sizes=window_sizes, device=device)
        passes.append(len(calls) - before if calls is not None else None)
        fin = np.isfinite(xy[b]).all(axis=1)
        assert np.isnan(uv[b][~fin]).all() and np.isnan(quality[b][~fin]).all()
        du = np.abs(uv[b][fin] - uv0[fin]).max(axis=1)
        dq = np.abs(quality[b][fin] - q0[fin])
        print(
            f"{label} pair {b} ({passes[-1]} passes of {sizes}): |uv diff| max {du.max():.2e} px, "
            f"99.5th percentile {np.percentile(du, 99.5):.2e} px; |quality diff| max {dq.max():.2e} "
            f"(median quality {np.median(q0[fin]):.3f})"
        )
        # one whole-pixel rounding of the deformation flipped by the correlations' rounding moves the dots
        # around one tile (about 20 at 16 px tiles) by up to a few hundredths of a pixel: allowed, not more
        assert np.count_nonzero(du > 1e-5) <= max(0.005 * len(du), 25)
        assert du.max() < 0.05
        assert dq.max() < 1e-3
    return sizes, passes


def test_batch_matches_host_pair_by_pair(device, monkeypatch):
    """Six 128 px pairs that end at different passes (the first, the 32 px one, the last 16 px one),
    an unrelated gradient image (quality about 0) among them."""
    calls = _passes_run(monkeypatch)
    kinds = ["still", "uniform", "vortex", "large", "strong", "unrelated"]
    refs, grads, xy = _pairs(1, (128, 128), kinds)
    sizes, passes = _compare(refs, grads, xy, device, calls=calls, label="mixed")
    assert sizes == [64, 32, 16, 16]
    assert passes[0] == 1 and passes[1] == 2 and passes[kinds.index("strong")] == 4
    _, q = predict_displacement(refs[-1], grads[-1], xy[-1])
    assert abs(np.nanmedian(q)) < 0.2


def test_batch_non_square_images(device):
    """180 x 236 px pairs (NumPy arrays in): the tile grids do not fill the image and are centred on it."""
    refs, grads, xy = _pairs(9, (180, 236), ["vortex", "large", "strong"])
    _compare(refs, grads, xy, device, label="180 x 236", upload=False)


def test_batch_single_pass(device):
    refs, grads, xy = _pairs(10, (128, 128), ["uniform", "vortex"])
    sizes, _ = _compare(refs, grads, xy, device, window_sizes=(32,), label="one pass")
    assert sizes == [32]


def test_batch_sparse_first_pass(device, monkeypatch):
    """256 px pairs with 16 px tiles: the first pass takes about every other tile along each axis."""
    calls = _passes_run(monkeypatch)
    refs, grads, xy = _pairs(2, (256, 256), ["uniform", "vortex", "still"])
    assert predict._sparse_grid(256, 256, 16)
    sizes, passes = _compare(refs, grads, xy, device, window_sizes=(16, 8), calls=calls, label="sparse")
    assert sizes == [16, 16] and 2 in passes


def test_batch_size_not_a_power_of_two(device, monkeypatch):
    """A sparse pattern (10 dots per 32 x 32 px) makes the last pass 24 px tiles, correlated directly,
    and the significance pooled over 3 x 3 tiles; the pairs end at each of the three passes."""
    calls = _passes_run(monkeypatch)
    refs, grads, xy = _pairs(3, (128, 128), ["vortex", "uniform", "strong"], per_32x32=10.0)
    sizes, passes = _compare(refs, grads, xy, device, calls=calls, label="24 px")
    assert sizes == [64, 32, 24] and not uses_tile_fft(24)
    assert passes == [1, 2, 3]
    assert predict.pooling_block(predictor_passes((128, 128), 160)[1], 24) == 3


def test_batch_512_pair(device, monkeypatch):
    calls = _passes_run(monkeypatch)
    refs, grads, xy = _pairs(4, (512, 512), ["vortex"])
    _compare(refs, grads, xy, device, calls=calls, label="512 px")


def test_batch_flat_tiles(device, monkeypatch):
    """A flat (dot-free, noise-free) corner of the reference image: its tiles are unusable; those
    without a usable neighbour take the values of the nearest usable tile, their neighbours' medians
    alike (at the 32 px pass where one pair stops, and at the 16 px passes)."""
    calls = _passes_run(monkeypatch)
    refs, grads, xy = _pairs(5, (128, 128), ["strong", "uniform"])
    refs[:, :64, :64] = 0.0
    _, passes = _compare(refs, grads, xy, device, calls=calls, label="flat corner")
    assert passes == [4, 2]


def test_fill_and_median_test_kernels(device):
    """The nearest-finite fill reproduces ``scipy.ndimage.distance_transform_edt``'s choice among equally
    near nodes, and the normalised median test ``predict._replace_outliers``, on random fields with holes
    (all-NaN and hole-free fields among them)."""
    rng = np.random.default_rng(6)
    nb, ny, nx = 60, 7, 9
    u = rng.normal(0.0, 1.0, (nb, ny, nx))
    u[rng.random(u.shape) < 0.05] += 20.0  # outliers
    holes = rng.random(u.shape) < np.linspace(0.0, 0.97, nb)[:, None, None]
    holes[-1] = True
    u[holes] = np.nan
    v = u + 1.0
    f = [wp.array(a, dtype=wp.float64, device=device) for a in (u, v)]
    out = [wp.empty((nb, ny, nx), dtype=wp.float64, device=device) for _ in range(4)]
    feature, stack = (wp.empty((nb, ny, nx), dtype=wp.int32, device=device) for _ in range(2))
    changed = wp.zeros((nb, 1), dtype=wp.int32, device=device)
    wp.launch(pk.replace_outliers, dim=(nb, ny, nx), inputs=[*f, changed, 0, out[0], out[1]], device=device)
    wp.launch(pk.nearest_in_columns, dim=(nb, nx), inputs=[f[0], changed, 0, 1, 0, feature], device=device)
    wp.launch(pk.nearest_in_rows, dim=(nb, ny), inputs=[*f, feature, stack, changed, 0, 1, 0, out[2], out[3]],
              device=device)  # fmt: skip
    replaced, filled = np.stack([out[0].numpy(), out[1].numpy()]), np.stack([out[2].numpy(), out[3].numpy()])
    assert_array_equal(replaced, predict._replace_outliers(np.stack([u, v])))
    for b in range(nb):
        assert_array_equal(filled[0, b], predict._fill_nan(u[b]))
        assert_array_equal(filled[1, b], predict._fill_nan(v[b]))
    assert np.isnan(u).any(axis=(1, 2)).sum() > nb // 2


def test_empty_schedule_gives_zeros(device):
    refs, grads, xy = _pairs(7, (64, 64), ["uniform"])
    uv, q = predict_displacement_stack(refs, grads, xy, sizes=[], density=0.02, device=device)
    assert_allclose(uv.numpy(), 0.0)
    assert_allclose(q.numpy(), 0.0)
    uv, q = predict_displacement_stack(refs, grads, xy[:, :0], sizes=[32], density=0.02, device=device)
    assert uv.shape == (1, 0) and q.shape == (1, 0)


@pytest.mark.parametrize("n", [24, 16, 32])
def test_tile_correlation_and_peak(device, n):
    """The planes of the route each tile size takes (24 and 16 px: direct DFTs over half the spectrum;
    32 px: tile FFTs in blocks of rows per transform) agree with a NumPy circular correlation of the
    mean-subtracted tiles, and the peak search finds their first maximum."""
    rng = np.random.default_rng(8)
    nb, side = 2, 2 * n
    refs = rng.random((nb, side, side))
    grads = np.roll(refs, (2, -3), axis=(1, 2)) + 0.1 * rng.random((nb, side, side))
    g = pk.TileGrid()
    g.top, g.left, g.row_step, g.col_step, g.size, g.ny, g.nx = 0, 0, n, n, n, 2, 2
    changed = wp.zeros((nb, 1), dtype=wp.int32, device=device)
    images = [wp.array(refs, dtype=wp.float64, device=device), wp.array(grads, dtype=wp.float32, device=device),
              wp.array(np.ones_like(grads), dtype=wp.float32, device=device),
              wp.zeros(grads.shape, dtype=wp.vec2f, device=device)]  # fmt: skip
    planes, peak, *_ = correlate_tiles(*images, changed, 0, g, wp.get_device(device))
    got = planes.numpy().reshape(nb, 2, 2, n, n)
    for b, i, j in np.ndindex(nb, 2, 2):
        a = refs[b, i * n : (i + 1) * n, j * n : (j + 1) * n].astype(np.float32)
        m = grads[b, i * n : (i + 1) * n, j * n : (j + 1) * n].astype(np.float32)
        a, m = a - a.mean(), m - m.mean()
        ref = np.array([[np.sum(a * np.roll(m, (n // 2 - dy, n // 2 - dx), axis=(0, 1))) for dx in range(n)]
                        for dy in range(n)])  # fmt: skip
        assert_allclose(got[b, i, j], ref, atol=1e-5 * np.abs(ref).max())
        assert peak.numpy()[b, i, j] == np.argmax(got[b, i, j]) == (n // 2 + 2) * n + n // 2 - 3


def test_the_default_passes_tile_kernels_are_among_the_modules_a_campaign_compiles():
    """The stacked predictor's tile kernels (a Warp module each) exist from import for the default passes,
    so ``load_kernels`` of ``predict_fft_kernels`` (a stacked campaign's list) compiles them up front."""
    from synthbos.tracking import predict_tiles
    from synthbos.tracking.predict import PREDICTOR_WINDOWS

    from synthbos.device import _warp_modules

    names = {m.name for m in _warp_modules("synthbos.tracking.predict_fft_kernels")}
    for size in set(PREDICTOR_WINDOWS):
        kernels = [predict_tiles._kernel("centre", size)]
        if predict_tiles.uses_tile_fft(size):
            kernels += list(predict_tiles._kernel("fft", size))
        assert {k.module.name for k in kernels} <= names, size
        # compiled ahead of the launch, each is built for its GPU launch's block size (Warp's default
        # 256 threads failed the 32-sample tile FFT's build on an H100, 2026-11-27)
        threads = [predict_tiles._cuda_threads("centre", size)] + [size // 2] * (len(kernels) - 1)
        assert [k.module.options["block_dim"] for k in kernels] == threads, size


def _grid_pair(pitch, shift, size, seed):
    """A regular grid of 3 px dots (the first at half a pitch from the corner), and the same grid moved
    by ``shift``, with noise; and the grid's positions."""
    rng = np.random.default_rng(seed)
    line = np.arange(pitch / 2, size, pitch)
    xy = np.stack(np.meshgrid(line, line), axis=-1).reshape(-1, 2)
    ref = draw_dots((size, size), xy, D) + NOISE * rng.standard_normal((size, size))
    grad = draw_dots((size, size), xy + np.asarray(shift), D) + NOISE * rng.standard_normal((size, size))
    return ref, grad, xy


@pytest.mark.parametrize(("pitch", "shift"), [(8, (1.2, -0.7)), (8, (0.2, 0.1)), (16, (3.0, 1.0))])
def test_a_dot_grid_whose_pitch_divides_the_tiles_is_predicted_at_its_smallest_shift(device, pitch, shift):
    """Every tile of a grid whose pitch divides it (8 and 16 px in 64, 32 and 16 px tiles) correlates
    circularly alike at every lattice shift; the predictor takes the nearest peak (``peak_index``), on the
    host and in the stack, where the first maximum fell on any of them (predictions up to 48 px off)."""
    ref, grad, xy = _grid_pair(pitch, shift, 128, seed=pitch)
    uv, quality = predict_displacement(ref, grad, xy)
    assert np.abs(uv - np.asarray(shift)).max() < 0.1
    assert np.median(quality) > 0.9
    _compare(ref[None], grad[None], xy[None], device, label=f"grid {pitch} px")


def test_the_stack_peak_search_is_the_host_rule_on_ties(device):
    """``search_peaks`` on planes of several equal peaks, a plateau and a peak just inside and just outside
    the tie: ``predict.peak_index`` of each searched block, in the first pass and a later one."""
    n, nb = 16, 3
    rng = np.random.default_rng(4)
    planes = (0.2 * rng.random((nb, 2, 2, n, n))).astype(np.float32)
    for b, i, j in np.ndindex(nb, 2, 2):
        for k, (r, c) in enumerate([(2, 2), (2 + i, 10), (9 + j, 12), (13, 5)]):
            planes[b, i, j, r, c] = np.float32(1.0 - 0.05 * k * b)  # ties for b = 0, 0.95 and 0.9 for b = 1 ...
    planes[2, 1, 1, 8:10, 7] = 1.5  # a plateau of two samples
    g = pk.TileGrid()
    g.top, g.left, g.row_step, g.col_step, g.size, g.ny, g.nx = 0, 0, n, n, n, 2, 2
    changed = wp.zeros((nb, 1), dtype=wp.int32, device=device)
    flat = wp.array(planes.reshape(-1, n), dtype=wp.float32, device=device)
    for lo, m in ((0, n), (n // 2 - n // 4, 2 * (n // 4) + 1)):
        peak = wp.zeros((nb, 2, 2), dtype=wp.int32, device=device)
        wp.launch(fk.search_peaks, dim=(nb, 2, 2), inputs=[flat, changed, 0, g, lo, m, peak], device=device)
        block = planes.reshape(-1, n, n)[:, lo : lo + m, lo : lo + m]
        r, c = np.divmod(predict.peak_index(block, centre=n // 2 - lo), m)
        assert_array_equal(peak.numpy().ravel(), (r + lo) * n + c + lo)
