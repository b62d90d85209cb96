"""Integration solvers on exact gradient fields: each case recovered to 1e-3 of the density range."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from synthbos.integration import (
    border_region,
    displacement_to_density_gradient,
    edge_increments,
    fill_missing,
    grid_for_points,
    lsq_integrate,
    pixel_to_midplane,
    poisson_dct,
    scattered_to_grid,
    set_reference,
    weighted_lsq,
)

from synthbos import SynthbosError
from synthbos.memo import forget_all

NY, NX = 80, 112
DX, DY = 0.25e-3, 0.3e-3  # metres: unequal spacings on purpose


def _grid():
    x = (np.arange(NX) - (NX - 1) / 2) * DX
    y = (np.arange(NY) - (NY - 1) / 2) * DY
    return np.meshgrid(x, y)


def _blob(X, Y):
    s, a, cx, cy = 3e-3, 0.05, 1.1e-3, -0.7e-3
    e = np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * s * s))
    return 1.2 + a * e, -a * (X - cx) / s**2 * e, -a * (Y - cy) / s**2 * e


def _linear(X, Y):
    gx, gy = 40.0, -25.0
    return 1.225 + gx * X + gy * Y, np.full_like(X, gx), np.full_like(X, gy)


def _sinusoid(X, Y):
    k = 2 * np.pi / 9e-3
    d = np.array([0.8, 0.6])
    s = d[0] * X + d[1] * Y
    c = 0.01 * k * np.cos(k * s + 0.3)
    return 1.1 + 0.01 * np.sin(k * s + 0.3), c * d[0], c * d[1]


CASES = {"blob": _blob, "linear": _linear, "sinusoid": _sinusoid}


def _solve(solver, gx, gy, **kw):
    if solver == "dct":
        return poisson_dct(gx, gy, dx=DX, dy=DY)
    if solver == "lsq":
        return lsq_integrate(gx, gy, dx=DX, dy=DY, **kw)
    rng = np.random.default_rng(0)  # arbitrary uncertainties: exact data stay exact whatever the weights
    return weighted_lsq(gx, gy, rng.uniform(0.5, 3, gx.shape), rng.uniform(0.5, 3, gx.shape), dx=DX, dy=DY, **kw)


@pytest.mark.parametrize("solver", ["dct", "lsq", "wlsq"])
@pytest.mark.parametrize("case", list(CASES))
def test_exact_fields_recovered(case, solver):
    X, Y = _grid()
    rho, gx, gy = CASES[case](X, Y)
    border = np.zeros(rho.shape, bool)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    # The reference: the true density over the border (a region of known density).
    phi = set_reference(_solve(solver, gx, gy), value=np.where(border, rho, np.nan), region=border)
    rel = np.sqrt(np.mean((phi - rho) ** 2)) / np.ptp(rho)
    print(f"{case:9s} {solver:5s} rms / range = {rel:.2e}")
    assert rel < 1e-3


@pytest.mark.parametrize("solver", ["lsq", "wlsq"])
def test_linear_gradient_with_known_reference_region(solver):
    """Dirichlet: the density is known on a 5 x 5 patch; the solver takes its level from it."""
    X, Y = _grid()
    rho, gx, gy = _linear(X, Y)
    known = np.full(rho.shape, np.nan)
    known[10:15, 20:25] = rho[10:15, 20:25]
    phi = _solve(solver, gx, gy, known=known)
    assert_allclose(phi, rho, atol=1e-3 * np.ptp(rho))
    assert np.sqrt(np.mean((phi - rho) ** 2)) / np.ptp(rho) < 1e-9


def test_dct_and_lsq_are_the_same_least_squares():
    X, _ = _grid()
    rng = np.random.default_rng(3)
    gx, gy = rng.normal(size=X.shape), rng.normal(size=X.shape)  # not a gradient at all
    a = poisson_dct(gx, gy, dx=DX, dy=DY)
    b = lsq_integrate(gx, gy, dx=DX, dy=DY)
    assert_allclose(a - a.mean(), b - b.mean(), atol=1e-10 * np.abs(a).max())


def test_masked_domain_and_islands():
    X, Y = _grid()
    rho, gx, gy = _blob(X, Y)
    mask = np.hypot(X, Y) < 8e-3
    mask[:, 50:53] = False  # a wall splits the disk into two islands
    phi = lsq_integrate(gx, gy, dx=DX, dy=DY, mask=mask)
    assert np.isnan(phi[~mask]).all() and np.isfinite(phi[mask]).all()
    cols = np.arange(NX)[None, :]
    for part in (mask & (cols < 50), mask & (cols >= 53)):
        err = phi[part] - rho[part]
        assert np.sqrt(np.mean((err - err.mean()) ** 2)) / np.ptp(rho) < 1e-3
        assert abs(phi[part].mean()) < 1e-12  # each island without a known node has zero mean
    # With a known node in the left island only, the right one cannot be levelled: NaN on request.
    known = np.full(rho.shape, np.nan)
    j, i = np.argwhere(mask & (cols < 50))[0]
    known[j, i] = rho[j, i]
    phi = lsq_integrate(gx, gy, dx=DX, dy=DY, mask=mask, known=known, unreferenced="nan")
    left = mask & (cols < 50)
    assert np.isnan(phi[mask & (cols >= 53)]).all()
    assert np.sqrt(np.mean((phi - rho)[left] ** 2)) / np.ptp(rho) < 1e-3


def test_weights_follow_the_uncertainty():
    """A block of bad vectors with large uncertainty barely disturbs the weighted solution."""
    X, Y = _grid()
    rho, gx, gy = _blob(X, Y)
    bad = np.zeros(rho.shape, bool)
    bad[30:40, 40:60] = True
    rng = np.random.default_rng(1)
    gxb = gx + np.where(bad, rng.normal(0, 5 * np.abs(gx).max(), gx.shape), 0)
    gyb = gy + np.where(bad, rng.normal(0, 5 * np.abs(gy).max(), gy.shape), 0)
    sig = np.where(bad, 100.0, 1.0)

    def err(phi):  # where the data are good
        phi = set_reference(phi, value=rho, region=~bad)
        return np.sqrt(np.mean((phi - rho)[~bad] ** 2)) / np.ptp(rho)

    plain, weighted = err(lsq_integrate(gxb, gyb, dx=DX, dy=DY)), err(weighted_lsq(gxb, gyb, sig, sig, dx=DX, dy=DY))
    print(f"bad block: plain lsq {plain:.3e}, weighted {weighted:.3e}")
    assert weighted < 0.05 * plain


def test_edge_increments_fourth_order():
    x = np.linspace(0, 1, 11)
    g = (3 * x**2)[None, :]  # d/dx of x^3: cubic through 4 nodes is exact
    d, ok, _ = edge_increments(g, x[1] - x[0])
    assert ok.all()
    assert_allclose(d[0, 1:-1], np.diff(x**3)[1:-1], rtol=1e-12)


def test_scattered_dots_to_grid():
    rng = np.random.default_rng(2)
    x, y = rng.uniform(0, 100, 4000), rng.uniform(0, 80, 4000)
    gxn, gyn = grid_for_points(x, y)
    assert abs((gxn[1] - gxn[0]) - np.sqrt(100 * 80 / 4000)) < 0.1
    out = scattered_to_grid(x, y, np.stack([2 * x - y + 3, x], axis=1), gxn, gyn)
    GX, GY = np.meshgrid(gxn, gyn)
    ok = np.isfinite(out[..., 0])
    assert ok.mean() > 0.9
    assert_allclose(out[ok, 0], (2 * GX - GY + 3)[ok], atol=1e-9)  # linear fields are exact
    assert np.isnan(scattered_to_grid(x, y, x, [-5.0], [-5.0])).all()  # outside the hull


def test_physics_inverts_eq4_and_maps_to_midplane():
    m, zd, L, K, n0, pitch = 0.1172, 0.25, 0.01, 2.25e-4, 1.000275, 1e-5
    g = np.array([30.0, -12.0])  # kg/m^4
    dX_px = -(m * zd / n0) * K * L * g / pitch  # Eq. 4 forward
    gx, gy = displacement_to_density_gradient(dX_px[0], dX_px[1], magnification=m, z_d_m=zd, depth_m=L,
                                              gladstone_dale_m3_per_kg=K, n0=n0, pixel_pitch_m=pitch)
    assert_allclose([gx, gy], g, rtol=1e-12)
    x, y = pixel_to_midplane([255.5, 355.5], [255.5, 155.5], principal_point_px=(255.5, 255.5), magnification=m,
                             pixel_pitch_m=pitch, z_d_m=zd, z_stop_m=1.0, volume_centre_m=(1e-3, 0.0))
    assert_allclose(x, [-1e-3, 100 * pitch / m * 0.75 - 1e-3], rtol=1e-12)
    assert_allclose(y, [0.0, -100 * pitch / m * 0.75], atol=1e-15)


def test_bad_input_is_refused():
    X, Y = _grid()
    _, gx, gy = _blob(X, Y)
    nan = np.full_like(gx, np.nan)
    with pytest.raises(SynthbosError, match="nothing to integrate"):
        lsq_integrate(nan, nan, dx=DX, dy=DY)
    with pytest.raises(SynthbosError, match="mask leaves no node"):
        lsq_integrate(gx, gy, dx=DX, dy=DY, mask=np.zeros(gx.shape, bool))
    with pytest.raises(SynthbosError, match="full rectangle"):
        poisson_dct(np.where(X > 0, gx, np.nan), gy, dx=DX, dy=DY)
    with pytest.raises(SynthbosError, match="one shape"):
        poisson_dct(gx, gy[:-1], dx=DX, dy=DY)
    with pytest.raises(SynthbosError, match="reference region"):
        set_reference(nan, value=1.0)


def test_fill_missing_and_border_region():
    X, Y = _grid()
    f = 3.0 * X - 2.0 * Y + 1.0
    measured = np.hypot(X, Y) < 6e-3
    measured[40, 56] = False  # a hole inside
    out = fill_missing(np.where(measured, f, np.nan), measured)
    assert np.isfinite(out).all()
    assert_allclose(out[40, 56], f[40, 56], rtol=1e-12)  # linear inside the hull is exact
    far = ~measured & (np.hypot(X, Y) > 7e-3)
    assert np.all((out[far] >= f[measured].min()) & (out[far] <= f[measured].max()))  # nearest beyond it
    ring = border_region(measured)
    assert ring[measured].sum() < measured.sum() and not ring[~measured].any()
    assert ring[40, 55] and ring[40, 57]  # the hole's neighbours belong to the border
    full = border_region(np.ones((4, 5), bool))
    assert full.sum() == 4 * 5 - 2 * 3


def test_remembered_factors_solve_bit_for_bit_like_spsolve(monkeypatch):
    # lsq_integrate remembers the LU factors of its matrix: a repeated domain must give exactly what
    # scipy's spsolve gives, weighted or not, with known nodes or not.
    from scipy.sparse import linalg as splinalg
    from synthbos.integration import solvers

    rng = np.random.default_rng(3)
    X, Y = _grid()
    mask = (X / X.max()) ** 2 + (Y / Y.max()) ** 2 < 0.9
    mask[30:34, 40:60] = False  # a hole
    known = np.where(border_region(mask), 1.2, np.nan)
    runs = []
    for k in range(3):  # the same domain, other gradients: the factors are reused
        gx = np.where(mask, np.cos(X * 900) + 0.01 * rng.standard_normal(X.shape), np.nan)
        gy = np.where(mask, np.sin(Y * 700) + 0.01 * rng.standard_normal(X.shape), np.nan)
        sx = 0.1 + rng.random(X.shape)
        runs.append(dict(gx=gx, gy=gy, dx=DX, dy=DY, mask=mask, known=known if k != 1 else None))
        runs.append(dict(gx=gx, gy=gy, dx=DX, dy=DY, sigma_x=sx, sigma_y=sx[::-1]))
    got = [lsq_integrate(**kw) for kw in runs + runs]
    monkeypatch.setattr(solvers, "_spsolve", lambda a, r: splinalg.spsolve(a, r))
    want = [lsq_integrate(**kw) for kw in runs]
    for g, w in zip(got, want + want, strict=True):
        assert np.isfinite(w).sum() > 1000
        assert g.tobytes() == w.tobytes()
    # the systems (matrix, the domain's parts) are remembered by edges, weights, mask and known nodes:
    # each run above, solved after others, equals the same run solved with nothing remembered
    for kw, g in zip(runs, got, strict=False):
        forget_all()
        assert lsq_integrate(**kw).tobytes() == g.tobytes()
