"""The buoyancy-driven mixing solver and the embedded snapshot file it generated."""

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.raytrace.buoyancy import (
    DEFAULT_PARAMS,
    flatness,
    gradient_magnitude,
    initial_density,
    main,
    phase_randomised,
    run_buoyancy,
)
from synthbos.raytrace.loaders import DEFAULT_SNAPSHOTS, read_snapshots

SHORT = {"n": 64, "times": (0.25, 0.5), "seed": 7}


def test_short_run_is_deterministic():
    a = run_buoyancy(**SHORT)
    b = run_buoyancy(**SHORT)
    assert_array_equal(a.density, b.density)
    assert a.steps == b.steps > 5
    c = run_buoyancy(**{**SHORT, "seed": 8})
    assert np.abs(c.density - a.density).max() > 1e-3
    # the flow has moved: the density field changed between the snapshots
    assert np.abs(a.density[1] - a.density[0]).max() > 1e-3


def test_mean_density_is_conserved():
    run = run_buoyancy(**SHORT)
    mean0 = initial_density(64, seed=7).mean()
    rel = np.abs(run.density.mean(axis=(1, 2)) - mean0) / mean0
    print(f"relative drift of the mean density: {rel}")
    assert rel.max() < 1e-12, f"mean density drift {rel.max():.2e}"


def test_initial_condition_two_segregated_fluids():
    A = 0.05
    rho = initial_density(128, seed=1, atwood=A)
    s = (rho - 1.0) / A
    pure = np.abs(s) > 0.9
    print(f"fraction of pure fluid {pure.mean():.3f}, heavy fraction {(s > 0).mean():.3f}")
    assert pure.mean() > 0.75  # mostly unmixed fluid, thin interfaces
    assert abs((s > 0).mean() - 0.5) < 0.01  # equal volumes of heavy and light fluid
    assert np.abs(s).max() < 1.01  # the interface smoothing does not overshoot the pure densities


def test_diffusion_of_a_stable_stratification_is_exact():
    # rho = 1 + a cos(3 y): no horizontal gradient, no baroclinic torque, so the fluid stays at rest and
    # the integrating factor must give exactly exp(-kappa k^2 t) decay.
    n, kappa, t = 32, 0.01, 2.0
    y = 2 * np.pi * np.arange(n) / n
    rho0 = np.broadcast_to((1.0 + 0.05 * np.cos(3 * y))[:, None], (n, n))
    run = run_buoyancy(n=n, times=(t,), rho_init=rho0, diffusivity=kappa, viscosity=kappa)
    expected = 1.0 + 0.05 * np.exp(-kappa * 9 * t) * np.cos(3 * y)
    assert_allclose(run.density[0], np.broadcast_to(expected[:, None], (n, n)), atol=1e-13)


def test_buoyancy_sign_heavy_fluid_sinks():
    # rho = 1 + A sin(x): heavy column at x = pi/2, light at 3 pi/2. Gravity along -y makes the heavy
    # column sink (v < 0) and the light one rise. A weak profile 0.01 cos(y), uniform
    # in x (no torque), shows the motion: at y = 3 pi/2 it increases upwards, so a sinking column brings
    # down larger values (rho rises) and a rising column smaller ones.
    n = 32
    x = 2 * np.pi * np.arange(n) / n
    rho0 = np.broadcast_to((1.0 + 0.05 * np.sin(x))[None, :], (n, n)).copy()
    rho0 += 0.01 * np.cos(x)[:, None]  # same grid along y
    run = run_buoyancy(n=n, times=(0.2,), rho_init=rho0, viscosity=0.0, diffusivity=0.0)
    drho = run.density[0] - rho0
    i_heavy, i_light, j = n // 4, 3 * n // 4, 3 * n // 4
    print(f"d rho at y = 3 pi/2: heavy column {drho[j, i_heavy]:.2e}, light column {drho[j, i_light]:.2e}")
    assert drho[j, i_heavy] > 1e-5 and drho[j, i_light] < -1e-5


