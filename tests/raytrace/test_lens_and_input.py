"""Thick lens, sensor noise, dot patterns, configuration checks and bad input."""

import h5py
import numpy as np
import pytest
import warp as wp
from _small import small_config as _config
from numpy.testing import assert_allclose
from synthbos.benchmarks.cli import main
from synthbos.raytrace import add_noise, kernels, load_config, read_pair, render_pair
from synthbos.raytrace.camera import camera_from_config
from synthbos.raytrace.checks import check_density as _check_density
from synthbos.raytrace.pattern import grid_pattern, random_pattern
from synthbos.raytrace.render import plan_render

from synthbos import SynthbosError


def test_thick_lens_focus_and_magnification_close_to_thin_lens():
    thin = camera_from_config(load_config(_config()))
    thick = camera_from_config(load_config(_config(camera={"lens": "thick", "lens_thickness_mm": 1.0})))
    assert_allclose(thick.magnification, thin.magnification, rtol=0.01)
    # A thin-lens limit: thickness -> 0 gives the thin lens exactly (paraxial).
    from synthbos.raytrace.camera import _thick_lens_focus, _thick_lens_radius

    f, n, d = 0.105, 1.5168, 1e-8
    s_image, m = _thick_lens_focus(f, n, d, _thick_lens_radius(f, n, d), 1.0)
    assert_allclose(abs(m), thin.magnification, rtol=1e-6)
    assert_allclose(s_image, thin.z_sensor - thin.z_stop, rtol=1e-6)


def test_thick_lens_renders_disk_dots():
    """The thick lens's magnification is a NumPy float: the dot radius it gives must still be a plain float
    for the kernels (a disk-dot render through a thick lens used to fail in wp.launch)."""
    config = _config(camera={"lens": "thick"}, target={"dot_model": "disk"})
    assert type(plan_render(config).dot_radius) is float
    pair = render_pair(config, device="cpu")
    assert pair.valid.mean() > 0.5 and np.isfinite(pair.gradient).all()


def test_thick_lens_displacement_matches_thin_lens(device):
    vol = {"source": "linear", "gradient_kg_m4": [0.0, 40.0], "grid": [8, 8, 4]}
    thin = render_pair(_config(volume=vol), device=device)
    thick = render_pair(_config(volume=vol, camera={"lens": "thick"}), device=device)
    ok = thin.valid & thick.valid
    assert ok.sum() >= 0.9 * thin.n_dots
    assert np.isfinite(thick.gradient).all() and np.isfinite(thick.reference_px[ok]).all()
    # The displacement is set in object space: the lens only maps it, with its own magnification.
    m_ratio = thick.attrs["magnification"] / thin.attrs["magnification"]
    assert_allclose(thick.displacement_px[ok, 1], thin.displacement_px[ok, 1] * m_ratio, rtol=0.01)
    # Near the axis the thick lens images dots where the paraxial model puts them.
    plan = plan_render(_config(volume=vol, camera={"lens": "thick"}))
    centre = np.array(plan.camera.principal_point)
    near = ok & (np.linalg.norm(thick.reference_px - centre, axis=1) < 20)
    geometric = plan.camera.target_to_pixel(thick.target_xy_m[near])
    # The spherically aberrated spot has a std of ~0.54 px, so a 200-ray mean scatters by ~0.04 px.
    err = np.abs(thick.reference_px[near] - geometric)
    assert err.max() < 0.15 and err.mean() < 0.05


def test_refraction_reports_total_internal_reflection(device):
    @wp.kernel
    def run(t: wp.array(dtype=wp.vec3), eta: float, out: wp.array(dtype=wp.vec3), flag: wp.array(dtype=int)):
        i = wp.tid()
        r, f = kernels.refract(t[i], wp.vec3(0.0, 0.0, -1.0), eta)
        out[i] = r
        flag[i] = f

    angles = np.radians([0.0, 20.0, 40.0, 60.0, 80.0])
    t = np.stack([np.sin(angles), np.zeros(5), np.cos(angles)], axis=1).astype(np.float32)
    out = wp.zeros(5, dtype=wp.vec3, device=device)
    flag = wp.zeros(5, dtype=int, device=device)
    wp.launch(run, dim=5, inputs=[wp.array(t, dtype=wp.vec3, device=device), 1.5], outputs=[out, flag], device=device)
    # From glass (n = 1.5) into air: the critical angle is asin(1/1.5) = 41.8 degrees.
    np.testing.assert_array_equal(flag.numpy(), [0, 0, 0, 1, 1])
    r = out.numpy()
    assert np.isfinite(r).all()
    # Snell: 1.5 sin(theta_i) = sin(theta_t) for the transmitted rays.
    assert_allclose(np.hypot(r[:3, 0], r[:3, 1]), 1.5 * np.sin(angles[:3]), atol=1e-6)


def test_noise_is_seeded_and_scaled():
    img = np.zeros((200, 200), np.float32)
    img[100, 100] = 2.0
    a = add_noise(img, percent=5.0, seed=1)
    b = add_noise(img, percent=5.0, seed=1)
    c = add_noise(img, percent=5.0, seed=2)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert_allclose((a - img).std(), 0.05 * 2.0, rtol=0.03)
    q = add_noise(img, percent=0.0, seed=0, bit_depth=8, full_scale=1.0)
    assert q.max() == 255.0 and q.min() == 0.0  # saturated at the full scale


