"""The spread of each dot's rays: covariance (gradient and reference image) and third moments."""

import h5py
import numpy as np
import pytest
import warp as wp
from _small import small_config
from numpy.testing import assert_allclose
from scipy.special import j1
from synthbos.raytrace import kernels, read_pair, reference, write_pair
from synthbos.raytrace.pairfile import in_cone_spread_px
from synthbos.raytrace.render import central_moments, moment_scales, plan_render, render_pair

# A sinusoid along x whose wavelength (2 mm) is below the width of a dot's cone of rays at the volume
# (aperture diameter 105 / 11 mm x Z_D / z_stop = 2.4 mm): the flow varies across the cone.
SINUSOID = {"source": "sinusoidal", "direction": [1.0, 0.0], "wavelength_mm": 2.0, "amplitude_kg_m3": 0.02,
            "size_mm": [16.0, 16.0, 10.0], "grid": [257, 3, 3]}


@wp.kernel
def _ray_samples(dots: wp.array(dtype=wp.vec2), dot_radius: float, aperture_radius: float, seed: int,
                 emit: wp.array2d(dtype=wp.vec2), aperture: wp.array2d(dtype=wp.vec2)):
    """The emission and aperture points ``render_rays`` draws for ray ``ray`` of dot ``dot``."""
    dot, ray = wp.tid()
    state = wp.rand_init(seed, ray * dots.shape[0] + dot)
    emit[dot, ray] = dots[dot] + kernels.sample_disk(state, dot_radius)
    aperture[dot, ray] = kernels.sample_disk(state, aperture_radius)


def _straight_ray_displacements(plan):
    """Eq. 4 (depth-weighted, ``reference.straight_ray_integrals``) for every ray the renderer traces,
    each taken straight: (N, rays, 2) px."""
    n, rays = plan.n_dots, plan.rays_per_dot
    dots = wp.array(plan.target_xy.astype(np.float32), dtype=wp.vec2, device="cpu")
    emit = wp.zeros((n, rays), dtype=wp.vec2, device="cpu")
    aperture = wp.zeros((n, rays), dtype=wp.vec2, device="cpu")
    wp.launch(_ray_samples, dim=(n, rays), inputs=[dots, plan.dot_radius, plan.camera.aperture_radius,
                                                   plan.cfg["rays"]["seed"]], outputs=[emit, aperture], device="cpu")
    e = emit.numpy().astype(np.float64).reshape(-1, 2)
    a = aperture.numpy().astype(np.float64).reshape(-1, 2)
    origins = np.concatenate([e, np.zeros((len(e), 1))], axis=1)
    aims = np.concatenate([a, np.full((len(a), 1), plan.camera.z_stop)], axis=1)
    integral, _ = reference.straight_ray_integrals(plan.medium, origins, aims, max(8, plan.steps_per_ray))
    m, zd = plan.camera.magnification, plan.medium.centre[2]
    return (-(m * zd / plan.medium.n0) * integral / plan.camera.pitch).reshape(n, rays, 2)


def _closed_form_variance(plan, pair):
    """var_x of a point dot's rays through the sinusoid in the weak-deflection, thin-volume limit.

    A ray from the dot at X0 to the aperture point A crosses the mid-plane at x = c + r, with c =
    X0 (1 - Z_D / z_stop) and r uniform on a disk of radius R = a Z_D / z_stop (a the aperture's
    radius); its displacement is C cos(k x + phi), C = (M Z_D / n0) K rho_a k L s / pitch (s = sin(k
    dx) / (k dx), the central difference of the grid's gradient). Over the disk, E[cos(k r_x)] =
    L1(k R) with L1(b) = 2 J1(b) / b, so with theta = k c + phi:
    var = C^2 (1/2 + cos(2 theta) L1(2 k R) / 2 - cos(theta)^2 L1(k R)^2).
    """
    cam, med = plan.camera, plan.medium
    k = 2.0 * np.pi / (SINUSOID["wavelength_mm"] * 1e-3)
    dx = med.spacing[0]
    zd, depth = med.centre[2], med.size[2]
    amplitude = (cam.magnification * zd / med.n0) * med.gladstone_dale * SINUSOID["amplitude_kg_m3"] * k * depth
    amplitude *= np.sin(k * dx) / (k * dx) / cam.pitch
    b = k * cam.aperture_radius * zd / cam.z_stop
    theta = k * pair.target_xy_m[:, 0] * (1.0 - zd / cam.z_stop)

    def lam(v):
        return 2.0 * j1(v) / v

    return amplitude**2 * (0.5 + 0.5 * np.cos(2.0 * theta) * lam(2.0 * b) - np.cos(theta) ** 2 * lam(b) ** 2), b


