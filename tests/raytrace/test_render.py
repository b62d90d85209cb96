"""Physics of the renderer, on every Warp device: each test takes ``device`` (cpu, and cuda:0 where present)."""

import numpy as np
import pytest
import warp as wp
from _small import small_config as _config
from numpy.testing import assert_allclose
from synthbos.raytrace import kernels, reference
from synthbos.raytrace.medium import medium_from_density, to_warp
from synthbos.raytrace.render import plan_render, render_pair
from synthbos.raytrace.sources import DensityField, node_coordinates


def test_uniform_medium_gives_identical_images_and_zero_displacement(device):
    """The same bits on the CPU; on CUDA the compiler contracts the straight rays' position sums into
    fused multiply-adds differently in the reference image's kernel (no medium) and the gradient
    image's, which moves spots by ~1e-7 px."""
    pair = render_pair(_config(volume={"source": "uniform", "density_kg_m3": 1.5, "grid": [8, 8, 4]}), device=device)
    assert pair.valid.all()
    if device == "cpu":
        np.testing.assert_array_equal(pair.reference, pair.gradient)
        np.testing.assert_array_equal(pair.displacement_px, 0.0)
    else:
        np.testing.assert_allclose(pair.gradient, pair.reference, rtol=0, atol=1e-6 * pair.reference.max())
        np.testing.assert_allclose(pair.displacement_px, 0.0, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(pair.theory_px, 0.0)
    assert pair.reference.sum() > 0


def test_constant_transverse_gradient_deflection_and_displacement(device):
    gx, K, W = 50.0, 2.25e-4, 10e-3  # kg/m^4, m^3/kg, volume depth (m)
    cfg = _config(volume={"source": "linear", "gradient_kg_m4": [gx, 0.0], "grid": [16, 16, 8]})
    pair = render_pair(cfg, device=device)
    plan = plan_render(cfg)
    n0 = plan.medium.n0
    eps = K * gx * W / n0  # deflection angle (rad)

    # The deflection of a ray through the volume.
    m = to_warp(plan.medium, device=device)
    o = wp.array(np.array([[0.0, 0.0, 0.0], [2e-3, -1e-3, 0.0]], np.float32), dtype=wp.vec3, device=device)
    t0 = np.array([[0.0, 0.0, 1.0], [-2e-3, 1e-3, 1.0]])
    t0 /= np.linalg.norm(t0, axis=1, keepdims=True)
    t = wp.array(t0.astype(np.float32), dtype=wp.vec3, device=device)
    xo, to = wp.zeros(2, dtype=wp.vec3, device=device), wp.zeros(2, dtype=wp.vec3, device=device)
    wp.launch(kernels.trace_to_exit, dim=2, inputs=[m, 1, o, t, plan.step, 0], outputs=[xo, to], device=device)
    angle = np.arctan(to.numpy()[:, 0] / to.numpy()[:, 2]) - np.arctan(t0[:, 0] / t0[:, 2])
    assert_allclose(angle, eps, rtol=0.01)

    # The dot displacement: M Z_D eps in pixels, towards lower density (-x).
    expected = -plan.camera.magnification * plan.medium.centre[2] * eps / plan.camera.pitch
    d = pair.displacement_px[pair.valid]
    print(f"\nconstant gradient: eps = {eps:.4e} rad, expected dX = {expected:.5f} px, "
          f"ray-traced mean {d[:, 0].mean():.5f} px (range {d[:, 0].min():.5f} .. {d[:, 0].max():.5f})")
    assert pair.valid.sum() >= 0.9 * pair.n_dots
    assert_allclose(d[:, 0], expected, rtol=0.01)
    assert_allclose(d[:, 1], 0.0, atol=0.01 * abs(expected))
    assert_allclose(pair.theory_px[pair.valid, 0], expected, rtol=0.01)


def _strong_linear_medium():
    # n - 1 = K rho with K = 1: a strongly refracting, exactly linear index field on which trilinear
    # sampling is exact, so the ray equation is smooth and RK4 shows its order.
    size = (0.02, 0.02, 0.02)
    x, y, z = node_coordinates((5, 5, 5), size)
    _, Y, X = np.meshgrid(z, y, x, indexing="ij")
    rho = 1.0 + 40.0 * X + 20.0 * Y
    return medium_from_density(DensityField(rho=rho, size_m=size, ambient=1.0), gladstone_dale=1.0, centre=(0, 0, 0.1))


_RAYS_O = np.array([[0.001, 0.002, 0.0], [-0.003, 0.001, 0.0]])
_RAYS_T = np.array([[0.0, 0.0, 1.0], [0.01, -0.02, 1.0]])
_RAYS_T = _RAYS_T / np.linalg.norm(_RAYS_T, axis=1, keepdims=True)
_STEPS = [0.02 / n for n in (3, 6, 12, 24)]


def test_rk4_order_of_the_algorithm():
    med = _strong_linear_medium()
    exact, _ = reference.trace_volume(med, _RAYS_O, _RAYS_T, 0.02 / 3072)
    errs = [np.abs(reference.trace_volume(med, _RAYS_O, _RAYS_T, h)[0] - exact)[:, :2].max() for h in _STEPS]
    slope = np.polyfit(np.log(_STEPS), np.log(errs), 1)[0]
    print(f"\nRK4 (float64 twin): errors {[f'{e:.2e}' for e in errs]} m, log-log slope {slope:.3f}")
    assert 3.8 <= slope <= 4.2


def test_rk4_kernel_matches_float64_twin_and_shows_its_order(device):
    med = _strong_linear_medium()
    m = to_warp(med, device=device)
    exact, _ = reference.trace_volume(med, _RAYS_O, _RAYS_T, 0.02 / 3072)
    o = wp.array(_RAYS_O.astype(np.float32), dtype=wp.vec3, device=device)
    t = wp.array(_RAYS_T.astype(np.float32), dtype=wp.vec3, device=device)
    errs = []
    for h in _STEPS:
        xo, to = wp.zeros(2, dtype=wp.vec3, device=device), wp.zeros(2, dtype=wp.vec3, device=device)
        wp.launch(kernels.trace_to_exit, dim=2, inputs=[m, 1, o, t, h, 0], outputs=[xo, to], device=device)
        twin_x, twin_t = reference.trace_volume(med, _RAYS_O, _RAYS_T, h)
        # float32 rounding over a 2 cm box: a few 1e-10 m
        assert_allclose(xo.numpy(), twin_x, atol=3e-9)
        assert_allclose(to.numpy(), twin_t, atol=3e-7)
        errs.append(np.abs(xo.numpy() - exact)[:, :2].max())
    # The kernel follows its float64 twin (slope 3.8-4.2, test above) down to float32's floor, a few
    # 1e-10 m in a 2 cm box, which the errors at the finer steps reach; the two coarsest steps lie
    # above it, and there the kernel's own slope is that of a 4th-order method (float32 rounding,
    # FMA contraction on CUDA, moves it by ~0.2; a 2nd-order method would show 2).
    slope = np.log(errs[0] / errs[1]) / np.log(_STEPS[0] / _STEPS[1])
    print(f"\nRK4 kernel on {device}: errors {[f'{e:.2e}' for e in errs]} m, coarse slope {slope:.3f}")
    assert 3.5 <= slope <= 4.5


def test_thin_lens_ray_mean_is_geometric_image(device):
    pair = render_pair(_config(volume={"source": "uniform", "grid": [4, 4, 2]}, rays={"per_dot": 500}), device=device)
    plan = plan_render(_config(volume={"source": "uniform", "grid": [4, 4, 2]}))
    geometric = plan.camera.target_to_pixel(pair.target_xy_m)
    err = np.abs(pair.reference_px - geometric).max()
    print(f"\nthin lens: max |ray mean - geometric image| = {err:.2e} px over {pair.n_dots} dots")
    assert err < 1e-3


def test_weak_gaussian_blob_agrees_with_eq4(device):
    cfg = _config(
        camera={"pixels": [128, 128]}, rays={"per_dot": 300}, target={"dots_per_32px": 10},
        volume={"source": "gaussian", "sigma_mm": 6.0, "amplitude_kg_m3": 0.02, "grid": [32, 32, 16]},
    )
    pair = render_pair(cfg, device=device)
    d, th = pair.displacement_px[pair.valid], pair.theory_px[pair.valid]
    rel = np.linalg.norm(d - th) / np.linalg.norm(th)
    print(f"\nGaussian blob: |theory| max {np.abs(th).max():.4f} px, relative RMS difference {rel:.4f}")
    assert np.abs(th).max() > 0.005
    assert rel < 0.04


def test_deposit_kernel_matches_numpy_twin(device):
    plan = plan_render(_config(volume={"source": "uniform", "grid": [4, 4, 2]}))
    from synthbos.raytrace.render import _sensor_struct

    sen = _sensor_struct(plan)
    rng = np.random.default_rng(3)
    px = rng.uniform(-2, 98, size=(40, 2))
    energy = rng.uniform(0.5, 2.0, size=40)
    img = wp.zeros((96, 96), dtype=wp.int64, device=device)
    wp.launch(kernels.deposit_spots, dim=40,
              inputs=[sen, wp.array(px.astype(np.float32), dtype=wp.vec2, device=device),
                      wp.array(energy.astype(np.float32), dtype=float, device=device)],
              outputs=[img], device=device)
    twin = reference.deposit_gaussian((96, 96), px.astype(np.float32), energy.astype(np.float32),
                                      plan.sigma_px, plan.half_width)
    from synthbos.raytrace.render import fixed_to_image

    assert_allclose(fixed_to_image(img.numpy()), twin, atol=2e-6 * energy.max())


@wp.kernel
def _deposit_plain(sen: kernels.Sensor, px: wp.array(dtype=wp.vec2), energy: wp.array(dtype=float),
                   image: wp.array2d(dtype=wp.int64)):
    i = wp.tid()
    kernels.deposit_gaussian_plain(image, sen, px[i], energy[i], (3 * i) % 11)  # any turn: the same sums


@pytest.mark.parametrize(("sigma_px", "half_width"), [(0.75, 3), (0.3, 1), (2.6, 8), (16.0, 48), (0.75, 49)])
def test_deposit_gives_the_plain_loops_bits(device, sigma_px, half_width):
    """``deposit_gaussian`` (on the CPU, column weights kept per spot and each edge's erf read once) adds
    exactly what the plain pixel-by-pixel loop adds, spots across the image's edges and corners included;
    half width 49 is beyond ``kernels.DEPOSIT_WINDOW``, where the CPU too takes the plain loop."""
    sen = kernels.Sensor()
    sen.width, sen.height, sen.pitch, sen.cx, sen.cy = 40, 33, 1.0e-5, 20.0, 16.0
    sen.sigma_px, sen.half_width, sen.energy = sigma_px, half_width, 1.0
    rng = np.random.default_rng(11)
    px = np.concatenate([rng.uniform(-60, 100, size=(300, 2)), rng.uniform(-3, 43, size=(300, 2)),
                         [[0.5, 0.5], [-0.5, 32.5], [39.49, -0.51], [20.0, 16.0]]]).astype(np.float32)
    energy = rng.uniform(0.1, 3.0, size=len(px)).astype(np.float32)
    images = []
    for kernel in (kernels.deposit_spots, _deposit_plain):
        img = wp.zeros((33, 40), dtype=wp.int64, device=device)
        wp.launch(kernel, dim=len(px), inputs=[sen, wp.array(px, dtype=wp.vec2, device=device),
                                               wp.array(energy, dtype=float, device=device)],
                  outputs=[img], device=device)
        images.append(img.numpy())
    assert images[0].sum() > 0
    np.testing.assert_array_equal(images[0], images[1])


def test_medium_sampling_matches_numpy_twin(device):
    rng = np.random.default_rng(5)
    size = (0.01, 0.012, 0.008)
    rho = 1.2 + 0.05 * rng.random((6, 7, 8))
    field = DensityField(rho=rho, size_m=size, ambient=1.2)
    med = medium_from_density(field, gladstone_dale=2.25e-4, centre=(0, 0, 0.2))
    pts = rng.uniform(-0.6, 0.6, size=(200, 3)) * np.array(size)  # some outside the box

    @wp.kernel
    def sample(m: kernels.Medium, p: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec4)):
        i = wp.tid()
        out[i] = kernels.sample_medium(m, p[i])

    out = wp.zeros(200, dtype=wp.vec4, device=device)
    wp.launch(sample, dim=200, inputs=[to_warp(med, device=device),
                                       wp.array(pts.astype(np.float32), dtype=wp.vec3, device=device)],
              outputs=[out], device=device)
    twin = reference.sample_medium(med, pts.astype(np.float32))
    scale = np.abs(med.field).max(axis=(0, 1, 2))
    assert_allclose(out.numpy() / scale, twin / scale, atol=2e-4)
    assert (np.abs(twin).sum(axis=1) == 0).any()  # the outside points read zero


