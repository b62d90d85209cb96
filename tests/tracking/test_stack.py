"""Stacked tracking (tracking.stack.track_pairs) against track_pair, pair by pair and dot by dot."""

import numpy as np
import pytest
from _synth import dot_pattern, smooth_displacement
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import DotStatus, TrackingSettings, pipeline, track_pair
from synthbos.tracking.stack import track_pairs

from synthbos import SynthbosError

SHAPE = (96, 128)


def _batch(seed=2):
    """Four pairs of one dense pattern: clean, noisy, saturated, a strong field; priors with NaN rows,
    rows outside the image and rows far from their dots."""
    rng = np.random.default_rng(seed)
    xy = dot_pattern(rng, SHAPE, per_32x32=35, min_distance=2.0)
    refs, grads = [], []
    for k, (amp, shift) in enumerate(((1.0, 0.0), (2.5, 3.0), (0.3, 0.0), (1.8, 0.0))):
        disp = smooth_displacement(xy, SHAPE, amp) + shift
        r = draw_dots(SHAPE, xy, 3.0) + 0.02 * k * rng.standard_normal(SHAPE)
        g = draw_dots(SHAPE, xy + disp, 3.0) + 0.02 * k * rng.standard_normal(SHAPE)
        if k == 2:
            r, g = np.minimum(r, 0.8), np.minimum(g, 0.8)
        refs.append(r)
        grads.append(g)
    prior = np.repeat((xy + 0.4 * rng.standard_normal(xy.shape))[None], 4, axis=0)
    prior[1, :5] = np.nan
    prior[2, :3] = -5.0
    prior[3, 10:15] += 0.9
    return np.array(refs), np.array(grads), prior


def _assert_same(batch_table, single_table):
    """Every field equal but for rounding: the predictor's float32 correlations (Warp's tile FFT in the
    batch, SciPy's in track_pair) to 1e-5, the positions and displacements fitted from them to 1e-7 px."""
    for name in single_table.dtype.names:
        a, b = batch_table[name], single_table[name]
        if a.dtype.kind == "f":
            assert_array_equal(np.isnan(a), np.isnan(b), err_msg=name)
            atol = 1e-5 if name in ("u_pred", "v_pred", "pred_correlation") else 1e-7
            assert_allclose(a[np.isfinite(a)], b[np.isfinite(b)], rtol=1e-12, atol=atol, err_msg=name)
        else:
            assert_array_equal(a, b, err_msg=name)


def _per_pair(monkeypatch):
    """``track_pair`` kept on its per-pair path (the variants the stack does not run) for every setting."""
    monkeypatch.setattr(pipeline, "stack_support", lambda settings: "the test's per-pair path")


@pytest.mark.parametrize(
    "settings",
    [TrackingSettings(), TrackingSettings(predictor="none"), TrackingSettings(diameter=3.0, max_iterations=2)],
    ids=["default", "no-predictor", "fixed-diameter"],
)
def test_track_pairs_equals_track_pair(device, settings, monkeypatch):
    """The stack against ``track_pair``'s per-pair path: on the CPU bit for bit (the stack's host engines
    there are the per-pair path's steps), on a GPU to rounding."""
    refs, grads, prior = _batch()
    tables = track_pairs(refs, grads, prior_xy=prior, settings=settings, device=device)
    assert tables.shape == prior.shape[:2]
    # each row names its prior row, in the batch as in track_pair (compared field by field below)
    assert_array_equal(tables["dot_id"], np.broadcast_to(np.arange(prior.shape[1]), prior.shape[:2]))
    # track_pair itself, with a prior and these settings, is the stack of one (on a GPU the float atomics of
    # the residual images may move last bits from run to run)
    for b in range(len(refs)):
        alone = track_pair(refs[b], grads[b], prior_xy=prior[b], settings=settings, device=device)
        one = track_pairs(refs[b : b + 1], grads[b : b + 1], prior_xy=prior[b : b + 1], settings=settings,
                          device=device)[0]  # fmt: skip
        if device == "cpu":
            assert alone.tobytes() == one.tobytes(), b
        else:
            _assert_same(alone, one)
    _per_pair(monkeypatch)
    for b in range(len(refs)):
        single = track_pair(refs[b], grads[b], prior_xy=prior[b], settings=settings, device=device)
        if device == "cpu":
            assert tables[b].tobytes() == single.tobytes(), b
        else:
            _assert_same(tables[b], single)
    # the batch holds the cases it is meant to: claims lost, later rounds, outliers, misses
    status = tables["status"]
    assert np.count_nonzero(status & 512) > 10
    assert np.count_nonzero(tables["iteration"] > 1) > 10
    assert np.count_nonzero(status & 4) > 1000