def test_sinusoid_spreads_each_dot_as_derived(device):
    """Through a sinusoid finer than the cone, the recorded covariance is the variance of Eq. 4 over the
    aperture: against the closed form (the mean over dots, and dot by dot) and against Eq. 4 along each
    traced ray, taken straight (dot by dot)."""
    plan = plan_render(small_config(volume=SINUSOID, rays={"per_dot": 400}))
    cone_diameter = 2.0 * plan.camera.aperture_radius * plan.medium.centre[2] / plan.camera.z_stop
    assert SINUSOID["wavelength_mm"] * 1e-3 < cone_diameter
    pair = render_pair(plan, device=device)
    v = pair.valid
    cov, ref = pair.ray_covariance_px2[v], pair.ray_covariance_reference_px2[v]
    assert v.sum() > 40
    assert np.abs(ref).max() < 1e-6  # point dots through a thin lens: one image point
    expected, b = _closed_form_variance(plan, pair)
    print(f"\nphase radius of the cone k R = {b:.2f}; var_x recorded {cov[:, 0].mean():.5f} px^2, closed form "
          f"{expected[v].mean():.5f}; dot by dot within {np.abs(cov[:, 0] / expected[v] - 1).max() * 100:.1f} %")
    assert_allclose(cov[:, 0].mean(), expected[v].mean(), rtol=0.03)
    assert_allclose(cov[:, 0], expected[v], rtol=0.25)  # 400 rays: the sample variance of each dot
    # Along each ray: the same rays, so only the weak-deflection limit and float32 remain.
    per_ray = _straight_ray_displacements(plan)[v]
    direct = np.stack([per_ray[..., 0].var(axis=1), per_ray[..., 1].var(axis=1),
                       np.mean((per_ray[..., 0] - per_ray[..., 0].mean(axis=1, keepdims=True))
                               * (per_ray[..., 1] - per_ray[..., 1].mean(axis=1, keepdims=True)), axis=1)], axis=1)
    assert_allclose(cov[:, 0], direct[:, 0] + ref[:, 0], rtol=0.01)
    assert np.abs(cov[:, 1:]).max() < 1e-4 * cov[:, 0].mean()  # no gradient along y
    assert_allclose(in_cone_spread_px(pair)[v], np.sqrt(cov[:, 0] + cov[:, 1] - ref[:, 0] - ref[:, 1]))
    # The third moment: the same rays' skew
    centred = per_ray[..., 0] - per_ray[..., 0].mean(axis=1, keepdims=True)
    m30 = np.mean(centred**3, axis=1)
    third = pair.ray_third_moment_px3[v]
    assert_allclose(third[:, 0], m30, atol=0.02 * np.abs(m30).max())
    assert np.abs(third[:, 1:]).max() < 1e-3 * np.abs(m30).max()


def test_uniform_medium_adds_nothing_to_the_reference_spread(device):
    """Disk dots through a uniform medium: the gradient image's moments are the reference image's bits,
    and the reference covariance is a uniform disk's, R^2 / 4 per axis."""
    cfg = small_config(volume={"source": "uniform", "density_kg_m3": 1.3, "grid": [8, 8, 4]},
                       target={"dot_model": "disk", "dot_diameter_px": 3.0}, rays={"per_dot": 300})
    pair = render_pair(cfg, device=device)
    v = pair.valid
    # The same rays to the last bit on the CPU; CUDA contracts the traced path's float32 arithmetic into fused
    # multiply-adds, so there to 5e-6 px^2 (5e-7 measured on an H100, 2026-11-26), a spread below 3e-3 px.
    cuda = device != "cpu"
    np.testing.assert_allclose(
        pair.ray_covariance_px2, pair.ray_covariance_reference_px2, rtol=0, atol=5e-6 if cuda else 0.0
    )
    np.testing.assert_allclose(in_cone_spread_px(pair), 0.0, rtol=0, atol=3e-3 if cuda else 0.0)
    ref = pair.ray_covariance_reference_px2[v]
    # The mean over dots of a 300-ray sample variance: within 3 % of 1.5^2 / 4 = 0.5625 px^2.
    assert_allclose(ref[:, :2].mean(axis=0), [1.5**2 / 4] * 2, rtol=0.03)
    assert np.abs(ref[:, 2].mean()) < 0.02
    # A disk is symmetric: the skew is the sample's alone, about sigma^3 / sqrt(N) per dot.
    third = pair.ray_third_moment_px3[v]
    assert np.abs(third.mean(axis=0)).max() < 0.01