def test_patterns_density_and_spacing():
    g = grid_pattern(128, 128, 16.0)
    assert len(g) == 16 * 16 and np.allclose(np.diff(np.unique(g[:, 0])), 8.0)
    r = random_pattern(256, 256, 20.0, min_spacing=3.0, seed=4)
    assert len(r) == 20 * 64
    from scipy.spatial import cKDTree

    d, _ = cKDTree(r).query(r, k=2)
    assert d[:, 1].min() >= 3.0
    np.testing.assert_array_equal(r, random_pattern(256, 256, 20.0, min_spacing=3.0, seed=4))


@pytest.mark.parametrize(
    ("tables", "message"),
    [
        ({"camera": {"f_number": 0}}, "camera.f_number must be >= 0.5 and <= 1000, got 0"),
        ({"camera": {"f_number": -2.8}}, "camera.f_number must be >= 0.5 and <= 1000, got -2.8"),
        ({"rays": {"per_dot": 0}}, "rays.per_dot must be >= 1 and <= 100000000, got 0"),
        ({"camera": {"fnumber": 8}}, "unknown configuration key camera.fnumber"),
        ({"optics": {"x": 1}}, "unknown configuration table [optics]"),
        ({"volume": {"source": "gaussian", "gradient_kg_m4": [1, 1]}}, "unknown configuration key volume.grad"),
        ({"volume": {"distance_from_target_mm": 1200}}, "behind the lens"),
        ({"volume": {"distance_from_target_mm": 3}}, "through the target plane"),
        ({"volume": {"offset_mm": [200.0, 0.0]}}, "misses the field of view"),
        ({"volume": {"source": "linear", "gradient_kg_m4": [200.0, 0.0]}}, "density must be > 0 everywhere"),
        ({"target": {"pattern": "hexagonal"}}, "target.pattern must be one of"),
    ],
)
def test_bad_configuration_is_rejected(tables, message):
    with pytest.raises(SynthbosError, match=None) as err:
        plan_render(_config(**tables))
    assert message in str(err.value)


def test_bad_density_arrays_are_rejected():
    rho = np.ones((4, 4, 4))
    rho[1, 2, 3] = np.nan
    with pytest.raises(SynthbosError, match=r"NaN/inf value\(s\), first at index \(1, 2, 3\)"):
        _check_density(rho, where="volume", ndim=(3,))
    with pytest.raises(SynthbosError, match="must be > 0"):
        _check_density(-np.ones((4, 4, 4)), where="volume", ndim=(3,))
    with pytest.raises(SynthbosError, match="3-D"):
        _check_density(np.ones((4, 4)), where="volume", ndim=(3,))
    with pytest.raises(SynthbosError, match="no fluid"):
        _check_density(np.full((4, 4, 4), 2e5), where="volume", ndim=(3,))


def test_cli_render_writes_a_complete_pair(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text('[camera]\npixels = [64, 48]\n[rays]\nper_dot = 50\n[target]\ndots_per_32px = 6\n'
                   '[volume]\nsource = "linear"\ngradient_kg_m4 = [30.0, -20.0]\ngrid = [8, 8, 4]\n')
    out = tmp_path / "pair.h5"
    assert main(["render", str(cfg), "-o", str(out), "-q", "--device", "cpu"]) == 0
    pair = read_pair(out)
    assert pair.reference.shape == (48, 64) and pair.reference.dtype == np.float32
    assert_allclose(pair.displacement_px, pair.gradient_px - pair.reference_px)
    with h5py.File(out) as f:
        assert f["dots/theory_px"].shape == (pair.n_dots, 2)
        assert "gradient_kg_m4 = [30.0, -20.0]" in f.attrs["config"]
        for key in ("magnification", "version", "device", "render_seconds"):
            assert key in f.attrs
    # x displacement has the sign of -d rho/dx, y of -d rho/dy (dots shift down the gradient)
    d = pair.displacement_px[pair.valid].mean(axis=0)
    assert d[0] < 0 < d[1]
    assert {p.name for p in tmp_path.iterdir()} == {"c.toml", "pair.h5"}


@pytest.mark.parametrize(
    "toml",
    [
        "[camera]\nf_number = 0\n",
        "[rays]\nper_dot = 0\n",
        "[volume]\nsize_mm = [32, 32]\n",
        "[camera]\nbogus = 1\n",
        "[volume]\noffset_mm = [500.0, 0.0]\n",
        "this is not toml",
    ],
)
def test_cli_bad_input_exits_2_without_output(tmp_path, capsys, toml):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(toml)
    out = tmp_path / "pair.h5"
    assert main(["render", str(cfg), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("synthbos: error:")
    assert {p.name for p in tmp_path.iterdir()} == {"bad.toml"}


def test_cli_missing_config_file(tmp_path, capsys):
    assert main(["render", str(tmp_path / "nope.toml"), "-o", str(tmp_path / "p.h5")]) == 2
    assert "does not exist" in capsys.readouterr().err
