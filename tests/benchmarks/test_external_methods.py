"""The methods from other libraries: ``optical-flow`` (scikit-image) and ``openpiv`` (OpenPIV).

Skipped where the ``methods`` extra is not installed (``pip install -e ".[methods]"``; the ``test``
extra installs it).
"""

from dataclasses import replace

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.ndimage import gaussian_filter, shift
from synthbos.benchmarks.items import score_pair
from synthbos.benchmarks.registry import get_method
from synthbos.benchmarks.spec import QUICK
from synthbos.raytrace import render_pair

from synthbos import SynthbosError

P90_TARGET = 0.2  # px, at every noise level of the quick campaign


def _dots(shape=(128, 128), *, seed=0, density=20 / 32**2):
    """A random pattern of Gaussian dots (sigma 0.8 px, about 3 px across) on a dark background."""
    rng = np.random.default_rng(seed)
    img = np.zeros(shape)
    n = int(density * shape[0] * shape[1])
    img[rng.integers(0, shape[0], n), rng.integers(0, shape[1], n)] = 1.0
    return gaussian_filter(img, 0.8) * 8.0


@pytest.mark.parametrize("algorithm", ["tvl1", "ilk"])
def test_optical_flow_measures_a_uniform_shift(algorithm):
    pytest.importorskip("skimage")
    ref = _dots()
    grad = shift(ref, (0.25, -0.4), order=3, mode="wrap")  # v = +0.25 px (rows), u = -0.4 px (columns)
    m = get_method("optical-flow")
    res = m.run(ref, grad, settings=m.settings({"algorithm": algorithm}))
    assert res.grid_shape == ref.shape and res.valid.all()
    inner = np.zeros(ref.shape, bool)
    inner[16:-16, 16:-16] = True
    assert_allclose(np.median(res.uv[inner.ravel()], axis=0), [-0.4, 0.25], atol=0.02)


def test_optical_flow_settings_are_checked():
    m = get_method("optical-flow")
    for bad in ({"algorithm": "farneback"}, {"attachment": -1.0}, {"radius": 0}, {"prefilter": "yes"}):
        with pytest.raises(SynthbosError, match="optical-flow settings"):
            m.settings(bad)


def test_optical_flow_beats_the_target_on_a_quick_pair_at_every_noise_level():
    """One pair of the quick campaign (``test_optical_flow_quick_campaign`` runs all of them)."""
    pytest.importorskip("skimage")
    pair = render_pair(QUICK.pair_config(2, 0), device="cpu")
    for noise in QUICK.noise_percent:
        seeds = (QUICK.noise_seed(2, 0, noise, "reference"), QUICK.noise_seed(2, 0, noise, "gradient"))
        sc = score_pair(pair, "optical-flow", noise_percent=noise, seeds=seeds, device="cpu")
        p90 = np.percentile(sc["error"][np.isfinite(sc["error"])], 90)
        assert p90 < P90_TARGET, (noise, p90)
        assert sc["measured"] >= 0.99 * sc["expected"]


@pytest.mark.slow
def test_optical_flow_quick_campaign(tmp_path, slow_only):
    """The whole quick campaign (minutes on two cores; run with -m slow)."""
    pytest.importorskip("skimage")
    from synthbos.benchmarks.campaign import run_campaign

    rows = run_campaign(replace(QUICK, methods=("optical-flow",)), tmp_path / "c", device="cpu", figures=False,
                        progress=False)
    p90 = {r["noise_percent"]: r["p90"] for r in rows if r["split"] == "all" and r["quantity"] == "displacement"}
    assert set(p90) == set(QUICK.noise_percent) and max(p90.values()) < P90_TARGET, p90


def test_openpiv_measures_a_uniform_shift_on_our_grid():
    pytest.importorskip("openpiv")
    ref = _dots(seed=1)
    grad = shift(ref, (0.3, 0.6), order=3, mode="wrap")
    m = get_method("openpiv")
    res = m.run(ref, grad, settings=m.settings())
    # 32 then 16 px windows without overlap: centres at 8, 24, ... as OpenPIV places them
    assert res.grid_shape == (8, 8)
    assert_allclose(res.table["x"][0], 8 + 16 * np.arange(8))
    assert_allclose(res.table["y"][:, 0], 8 + 16 * np.arange(8))
    assert res.valid.mean() > 0.9
    assert_allclose(np.median(res.uv[res.valid], axis=0), [0.6, 0.3], atol=0.02)
    with pytest.raises(SynthbosError, match="openpiv settings"):
        m.settings({"window_sizes": (32, 4)})


def test_openpiv_window_centres_follow_a_linear_field():
    """u = g (x - 64): the measured u at each window centre is g times the centre's offset, so the
    centres are where OpenPIV measured (half a pixel off would show as g / 2 = 0.02 px: the middles
    of the windows, 7.5, 23.5, ..., are)."""
    pytest.importorskip("openpiv")
    from scipy.ndimage import map_coordinates

    g = 0.04
    ref = _dots((128, 128), seed=2, density=40 / 32**2)
    rows, cols = np.mgrid[0:128, 0:128].astype(float)
    # the gradient image shows at x + u(x) what the reference shows at x: sample the reference at x - u
    grad = map_coordinates(ref, [rows, cols - g * (cols - 64) / (1 + g)], order=3, mode="nearest")
    m = get_method("openpiv")
    res = m.run(ref, grad, settings=m.settings())
    inner = res.valid & (np.abs(res.xy[:, 0] - 64) < 48)
    residual = res.uv[inner, 0] - g * (res.xy[inner, 0] - 64)
    assert abs(np.median(residual)) < 0.01, np.median(residual)
