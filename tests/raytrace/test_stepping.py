"""RK4 stepping through the volume: steps that end at node planes ("cells", the default) against equal
steps ("fixed"), both against a float64 trace with fine steps (``raytrace.reference``)."""

import numpy as np
import pytest
import warp as wp
from _small import small_config
from synthbos.raytrace import kernels, reference
from synthbos.raytrace.medium import to_warp
from synthbos.raytrace.render import plan_render, render_pair

_FLOWS = {
    "slice": {"source": "slice", "snapshot": 0},  # the paper's turbulence: one node plane through the depth
    "blob": {"source": "gaussian", "sigma_mm": 2.0, "amplitude_kg_m3": 0.2, "grid": [40, 40, 20]},
}


def _rays(plan, n=16, seed=3, *, side=False):
    """Rays across the volume; ``side``: rays that leave it through its side at x = +half (where the
    field stops: a jump, not only a kink), as the rays of dots near the image's edges do."""
    med = plan.medium
    rng = np.random.default_rng(seed)
    c, half = np.array(med.centre), np.array(med.size) / 2.0
    lo, hi = (0.985, 0.995) if side else (-0.9, 0.9)
    x = rng.uniform(lo, hi, n) * half[0]
    y = rng.uniform(-0.9, 0.9, n) * half[1]
    o = np.stack([x + c[0], y + c[1], np.full(n, c[2] - half[2] - 1e-3)], axis=1)
    t = np.concatenate([rng.uniform(0.01, 0.03, (n, 1)) if side else rng.uniform(-0.03, 0.03, (n, 1)),
                        rng.uniform(-0.03, 0.03, (n, 1)), np.ones((n, 1))], axis=1)
    return o, t / np.linalg.norm(t, axis=1, keepdims=True)


def _trace(plan, o, t, device, *, step, cells):
    m = to_warp(plan.medium, device=device, field="float32_vec")
    n = len(o)
    xo, to = wp.zeros(n, dtype=wp.vec3, device=device), wp.zeros(n, dtype=wp.vec3, device=device)
    wp.launch(kernels.trace_to_exit, dim=n, device=device, outputs=[xo, to],
              inputs=[m, 1, wp.array(o.astype(np.float32), dtype=wp.vec3, device=device),
                      wp.array(t.astype(np.float32), dtype=wp.vec3, device=device), step, int(cells)])
    return xo.numpy().astype(np.float64), to.numpy().astype(np.float64)


@pytest.mark.parametrize("flow", [*_FLOWS, "slice-side"])
def test_cell_steps_follow_the_float64_trace_closer_than_equal_steps(flow, device):
    side = flow.endswith("side")
    plan = plan_render(small_config(volume=_FLOWS[flow.split("-")[0]]))
    o, t = _rays(plan, n=16, side=side)
    # Equal steps err by O(step) where the field stops at the box's side: the reference's too, so finer there.
    x_ref, t_ref = reference.trace_volume(plan.medium, o, t, plan.step / (16 if side else 4))
    px_per_rad = plan.camera.magnification * plan.medium.centre[2] / plan.camera.pitch  # an angle's image
    px_per_m = plan.camera.magnification / plan.camera.pitch
    deflection = np.abs(t_ref[:, :2] - t[:, :2]).max() * px_per_rad
    assert deflection > 0.05  # strong enough to matter
    errors = {}
    for name, step, cells in (("fixed", plan.step, 0), ("cells", plan.ray_step, 1)):
        x, tt = _trace(plan, o, t, device, step=step, cells=cells)
        errors[name] = (np.abs(tt[:, :2] - t_ref[:, :2]).max() * px_per_rad,
                        np.abs(x[:, :2] - x_ref[:, :2]).max() * px_per_m)
    print(f"\n{flow}: deflection {deflection:.3f} px; exit angle / position error (px): "
          + ", ".join(f"{k} {a:.2e} / {b:.2e}" for k, (a, b) in errors.items()))
    assert plan.ray_step == pytest.approx(plan.medium.size[2] / 4)  # the default: a quarter of the depth
    if side:  # the reference's own error at the side is ~1/16 of the equal grid steps'
        assert errors["cells"][0] < 5e-4 and errors["cells"][0] < errors["fixed"][0] / 5
    else:
        assert errors["cells"][0] < 5e-5 and errors["cells"][1] < 1.5e-4
        assert errors["cells"][0] < errors["fixed"][0] and errors["cells"][1] < errors["fixed"][1]


def test_fixed_stepping_is_still_there_and_both_agree_on_a_render():
    slice_ = {"source": "slice", "snapshot": 2}
    cells = render_pair(small_config(volume=slice_, rays={"per_dot": 30}), device="cpu")
    fixed = render_pair(small_config(volume=slice_, rays={"per_dot": 30, "stepping": "fixed"}), device="cpu")
    assert not np.array_equal(cells.displacement_px, fixed.displacement_px)
    np.testing.assert_allclose(cells.displacement_px, fixed.displacement_px, atol=1e-3)
    np.testing.assert_array_equal(cells.theory_cone_px, fixed.theory_cone_px)  # the truths do not step