def test_masks_in_a_stack_equal_track_pairs_per_pair_path(device, monkeypatch):
    """A mask per pair (a disk, a stripe at the edge, none): the stack against ``track_pair``'s per-pair
    path with each pair's mask, bit for bit on the CPU; the dots near the excluded pixels are MASKED, none
    of them matched, and the unmasked pair's table is the one it has without a mask."""
    refs, grads, prior = _batch()
    yy, xx = np.mgrid[: SHAPE[0], : SHAPE[1]]
    masks = np.zeros((4, *SHAPE), dtype=bool)
    masks[0] = (xx - 40) ** 2 + (yy - 50) ** 2 < 15**2
    masks[1, :, 110:] = True
    masks[3] = np.roll(masks[0], 60, axis=1)
    tables = track_pairs(refs, grads, prior_xy=prior, mask=masks, device=device)
    masked = (tables["status"] & DotStatus.MASKED) != 0
    assert masked[[0, 1, 3]].sum(axis=1).min() > 10
    assert not masked[2].any()
    assert not (masked & ((tables["status"] & DotStatus.MATCHED) != 0)).any()
    plain = track_pairs(refs[2:3], grads[2:3], prior_xy=prior[2:3], device=device)[0]
    # one (H, W) mask for every pair is each pair's
    shared = track_pairs(refs[:2], grads[:2], prior_xy=prior[:2], mask=masks[0], device=device)
    _assert_same(shared[0], tables[0])
    _assert_same(shared[1], track_pairs(refs[1:2], grads[1:2], prior_xy=prior[1:2], mask=masks[:1], device=device)[0])
    _per_pair(monkeypatch)
    for b in range(len(refs)):
        single = track_pair(refs[b], grads[b], prior_xy=prior[b], mask=masks[b], device=device)
        if device == "cpu":
            assert tables[b].tobytes() == single.tobytes(), b
        else:
            _assert_same(tables[b], single)
    _assert_same(tables[2], plain)


def test_a_pairs_table_does_not_depend_on_its_stack(device):
    """Each pair's model images take their fixed-point scale from its own dots, so on the CPU a pair
    tracked alone, in a stack of two or of four gives the same bytes (the saturated pair's peaks are the
    lowest, the strong field's the highest: with one scale for the stack its last bits moved). On CUDA
    the last bits of a few values still move with the stack (an H100 on 2026-11-27: one row's peak), so
    there the tables agree to rounding with the same status bits."""
    refs, grads, prior = _batch()
    four = track_pairs(refs, grads, prior_xy=prior, device=device)
    for picks in ([2], [2, 3], [0, 2]):
        some = track_pairs(refs[picks], grads[picks], prior_xy=prior[picks], device=device)
        for k, b in enumerate(picks):
            if device == "cpu":
                assert some[k].tobytes() == four[b].tobytes(), (picks, b)
            else:
                _assert_same(some[k], four[b])


def test_track_pairs_one_prior_for_all(device):
    refs, grads, prior = _batch(seed=5)
    tables = track_pairs(refs[:2], grads[:2], prior_xy=prior[0], device=device)
    _assert_same(tables[1], track_pair(refs[1], grads[1], prior_xy=prior[0], device=device))


