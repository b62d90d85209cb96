"""Stacked tracking (tracking.stack.track_pairs), the method's one orchestration: each pair of a stack
tracked as alone, against the displacement the pairs were drawn with, for every estimator, with and
without a prior, with masks, in groups and in turns."""

import numpy as np
import pytest
from _synth import dot_pattern, smooth_displacement
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import DotStatus, TrackingSettings, is_valid, track_pair
from synthbos.tracking.stack import track_pairs

from synthbos import SynthbosError

SHAPE = (96, 128)


def _batch(seed=2, truth=False):
    """Four pairs of one dense pattern: clean, noisy, saturated, a strong field; priors with NaN rows,
    rows outside the image and rows far from their dots (and with ``truth``, each pair's displacement)."""
    rng = np.random.default_rng(seed)
    xy = dot_pattern(rng, SHAPE, per_32x32=35, min_distance=2.0)
    refs, grads, disps = [], [], []
    for k, (amp, shift) in enumerate(((1.0, 0.0), (2.5, 3.0), (0.3, 0.0), (1.8, 0.0))):
        disp = smooth_displacement(xy, SHAPE, amp) + shift
        r = draw_dots(SHAPE, xy, 3.0) + 0.02 * k * rng.standard_normal(SHAPE)
        g = draw_dots(SHAPE, xy + disp, 3.0) + 0.02 * k * rng.standard_normal(SHAPE)
        if k == 2:
            r, g = np.minimum(r, 0.8), np.minimum(g, 0.8)
        refs.append(r)
        grads.append(g)
        disps.append(disp)
    prior = np.repeat((xy + 0.4 * rng.standard_normal(xy.shape))[None], 4, axis=0)
    prior[1, :5] = np.nan
    prior[2, :3] = -5.0
    prior[3, 10:15] += 0.9
    if truth:
        return np.array(refs), np.array(grads), prior, xy, np.array(disps)
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


SETTINGS = {
    "default": TrackingSettings(),
    "no-predictor": TrackingSettings(predictor="none"),
    "fixed-diameter": TrackingSettings(diameter=3.0, max_iterations=2),
    "paper": TrackingSettings.paper(),
    "gaussian4-paper-correction": TrackingSettings(centroid="gaussian4", correction="paper"),
}


def _errors(table, xy, disp, columns=("u", "v")):
    """Per valid row of a table: its displacement error (px) against the drawn one, the row's dot found by
    its reference position (nearest drawn dot within 0.5 px)."""
    ok = is_valid(table)
    t = table[ok]
    d2 = (t["x"][:, None] - xy[None, :, 0]) ** 2 + (t["y"][:, None] - xy[None, :, 1]) ** 2
    near = np.argmin(d2, axis=1)
    close = d2[np.arange(len(t)), near] < 0.25
    e = np.hypot(t[columns[0]] - disp[near, 0], t[columns[1]] - disp[near, 1])
    return e[close], ok.mean()


@pytest.mark.parametrize("name", list(SETTINGS))
def test_each_pair_of_a_stack_is_tracked_as_alone_and_right(device, name):
    """Every pair of a stack gets the table it gets alone (``track_pair``, a stack of one: on the CPU the
    same bytes; on a GPU the float atomics of the residual images may move last bits from run to run), and
    the clean pair's displacements are those it was drawn with, for each estimator."""
    settings = SETTINGS[name]
    refs, grads, prior, xy, disp = _batch(truth=True)
    tables = track_pairs(refs, grads, prior_xy=prior, settings=settings, device=device)
    assert tables.shape == prior.shape[:2]
    # each row names its prior row
    assert_array_equal(tables["dot_id"], np.broadcast_to(np.arange(prior.shape[1]), prior.shape[:2]))
    for b in range(len(refs)):
        alone = track_pair(refs[b], grads[b], prior_xy=prior[b], settings=settings, device=device)
        if device == "cpu":
            assert alone.tobytes() == tables[b].tobytes(), b
        else:
            _assert_same(alone, tables[b])
    # the clean pair (a dense pattern of overlapping dots, 35 per 32 x 32 px, in a smooth field of 1 px):
    # p90 0.062 and 0.057 px with the model (u, u_cc), 0.16 and 0.28 px with the paper's estimators
    for columns, bounds in ((("u", "v"), (0.1, 0.3)), (("u_cc", "v_cc"), (0.1, 0.45))):
        e, valid = _errors(tables[0], xy, disp[0], columns)
        assert valid > 0.85 and e.size > 300, (columns, valid, e.size)
        assert np.percentile(e, 90) < bounds[settings.centroid != "model"], (columns, np.percentile(e, 90))
    # the batch holds the cases it is meant to: claims lost, later rounds, outliers, misses
    status = tables["status"]
    assert np.count_nonzero(status & DotStatus.AMBIGUOUS) > 10
    assert np.count_nonzero(tables["iteration"] > 1) > 10
    assert np.count_nonzero(status & DotStatus.MATCHED) > 1000