@pytest.mark.gpu
def test_cpu_and_cuda_agree():
    wp.init()
    if not wp.is_cuda_available():
        pytest.skip("no CUDA device visible to Warp")
    cfg = _config(
        camera={"pixels": [128, 128]}, rays={"per_dot": 500},
        volume={"source": "gaussian", "sigma_mm": 4.0, "amplitude_kg_m3": 0.05, "grid": [48, 48, 16]},
    )
    cpu, gpu = render_pair(cfg, device="cpu"), render_pair(cfg, device="cuda:0")
    diff = np.abs(cpu.displacement_px - gpu.displacement_px).max()
    pos = np.abs(cpu.reference_px - gpu.reference_px).max()
    img = np.abs(cpu.gradient - gpu.gradient).max() / cpu.gradient.max()
    print(f"\nCPU vs CUDA: max |displacement difference| {diff:.2e} px, max |reference position difference| "
          f"{pos:.2e} px, max relative image difference {img:.2e}, over {cpu.n_dots} dots")
    np.testing.assert_array_equal(cpu.valid, gpu.valid)
    assert diff < 1e-4


def test_render_is_deterministic(device):
    cfg = _config(volume={"source": "gaussian", "sigma_mm": 3.0, "grid": [24, 24, 8]}, rays={"per_dot": 300})
    a, b = render_pair(cfg, device=device), render_pair(cfg, device=device)
    np.testing.assert_array_equal(a.gradient, b.gradient)
    np.testing.assert_array_equal(a.displacement_px, b.displacement_px)