def test_track_pairs_bad_input():
    refs, grads, prior = _batch()
    with pytest.raises(SynthbosError, match="differ in shape"):
        track_pairs(refs, grads[:, :, :-1], prior_xy=prior, device="cpu")
    with pytest.raises(SynthbosError, match=r"\(pairs, height, width\)"):
        track_pairs(refs[0], grads[0], prior_xy=prior[0], device="cpu")
    bad = grads.copy()
    bad[2, 5, 5] = np.nan
    with pytest.raises(SynthbosError, match="pair 2"):
        track_pairs(refs, bad, prior_xy=prior, device="cpu")
    with pytest.raises(SynthbosError, match="Nx2"):
        track_pairs(refs, grads, prior_xy=prior[:2], device="cpu")
    with pytest.raises(SynthbosError, match="default estimators"):
        track_pairs(refs, grads, prior_xy=prior, settings=TrackingSettings.paper(), device="cpu")
    with pytest.raises(SynthbosError, match=r"mask must be an HxW or 4xHxW"):
        track_pairs(refs, grads, prior_xy=prior, mask=np.zeros((2, *SHAPE), bool), device="cpu")
    with pytest.raises(SynthbosError, match="mask has shape"):
        track_pairs(refs, grads, prior_xy=prior, mask=np.zeros((4, 8, 8), bool), device="cpu")
    everything = np.zeros((4, *SHAPE), bool)
    everything[3] = True
    with pytest.raises(SynthbosError, match="excludes every pixel"):
        track_pairs(refs, grads, prior_xy=prior, mask=everything, device="cpu")


def test_track_pairs_pairs_of_different_dot_sizes(device):
    """Pairs whose windows differ (3 and 5 px dots) are tracked in groups, each as track_pair does."""
    rng = np.random.default_rng(7)
    xy = dot_pattern(rng, SHAPE, per_32x32=12, min_distance=4.0)
    disp = smooth_displacement(xy, SHAPE, 1.0)
    refs = np.array([draw_dots(SHAPE, xy, d) + 0.01 * rng.standard_normal(SHAPE) for d in (3.0, 5.0, 3.0)])
    grads = np.array([draw_dots(SHAPE, xy + disp, d) + 0.01 * rng.standard_normal(SHAPE) for d in (3.0, 5.0, 3.0)])
    tables = track_pairs(refs, grads, prior_xy=xy, device=device)
    for b in range(3):
        _assert_same(tables[b], track_pair(refs[b], grads[b], prior_xy=xy, device=device))
    assert np.median(tables["diameter"][1]) > 1.4 * np.median(tables["diameter"][0])


def test_track_pairs_in_turns(device, monkeypatch):
    """Pairs beyond what one turn holds (pairs_per_call, set to 3 here) are tracked in turns: the same
    table as in one turn (the fit's fixed-point scale depends on the batch: rounding apart), from NumPy
    or Warp stacks, and errors name the pair in the whole stack."""
    import warp as wp
    from synthbos.tracking import stack

    refs, grads, prior = _batch(seed=9)
    refs, grads, prior = np.concatenate([refs, refs[:1]]), np.concatenate([grads, grads[:1]]), prior[[0, 1, 2, 3, 0]]
    whole = track_pairs(refs, grads, prior_xy=prior, device=device)
    asked = []

    def three(shape, dots, dev, *, on_device=True):
        asked.append((shape, dots, on_device))
        return 3

    monkeypatch.setattr(stack, "pairs_per_call", three)
    in_turns = track_pairs(refs, grads, prior_xy=prior, device=device)
    assert asked == [(SHAPE, prior.shape[1], False)]
    for b in range(len(refs)):
        _assert_same(in_turns[b], whole[b])
    stacks = [wp.array(a, dtype=wp.float64, device=device) for a in (refs, grads)]
    shared = track_pairs(*stacks, prior_xy=prior[0], device=device)
    assert asked[-1][2] is True
    _assert_same(shared[4], whole[0])
    bad = grads.copy()
    bad[4] = 0.0
    with pytest.raises(SynthbosError, match="pair 4's gradient image is all zero"):
        track_pairs(refs, bad, prior_xy=prior, device=device)


def test_pairs_per_call_on_the_cpu_is_unbounded():
    from synthbos.tracking.stack import pairs_per_call

    assert pairs_per_call((512, 512), 5120, "cpu") is None