def test_linear_gradient_displaces_every_ray_alike(device):
    """A linear field displaces every ray of a dot alike: the covariance stays the reference's while the
    dots move by most of a pixel. (What remains is of second order: 1 / n in Fermat's equation varies
    across the cone by K |grad rho| times its width, here 2e-5 of the displacement; with a ten times
    larger Gladstone-Dale constant, 8 px displacements spread by 1.3e-3 px, as a float64 trace
    confirms.)"""
    cfg = small_config(volume={"source": "linear", "density_kg_m3": 2.0, "gradient_kg_m4": [120.0, -60.0],
                               "size_mm": [16.0, 16.0, 10.0], "grid": [9, 9, 3]}, rays={"per_dot": 300})
    pair = render_pair(cfg, device=device)
    v = pair.valid
    assert np.abs(pair.displacement_px[v, 0]).min() > 0.75
    assert_allclose(pair.ray_covariance_px2[v], pair.ray_covariance_reference_px2[v], atol=1e-8)
    assert np.nanmax(in_cone_spread_px(pair)[v]) < 1e-4
    assert np.abs(pair.ray_third_moment_px3[v]).max() < 1e-8  # the fixed point: units of 2^-28 px^3


def test_central_moments_of_known_offsets():
    """Fixed-point sums of known offsets give their central moments, far from the nominal position too."""
    rng = np.random.default_rng(3)
    n_rays = 1000
    offsets = np.stack([rng.normal(12.0, 0.05, n_rays), rng.gamma(2.0, 0.02, n_rays) - 7.0], axis=1)
    offsets = offsets.astype(np.float32).astype(np.float64)
    s1, (s2, s3) = float(kernels.POSITION_SCALE), moment_scales(n_rays)
    x, y = offsets[:, 0], offsets[:, 1]

    def fixed(values, scale):
        return np.floor(values * scale + 0.5).astype(np.int64).sum()

    sums = np.array([[fixed(x * x, s2), fixed(y * y, s2), fixed(x * y, s2), fixed(x**3, s3), fixed(x * x * y, s3),
                      fixed(x * y * y, s3), fixed(y**3, s3)]])
    cov, third = central_moments([fixed(x, s1)], [fixed(y, s1)], sums, [n_rays], [0], scales=(s2, s3))
    dx, dy = x - x.mean(), y - y.mean()
    assert_allclose(cov[0], [np.mean(dx * dx), np.mean(dy * dy), np.mean(dx * dy)], rtol=1e-7, atol=1e-12)
    expected = [np.mean(dx**3), np.mean(dx * dx * dy), np.mean(dx * dy * dy), np.mean(dy**3)]
    assert_allclose(third[0], expected, rtol=1e-5, atol=1.0 / s3)  # within one unit of the fixed point
    # No ray, or a ray beyond the range: no moments.
    cov, third = central_moments([0, 5], [0, 5], np.zeros((2, 7), np.int64), [0, 10], [0, 1], scales=(s2, s3))
    assert np.isnan(cov).all() and np.isnan(third).all()


@pytest.mark.parametrize("rays", [1, 1000, 10**4, 10**6, 10**8])
def test_moment_sums_cannot_overflow(rays):
    """At the range's edge on both axes, every ray of a dot sums within int64."""
    r = float(kernels.MOMENT_RANGE_PX)
    s2, s3 = moment_scales(rays)
    assert rays * r**2 * s2 <= 2.0**62 and rays * r**3 * s3 <= 2.0**62
    assert s2 >= 2.0**19 and s3 >= 2.0**11


def test_pair_file_stores_the_moments_and_reads_older_files(tmp_path):
    pair = render_pair(small_config(volume={"source": "gaussian", "grid": [16, 16, 8]}, rays={"per_dot": 50}),
                       device="cpu")
    out = write_pair(tmp_path / "p.h5", pair)
    back = read_pair(out)
    for name in ("ray_covariance_px2", "ray_covariance_reference_px2", "ray_third_moment_px3"):
        np.testing.assert_array_equal(getattr(back, name), getattr(pair, name))
    with h5py.File(out, "r+") as f:
        assert f["dots/ray_covariance_px2"].attrs["units"] == "px^2"
        assert f["dots/ray_covariance_reference_px2"].attrs["units"] == "px^2"
        assert f["dots/ray_third_moment_px3"].attrs["units"] == "px^3"
        assert "reference" in f["dots/ray_covariance_reference_px2"].attrs["description"]
        for name in ("ray_covariance_px2", "ray_covariance_reference_px2", "ray_third_moment_px3"):
            del f[f"dots/{name}"]
    old = read_pair(out)
    assert old.ray_covariance_px2 is None and old.ray_third_moment_px3 is None
    assert np.isnan(in_cone_spread_px(old)).all()
