"""Sensor noise: remembering a seed's draws changes no bit of the noisy images."""

import numpy as np
import pytest
from synthbos.raytrace import add_noise

from synthbos import SynthbosError


def reference_add_noise(image, *, percent, seed, peak=None, bit_depth=0, full_scale=None):
    """The implementation before the draws were remembered (kept here only)."""
    img = np.asarray(image, dtype=np.float64)
    ref = float(img.max()) if peak is None else float(peak)
    rng = np.random.default_rng(seed)
    noisy = img + rng.normal(0.0, percent / 100.0 * ref, size=img.shape) if percent > 0 else img.copy()
    if bit_depth:
        top = 2.0 ** int(bit_depth) - 1.0
        scale = top / (ref if full_scale is None else float(full_scale))
        noisy = np.clip(np.round(noisy * scale), 0.0, top)
    return noisy.astype(np.float32)


def rendered_like(shape=(96, 128), seed=0):
    """Dots on a background: float32 intensities in [0, 1], exact zeros between dots."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    img = np.zeros(shape)
    for x, y in rng.uniform(0, shape[1], (60, 2)) * [1, shape[0] / shape[1]]:
        img += np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 1.5)
    img[img < 1e-3] = 0.0
    return np.minimum(img, 1.0).astype(np.float32)


@pytest.mark.parametrize("seed", [0, 7, np.int64(2019), 2**31 - 1, np.random.SeedSequence(5), [1, 2]])
def test_noise_is_bit_identical_to_the_direct_draws(seed):
    img = rendered_like()
    for percent in (0.0, 0.5, 1.0, 2.0, 5.0, 13.7):
        for kw in ({}, {"peak": 1.0}, {"peak": 0.73}, {"bit_depth": 12}, {"bit_depth": 8, "full_scale": 0.8}):
            want = reference_add_noise(img, percent=percent, seed=seed, **kw)
            for _ in range(2):  # the second call reuses the remembered draws of an integer seed
                got = add_noise(img, percent=percent, seed=seed, **kw)
                assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    f64 = img.astype(np.float64) * 1.1
    assert add_noise(f64, percent=3.0, seed=3).tobytes() == reference_add_noise(f64, percent=3.0, seed=3).tobytes()


def test_remembered_draws_stay_untouched():
    img = rendered_like()
    first = add_noise(img, percent=4.0, seed=11)
    first += 1.0  # the caller owns its image
    again = add_noise(img, percent=4.0, seed=11)
    assert again.tobytes() == reference_add_noise(img, percent=4.0, seed=11).tobytes()
    other = rendered_like((64, 64))  # another shape, same seed
    want = reference_add_noise(other, percent=4.0, seed=11)
    assert add_noise(other, percent=4.0, seed=11).tobytes() == want.tobytes()


def test_negative_reference_intensity_is_refused():
    with pytest.raises(SynthbosError):
        add_noise(rendered_like(), percent=1.0, seed=0, peak=-1.0)
