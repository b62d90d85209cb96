"""Per-frame image statistics on the device against the tracker's host functions."""

import numpy as np
import pytest
import warp as wp
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking.frame_stats import FRAME_STATISTICS, frame_statistics, segment_medians
from synthbos.tracking.reference import frame_statistics_numpy

from synthbos import SynthbosError

# Shapes chosen so that the quartile's position 0.25 (n - 1) has every remainder (n = rows x (W - 1)):
# 33x34 -> 0, 66x34 -> 0.25, 35x50 -> 0.5, 64x80 -> 0.75; odd and even fill counts; 515 rows use every
# second row for the noise.
SHAPES = [(64, 80), (33, 34), (66, 34), (35, 50), (128, 128), (300, 257), (515, 72)]
EXACT = ("lo", "hi", "bad", "saturation", "fill", "noise")


def _dots(rng, shape, diameter, intensity, noise):
    h, w = shape
    n = max(4, h * w // 40)
    xy = rng.uniform([-2.0, -2.0], [w + 1.0, h + 1.0], size=(n, 2))
    image = draw_dots(shape, xy, diameter, intensity=rng.uniform(0.5, 1.0, n) * intensity)
    return image + 0.1 + rng.normal(0.0, noise, shape)


def _stack(shape, seed):
    """Frames of different content: dots and noise, saturation, ties, zero, constant, NaN and inf."""
    rng = np.random.default_rng(seed)
    h = shape[0]
    frames = [_dots(rng, shape, 3.0, 1.0, 0.01), _dots(rng, shape, 4.5, 200.0, 2.0)]
    sat = _dots(rng, shape, 3.5, 1.0, 0.02)
    frames.append(np.minimum(sat, np.sort(sat.ravel())[-12]))  # twelve pixels at the clip level
    for n_top in (4, 5):  # one short of the saturation rule, and just enough
        img = _dots(rng, shape, 3.0, 1.0, 0.01)
        flat = img.reshape(-1)
        flat[rng.choice(flat.size, n_top, replace=False)] = img.max() + 0.25
        frames.append(img)
    frames.append(np.round(_dots(rng, shape, 3.0, 20.0, 0.7)))  # many ties in both order statistics
    frames.append(_dots(rng, shape, 2.5, 1.0, 0.01) - 0.6)  # negative values
    frames.append(1.0 + rng.normal(0.0, 1e-12, shape))  # every pixel of the fill's sub-sample one float32 key
    frames.append(np.zeros(shape))
    frames.append(np.full(shape, 2.0))
    on_grid = _dots(rng, shape, 3.0, 1.0, 0.01)
    on_grid[4, 8] = np.nan  # in the fill's sub-sample and in a noise row
    frames.append(on_grid)
    off_grid = _dots(rng, shape, 3.0, 1.0, 0.01)
    off_grid[h - 2 if h % 2 else h - 1, 3] = np.nan  # an odd row: outside the fill, noise only for h < 512
    frames.append(off_grid)
    inf = _dots(rng, shape, 3.0, 1.0, 0.01)
    inf[0, 0] = -np.inf  # in the fill's sub-sample
    inf[2, 5] = np.inf  # infinite differences, no NaN: the noise stays finite
    frames.append(inf)
    inf = _dots(rng, shape, 3.0, 1.0, 0.01)
    inf[2, 5:7] = np.inf  # inf - inf: a NaN difference
    frames.append(inf)
    return np.stack(frames)


def _check(got, ref):
    assert set(got) == set(FRAME_STATISTICS)
    for name in EXACT:
        assert_array_equal(got[name], ref[name], err_msg=name)
    assert_allclose(got["diameter"], ref["diameter"], rtol=1e-10, atol=0.0)


@pytest.mark.parametrize("shape", SHAPES, ids=[f"{h}x{w}" for h, w in SHAPES])
def test_frame_statistics_match_host(device, shape):
    stack = _stack(shape, seed=shape[0] * 1000 + shape[1])
    ref = frame_statistics_numpy(stack)
    # the test frames do what they are meant to
    assert list(ref["bad"][-6:]) == [2, 0, 1, 1, 1, 1]
    assert np.isfinite(ref["noise"][-2]) and np.isnan(ref["noise"][-1]) and np.isfinite(ref["fill"][-2])
    assert np.isinf(ref["saturation"][3]) and np.isfinite(ref["saturation"][[2, 4]]).all()
    assert np.isnan(ref["fill"][-4]) and np.isfinite(ref["fill"][-3])
    assert np.isfinite(ref["diameter"][:7]).all()
    out = frame_statistics(wp.array(stack, dtype=wp.float64, device=device))
    for name, arr in out.items():
        assert arr.device == wp.get_device(device)
        assert arr.shape == (len(stack),)
        assert arr.dtype == (wp.int32 if name == "bad" else wp.float64)
    _check({name: arr.numpy() for name, arr in out.items()}, ref)


@pytest.mark.parametrize("shape", [(8, 9), (10, 8), (9, 8), (9, 10)])
def test_frame_statistics_many_small_frames(device, shape):
    # Pixels spread over many binades, so that the quartile's two neighbours lie far apart and the two
    # interpolation formulas round differently: each branch must round as the host's (the four shapes
    # give the remainders 0.75, 0.25, 0.5 and 0; signs mixed for the fill's median).
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    stack = np.exp(rng.uniform(-15.0, 15.0, (300, *shape))) * rng.choice([-1.0, 1.0], (300, *shape), p=[0.2, 0.8])
    out = frame_statistics(stack, device=device)
    _check({name: arr.numpy() for name, arr in out.items()}, frame_statistics_numpy(stack))


def test_frame_statistics_numpy_input(device):
    stack = _stack((40, 48), seed=7)[:3].astype(np.float32)
    out = frame_statistics(stack, device=device)
    _check({name: arr.numpy() for name, arr in out.items()}, frame_statistics_numpy(stack))


def test_frame_statistics_empty_and_errors(device):
    out = frame_statistics(np.zeros((0, 16, 16)), device=device)
    assert all(arr.shape == (0,) for arr in out.values())
    with pytest.raises(SynthbosError, match="too small"):
        frame_statistics(np.ones((2, 7, 16)), device=device)
    with pytest.raises(SynthbosError, match="float64"):
        frame_statistics(wp.zeros((2, 16, 16), dtype=wp.float32, device=device))


def test_frame_statistics_graph_capture(device):
    if not wp.get_device(device).is_cuda or not wp.is_mempool_enabled(device):
        pytest.skip("graph capture of the allocations needs a CUDA device with a memory pool")
    stack = _stack((64, 80), seed=11)
    img = wp.array(stack, dtype=wp.float64, device=device)
    frame_statistics(img)  # loads the modules outside the capture
    with wp.ScopedCapture(device=device) as capture:
        out = frame_statistics(img)
    wp.capture_launch(capture.graph)
    _check({name: arr.numpy() for name, arr in out.items()}, frame_statistics_numpy(stack))


def test_segment_medians_are_numpys(device):
    """Each segment's median of the values taking part, as NumPy's (the mean of the middle two for an even
    count, NaN for none), to the bit: values that round to one float32 key (ties of the sort) among them."""
    rng = np.random.default_rng(3)
    length, segments = 37, 6
    values = rng.normal(1.0, 0.3, (segments, length))
    values[1, :20] = 1.0 + rng.integers(0, 4, 20) * 1e-12  # distinct float64 values, one float32 key
    values[2, :] = 0.5  # all equal
    valid = rng.random((segments, length)) < 0.7
    valid[3] = False  # none takes part
    valid[4] = False
    valid[4, [5, 9]] = True  # an even count of two
    valid[1, :20] = True
    got = segment_medians(
        wp.array(values.ravel(), dtype=wp.float64, device=device),
        wp.array(valid.ravel().astype(np.int32), dtype=wp.int32, device=device),
        length=length,
        segments=segments,
        device=device,
    ).numpy()
    want = np.array([np.median(v[m]) if m.any() else np.nan for v, m in zip(values, valid, strict=True)])
    assert np.isnan(got[3]) and np.isnan(want[3])
    assert_array_equal(got, want)
    assert got[4] == (values[4, 5] + values[4, 9]) / 2


@pytest.mark.parametrize("length", [33, 400])
def test_segment_medians_resolve_large_ties_exactly(device, length):
    """Segments whose values share a float32 key by the hundreds (the order statistic bisects their range
    first, then steps): distinct values 1 + k 1e-13, repeated ones, values past float32's range beside
    inf, and signed zeros; NumPy's median to the bit."""
    rng = np.random.default_rng(11)
    values = np.stack([
        1.0 + rng.integers(0, length // 3, length) * 1e-13,
        1.0 + rng.permutation(length) * 1e-14,
        np.where(rng.random(length) < 0.3, np.inf, 1e300 * rng.uniform(1.0, 1e8, length)),
        np.where(rng.random(length) < 0.5, -0.0, 0.0) + rng.integers(0, 2, length) * 1e-320,
        np.repeat(rng.normal(0.0, 1.0, 3), length // 3 + 1)[:length],
    ])  # fmt: skip
    valid = np.ones(values.shape, dtype=bool)
    valid[1, ::7] = False
    got = segment_medians(
        wp.array(values.ravel(), dtype=wp.float64, device=device),
        wp.array(valid.ravel().astype(np.int32), dtype=wp.int32, device=device),
        length=length,
        segments=len(values),
        device=device,
    ).numpy()
    want = np.array([np.median(v[m]) for v, m in zip(values, valid, strict=True)])
    assert_array_equal(got, want)
    assert np.unique(np.float32(values[1])).size == 1  # one key for a whole segment