@pytest.mark.parametrize("name", ["default", "paper"])
def test_standard_tracking_in_a_stack(device, name):
    """Without a prior each pair's dots are identified, paired and tracked in the stack as alone: one table
    per pair, of its reference image's dots (dot_id -1), and the clean pair's displacements are right."""
    settings = SETTINGS[name]
    refs, grads, _, xy, disp = _batch(truth=True)
    tables = track_pairs(refs[:3], grads[:3], settings=settings, device=device)
    assert len(tables) == 3
    for b, table in enumerate(tables):
        alone = track_pair(refs[b], grads[b], settings=settings, device=device)
        if device == "cpu":
            assert alone.tobytes() == table.tobytes(), b
        else:
            _assert_same(alone, table)
        assert (table["dot_id"] == -1).all()
    e, valid = _errors(tables[0], xy, disp[0])  # p90 0.074 px (default) and 0.071 px (paper)
    assert valid > 0.75 and e.size > 250, (valid, e.size)
    assert np.percentile(e, 90) < 0.12, np.percentile(e, 90)


def test_masks_in_a_stack(device):
    """A mask per pair (a disk, a stripe at the edge, none): each pair gets the table it gets alone with
    its mask; the dots near the excluded pixels are MASKED, none of them matched, and the unmasked pair's
    table is the one it has without a mask."""
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
    for b in range(len(refs)):
        alone = track_pair(refs[b], grads[b], prior_xy=prior[b], mask=masks[b], device=device)
        if device == "cpu":
            assert tables[b].tobytes() == alone.tobytes(), b
        else:
            _assert_same(tables[b], alone)
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


def test_tables_do_not_depend_on_fresh_memory(device, monkeypatch):
    """Nothing the tables hold is read from memory before it is written: with every array that
    ``wp.empty`` and ``wp.empty_like`` make (the thread's workspace among them, made afresh) filled with
    0x7f bytes (float64 1.4e306, int32 2,139,062,143), the tables are the same bytes. (On CUDA, Compute
    Sanitizer's initcheck also flags reads of values never used: the common-shape model image in the fit's
    earlier steps, on 2026-11-27.)"""
    import warp as wp
    from synthbos.tracking import workspace

    refs, grads, prior = _batch(seed=4)
    plain = track_pairs(refs, grads, prior_xy=prior, device=device)
    empty, empty_like = wp.empty, wp.empty_like

    def poisoned(a):
        if a.size:
            wp.array(ptr=a.ptr, dtype=wp.uint8, shape=(a.capacity,), device=a.device).fill_(0x7F)
        return a

    monkeypatch.setattr(wp, "empty", lambda *a, **k: poisoned(empty(*a, **k)))
    monkeypatch.setattr(wp, "empty_like", lambda *a, **k: poisoned(empty_like(*a, **k)))
    monkeypatch.setattr(workspace._local, "arrays", {}, raising=False)
    assert track_pairs(refs, grads, prior_xy=prior, device=device).tobytes() == plain.tobytes()


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


