"""A CUDA render sums each block's spots in shared-memory tiles before it adds them to the image
(``kernels.render_rays`` with ``tile_side > 0``, ``render.spot_tile_side``): the same integer sums, so the
same images and truths to the bit as a render that adds every spot's pixels to the image directly, with
spots on the tiles, across their edges (strong displacements) and with four wide tiles a block."""

import numpy as np
import pytest
import warp as wp
from _small import small_config
from synthbos.raytrace import render
from synthbos.raytrace.render import render_pair, spot_tile_side

CASES = {
    "slice": {},
    "strong planar waves, 11 px tiles (spots across their edges)": {
        "volume": {
            "source": "sinusoidal",
            "direction": [1, 0, 0],
            "amplitude_kg_m3": 1.0,
            "wavelength_mm": 6.0,
            "density_kg_m3": 1.2,
        },
        "rays": {"rays_per_thread": 8, "rays_per_group": 8},
    },
    "slice, 8 rays a thread in groups of 64 (24 px tiles)": {"rays": {"rays_per_thread": 8, "rays_per_group": 64}},
}


@pytest.mark.gpu
@pytest.mark.parametrize("case", list(CASES))
def test_spot_tiles_give_the_same_bits(case, monkeypatch):
    wp.init()
    if not wp.is_cuda_available():
        pytest.skip("no CUDA device visible to Warp")
    tables = {k: dict(v) for k, v in CASES[case].items()}
    tables.setdefault("rays", {})["per_dot"] = 400
    cfg = small_config(**tables)
    tiled = render_pair(cfg, device="cuda:0")
    monkeypatch.setattr(render, "spot_tile_side", lambda *a: 0)
    plain = render_pair(cfg, device="cuda:0")
    moved = np.abs(tiled.displacement_px[tiled.valid]).max()
    print(f"\n{case}: {tiled.n_dots} dots, largest displacement {moved:.2f} px")
    if "edges" in case:
        assert moved > 4.0  # spots of the gradient image well off their tiles
    for name in ("reference", "gradient", "reference_px", "gradient_px", "theory_px", "ray_covariance_px2"):
        np.testing.assert_array_equal(getattr(tiled, name), getattr(plain, name), err_msg=name)
    assert tiled.gradient.max() > 0


def test_tile_side_holds_a_spot():
    """A tile holds a spot with a pixel of play each way, or there are none."""
    for block_dim in (32, 64, 128, 256, 512, 1024):
        for group in (1, 2, 4, 8, 16, 32, 64, 3):
            for half_width in (1, 2, 3, 5, 8):
                side = spot_tile_side(block_dim, group, half_width, 8)
                assert spot_tile_side(block_dim, group, half_width, 1) == 0
                if side:
                    assert block_dim % group == 0 and side >= 2 * half_width + 3
                    assert (block_dim // group) * side * side <= render.kernels.SPOT_CELLS
    assert spot_tile_side(256, 8, 3, 8) == 11
