"""Planar media (a 2-D field carried through the depth, like the embedded slices): the exact fields
sample one node plane bilinearly instead of blending two equal planes, the same numbers up to the
rounding of that blend."""

import numpy as np
import warp as wp
from _small import small_config
from synthbos.raytrace import kernels, sources
from synthbos.raytrace.medium import EXACT_FIELDS, is_planar, to_warp
from synthbos.raytrace.render import plan_render, render_pair

_SLICE = {"source": "slice", "snapshot": 2}


def test_planar_media_are_recognised():
    assert is_planar(plan_render(small_config(volume=_SLICE)).medium.field)
    assert sources.extruded(_SLICE)  # what render_modules takes without building the medium
    blob = {"source": "gaussian", "sigma_mm": 4.0, "amplitude_kg_m3": 0.05, "grid": [24, 24, 8]}
    assert not is_planar(plan_render(small_config(volume=blob)).medium.field)
    field = np.zeros((3, 4, 5, 4), np.float32)
    assert is_planar(field)
    field[2, 1, 1, 0] = 1e-30  # one node of one plane differs
    assert not is_planar(field)


def _trace(medium, device, n=256):
    """Rays from a fan of points and directions across the volume's front: exit positions and tangents."""
    rng = np.random.default_rng(4)
    o = np.concatenate([rng.uniform(-12e-3, 12e-3, (n, 2)), np.zeros((n, 1))], axis=1)
    t = np.concatenate([rng.uniform(-0.03, 0.03, (n, 2)), np.ones((n, 1))], axis=1)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    xo, to = wp.zeros(n, dtype=wp.vec3, device=device), wp.zeros(n, dtype=wp.vec3, device=device)
    wp.launch(kernels.trace_to_exit, dim=n, device=device, outputs=[xo, to],
              inputs=[medium, 1, wp.array(o.astype(np.float32), dtype=wp.vec3, device=device),
                      wp.array(t.astype(np.float32), dtype=wp.vec3, device=device), 1e-4, 0])
    return xo.numpy(), to.numpy() - t.astype(np.float32)


def test_one_plane_sampling_matches_the_blend_of_equal_planes(device):
    plan = plan_render(small_config(volume=_SLICE))
    for field in EXACT_FIELDS:
        m = to_warp(plan.medium, device=device, field=field)
        assert m.planar == 1, field
        x1, dt1 = _trace(m, device)
        m.planar = 0  # the trilinear blend of the two equal planes
        x0, dt0 = _trace(m, device)
        scale = np.abs(dt0).max()
        assert scale > 1e-5  # the rays are deflected
        print(f"\n{field}: deflection max {scale:.3e}, planar - blended max {np.abs(dt1 - dt0).max():.2e}")
        np.testing.assert_allclose(dt1, dt0, rtol=0, atol=1e-5 * scale)
        np.testing.assert_allclose(x1, x0, rtol=0, atol=1e-9)
    # The flag decides the path: on a field that varies along z, reading one plane is another field.
    blob = {"source": "gaussian", "sigma_mm": 4.0, "amplitude_kg_m3": 0.05, "grid": [24, 24, 8]}
    m = to_warp(plan_render(small_config(volume=blob)).medium, device=device, field="float32_vec")
    assert m.planar == 0
    _, dt3 = _trace(m, device)
    m.planar = 1
    assert np.abs(_trace(m, device)[1] - dt3).max() > 0.01 * np.abs(dt3).max()


def test_exact_fields_give_the_same_bits_on_a_planar_medium():
    """On the CPU the exact fields read the same float32 values and do the same arithmetic."""
    cfg = small_config(volume=_SLICE, rays={"per_dot": 40})
    first = render_pair(cfg, device="cpu")
    for field in EXACT_FIELDS[1:]:
        other = render_pair(small_config(volume=_SLICE, rays={"per_dot": 40, "field": field}), device="cpu")
        np.testing.assert_array_equal(other.gradient, first.gradient)
        np.testing.assert_array_equal(other.displacement_px, first.displacement_px)
        np.testing.assert_array_equal(other.theory_cone_px, first.theory_cone_px)


def test_plans_of_one_volume_share_its_density_read_only():
    """A campaign renders many pairs of each snapshot: the density of a volume table is read once (the
    last two tables are kept), shared read-only, and gives the same medium."""
    a = plan_render(small_config(volume={"source": "slice", "snapshot": 1}))
    b = plan_render(small_config(volume={"source": "slice", "snapshot": 1}, target={"seed": 5}))
    assert b.medium.density is a.medium.density and not a.medium.density.rho.flags.writeable
    assert b.medium.field.tobytes() == a.medium.field.tobytes()
    c = plan_render(small_config(volume={"source": "slice", "snapshot": 3}))
    assert c.medium.density is not a.medium.density