def test_stamps_leave_the_residual_in_any_order():
    """Identification's GPU engine takes found dots near a waiting dot out of the residual image in
    fixed point (``claim_kernels.stamp_near_waiting``, ``apply_stamps``): the residual has the same bits
    whatever order the threads run in (here: the dots' ids forward and reversed, their stamps
    overlapping), is Eq. 2's (``subtract_gaussians``) to 1e-11 of the peak, and the stamps are left zero."""
    import warp as wp
    from synthbos.tracking import claim_kernels as ck
    from synthbos.tracking.residual import subtract_gaussians
    from synthbos.tracking.settings import RESIDUAL_STAMP_WIDTHS, RESIDUAL_WIDTH_CLIP

    rng = np.random.default_rng(7)
    per_frame, shape, eta0 = 8, (2, 24, 28), 1.1
    # frame 0: six found dots crowded around a waiting one (row 0), one found dot far away (row 7);
    # frame 1: its copy, nothing waiting
    crowd = np.array([12.3, 11.6]) + rng.uniform(-2.5, 2.5, (6, 2))
    xy = np.vstack([[12.3, 11.6], crowd, [2.0, 3.0]])
    xy = np.vstack([xy, xy])
    found = np.ones(2 * per_frame, bool)
    found[0] = False
    x = np.where(found, xy[:, 0], np.nan)
    i0, eta = rng.uniform(0.3, 2.0, 2 * per_frame), rng.uniform(0.4, 2.0, 2 * per_frame)
    image = rng.uniform(0.0, 1.0, shape)
    todo = np.where(found, 0, np.r_[1, np.zeros(2 * per_frame - 1)]).astype(np.int32)
    reach = np.full(2, 6.0)

    def arr(a, dtype):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device="cpu")

    def run(ids):
        residual, stamps = arr(image, wp.float64), wp.zeros(shape, dtype=wp.int64, device="cpu")
        subtracted = wp.zeros(2 * per_frame, dtype=wp.int32, device="cpu")
        points = wp.empty(2 * per_frame, dtype=wp.vec3, device="cpu")
        pred, todo_ = arr(xy, wp.vec2d), arr(todo, wp.int32)
        wp.launch(ck.waiting_points, 2 * per_frame, [pred, todo_, per_frame, 1000.0, points], device="cpu")
        grid = wp.HashGrid(16, 16, 4, device="cpu")
        grid.build(points, 7.0)
        ids = arr(ids, wp.int32)
        fx, fy = arr(x, wp.float64), arr(xy[:, 1], wp.float64)
        e0, peak, one = arr([eta0, eta0], wp.float64), arr([1.3, 1.3], wp.float64), arr([1, 1], wp.int32)
        wp.launch(ck.stamp_near_waiting, len(ids), [grid.id, ids, per_frame, 1000.0, 1, one, pred, todo_, fx, fy,
                  arr(eta, wp.float64), arr(i0, wp.float64), e0, arr(reach, wp.float64), peak, subtracted, stamps],
                  device="cpu")  # fmt: skip
        wp.launch(ck.apply_stamps, len(ids), [ids, per_frame, 1, fx, fy, e0, peak, subtracted, arr(image, wp.float64),
                  stamps, residual], device="cpu")  # fmt: skip
        wp.launch(ck.clear_stamps, len(ids), [ids, per_frame, fx, fy, e0, subtracted, stamps], device="cpu")
        return residual.numpy(), subtracted.numpy(), stamps.numpy()

    ids = np.arange(2 * per_frame)
    forward, subtracted, stamps = run(ids)
    backward, _, _ = run(ids[::-1].copy())
    assert forward.tobytes() == backward.tobytes()
    assert_array_equal(subtracted, np.r_[0, np.ones(6), np.zeros(9)])  # the six near the waiting dot only
    assert not stamps.any()
    lo, hi = RESIDUAL_WIDTH_CLIP
    near = np.arange(1, 7)
    expect = subtract_gaussians(image[0], xy[near], i0[near], np.clip(eta[near], lo * eta0, hi * eta0),
                                radius=int(np.ceil(RESIDUAL_STAMP_WIDTHS * eta0)))  # fmt: skip
    assert np.abs(expect - image[0]).max() > 0.5  # the stamps overlap and take real light
    assert_allclose(forward[0], expect, rtol=0, atol=1e-11 * 1.3)
    assert_array_equal(forward[1], image[1])