def test_gradient_helpers():
    n = 64
    x = 2 * np.pi * np.arange(n) / n
    f = np.sin(x)[None, :] * np.ones((n, 1))
    g = gradient_magnitude(f, spacing=2 * np.pi / n)
    assert_allclose(g[0], np.abs(np.cos(x)) * np.sin(2 * np.pi / n) / (2 * np.pi / n), atol=1e-12)
    rng = np.random.default_rng(0)
    ray = np.hypot(rng.standard_normal(200_000), rng.standard_normal(200_000))
    assert_allclose(flatness(ray), 2.0, rtol=0.02)  # Rayleigh magnitude
    r = phase_randomised(f + 1.0, seed=3)
    assert_allclose(np.abs(np.fft.fft2(r - 1)), np.abs(np.fft.fft2(f)), atol=1e-9)
    assert_allclose(r.mean(), 1.0, atol=1e-14)


def test_embedded_file_schema_and_size():
    dens, times, attrs = read_snapshots()
    size_mb = DEFAULT_SNAPSHOTS.stat().st_size / 1e6
    print(f"embedded file: {size_mb:.2f} MB, shape {dens.shape}, times {times}")
    assert dens.shape[0] == 5 and dens.shape[1] == dens.shape[2] >= 256
    assert size_mb < 2.5
    assert np.all(np.diff(times) > 0)
    assert_allclose(dens.mean(axis=(1, 2)), 1.0, atol=2e-6)
    for key in ("seed", "atwood", "gravity", "viscosity", "diffusivity", "n", "times", "format"):
        assert key in attrs, key
    assert_allclose(attrs["times"], times)
    assert 0.03 <= attrs["atwood"] <= 0.07
    import h5py

    with h5py.File(DEFAULT_SNAPSHOTS) as h5:
        assert h5["density"].dtype == np.float32


def test_embedded_snapshots_gradient_is_intermittent():
    dens, times, attrs = read_snapshots()
    h = float(attrs["box"]) / dens.shape[-1]
    rows = []
    for k, d in enumerate(dens):
        F = flatness(gradient_magnitude(d, spacing=h))
        ref = np.mean(
            [flatness(gradient_magnitude(phase_randomised(d, seed=s), spacing=h)) for s in range(3)]
        )
        rows.append((k, times[k], F, ref, F / ref))
    table = "\n".join(
        f"snapshot {k} t={t:6.2f}: flatness {F:6.2f}, Gaussian ref {r:5.2f}, ratio {q:5.2f}"
        for k, t, F, r, q in rows
    )
    print("\n" + table)
    for k, _, F, ref, q in rows:
        assert ref == pytest.approx(2.0, abs=0.3), f"reference off for snapshot {k}\n{table}"
        assert q >= 1.5, f"snapshot {k}: |grad rho| flatness {F:.2f} < 1.5 x Gaussian {ref:.2f}\n{table}"


def test_main_writes_a_snapshot_file(tmp_path):
    out = tmp_path / "snaps.h5"
    assert (
        main(["-o", str(out), "--n", "32", "--seed", "5", "--times", "0.1", "0.2", "0.3", "0.4", "0.5"]) == 0
    )
    dens, times, attrs = read_snapshots(out)
    assert dens.shape == (5, 32, 32)
    assert_allclose(times, [0.1, 0.2, 0.3, 0.4, 0.5])
    assert attrs["seed"] == 5 and attrs["n"] == 32
    assert_allclose(dens.mean(axis=(1, 2)), 1.0, atol=1e-6)
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.slow
def test_regeneration_reproduces_embedded_file(slow_only):
    """The full default run (about a minute) gives back the embedded snapshots (run with -m slow)."""
    dens, times, attrs = read_snapshots()
    run = run_buoyancy(workers=2)
    assert attrs["seed"] == DEFAULT_PARAMS["seed"]
    assert_allclose(run.times, times)
    fresh = run.density / run.density.mean(axis=(1, 2), keepdims=True)
    err = np.abs(fresh - dens).max(axis=(1, 2))
    print(f"max |fresh - embedded| per snapshot: {err}")
    assert err[0] < 1e-6  # float32 storage; later snapshots may drift on another CPU's round-off
    mixed = 1.0 - ((dens - 1.0) ** 2).mean(axis=(1, 2)) / attrs["atwood"] ** 2
    assert_allclose(run.mixedness, mixed, atol=0.02)
