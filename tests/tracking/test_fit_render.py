"""The model fit's render: split over the stamps' columns (a GPU's engine) it draws the same fixed-point
images, to the bit, as a thread per dot (the CPU's), its profiles computed in it or ahead of it, in the
fit's own profiles array (on a GPU a transposed view) or a contiguous one."""

import numpy as np
import pytest
import warp as wp
from numpy.testing import assert_array_equal
from synthbos.tracking import fit_kernels as fk
from synthbos.tracking.dotfit import _profiles

H, W, HALF = 40, 56, 4


def _rows(rng, n, frames):
    """Dots anywhere in the frames, some of whose stamps cross the image's edges, and their partners."""
    params = np.column_stack([
        rng.uniform(-2.0, W + 1.0, n), rng.uniform(-2.0, H + 1.0, n), rng.uniform(0.2, 1.5, n),
        rng.uniform(0.5, 1.4, n), np.zeros(n),
    ])  # fmt: skip
    frame = rng.integers(0, frames, n).astype(np.int32)
    partner = np.where(rng.random(n) < 0.8, rng.permutation(n), -1).astype(np.int32)
    return params, frame, partner


def _render(device, params, frame, partner, frames, *, common, parts):
    n = len(params)
    p = wp.array(params, dtype=wp.float64, device=device)
    # split: the fit's own profiles array (on a GPU a transposed view, a warp's dots side by side)
    if parts > 1:
        prof = _profiles("test_profiles", n, HALF, device, large=True)
    else:
        prof = wp.zeros((n, 6, 2 * HALF + 1), dtype=wp.float64, device=device)
    scales = wp.array(np.linspace(2.0**30, 2.0**31, frames), dtype=wp.float64, device=device)
    models = wp.zeros(2 * frames * H * W, dtype=wp.int64, device=device)
    if parts > 1:
        wp.launch(fk.dot_profiles_kernel, dim=n, inputs=[p, HALF, prof], device=device)
    inputs = [p, wp.array(frame, device=device), wp.array(partner, device=device), HALF, common, int(parts == 1),
              parts, prof, scales, H, W, models]  # fmt: skip
    wp.launch(fk.render_dots_kernel, dim=n * parts, inputs=inputs, device=device)
    return models.numpy(), prof.numpy()


@pytest.mark.parametrize("common", [0, 1])
def test_render_split_over_columns_draws_the_same_bits(device, common):
    rng = np.random.default_rng(5)
    frames = 3
    params, frame, partner = _rows(rng, 300, frames)
    whole, prof_whole = _render(device, params, frame, partner, frames, common=common, parts=1)
    split, prof_split = _render(device, params, frame, partner, frames, common=common, parts=2 * HALF + 1)
    assert_array_equal(split, whole)
    assert_array_equal(prof_split, prof_whole)
    drawn = whole.reshape(2, frames, H, W)
    assert (drawn[0] != 0).mean() > 0.5  # the dots cover the images, edges included
    assert (drawn[0, :, 0, :] != 0).any() and (drawn[0, :, :, -1] != 0).any()
    assert (drawn[1] != 0).any() == bool(common)
    # the free layer sums each dot's fixed-point stamp: its total is the dots' integrated intensity
    scales = np.linspace(2.0**30, 2.0**31, frames)
    inside = (np.abs(params[:, 0] - W / 2) < W / 2 - HALF - 2) & (np.abs(params[:, 1] - H / 2) < H / 2 - HALF - 2)
    total = drawn[0].sum(axis=(1, 2)) / scales
    volume = params[:, 2] * 2 * np.pi * params[:, 3] ** 2
    assert np.all(total > 0.9 * np.bincount(frame[inside], weights=volume[inside], minlength=frames))
