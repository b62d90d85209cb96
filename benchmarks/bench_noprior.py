"""Tracking without a prior on dots and on patterns that are not dots: honesty, yield and speed next to OpenPIV.

Run ``python3 -m synthbos.benchmarks.bench_noprior`` (OpenPIV comes with the ``bench`` extra). Three
pairs are drawn at ``--size`` px, each displaced by the same smooth field (a periodic array of vortices,
peak ``--amplitude`` px per component) with white noise of 1 % of the pattern's peak:

- integrated Gaussian dots of 3 px, 20 per 32x32 px;
- a laser-speckle-like pattern: the squared modulus of Gaussian-filtered complex white noise, grains of
  ``--grain`` px, the gradient image sampled along the inverse of the field;
- random axis-aligned squares of 2-6 px, 8 per 32x32 px, and of 4-10 px, 4 per 32x32 px (exact pixel
  area coverage, overlapping freely), each moved by the field at its centre.

``tracking-cc`` (``track_pair`` without a prior, default settings) runs on each with the registration
check on and off (``registration_tolerance`` 0.25 px and ``inf``). The table gives the dots identified,
the number counted valid (MATCHED), and among those the share more than 0.5 px from the drawn field at
the dot's reference position and the RMS error of ``u_cc``. The timing rows compare ``track_pair`` with
OpenPIV's window deformation (the ``openpiv`` method with its default settings: 32 then 16 px windows,
two iterations each) on the same pair in this one process on ONE CPU core: best of ``--repeat`` calls
after a warm-up call, wall and CPU time.
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # one core for every library, as OpenPIV's own runs are timed
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        os.environ[_var] = "1"

import argparse

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from synthbos.benchmarks.timing import best_times
from synthbos.raytrace.dots import draw_dots
from synthbos.tracking import TrackingSettings, is_valid, track_pair

from synthbos.device import init_warp

__all__ = ["dots_pair", "field", "score", "speckle_pair", "squares_pair"]


def field(xy, shape, amplitude):
    """Displacement (px) at points ``xy`` (x = column): a one-period array of vortices (divergence-free) of
    peak ``amplitude`` per component."""
    h, w = shape
    x, y = 2 * np.pi * np.asarray(xy, dtype=np.float64).T / np.array([[w], [h]])
    return amplitude * np.stack([np.sin(y) * np.cos(x), -np.cos(y) * np.sin(x)], axis=1)


def _pixel_grid(shape):
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


def _inverse(points, shape, amplitude, steps=40):
    """Reference positions that the field carries onto ``points`` (fixed-point iteration; the field's
    gradient is far below 1 px/px, so it contracts)."""
    x = points.copy()
    for _ in range(steps):
        x = points - field(x, shape, amplitude)
    return x


def speckle_pair(shape, *, seed, amplitude=1.5, grain=3.0, noise=0.01):
    """A laser-speckle-like pattern and the same pattern moved by :func:`field`: ``|G * (a + i b)|^2`` for
    white noises ``a, b`` and a Gaussian filter ``G`` of ``grain / 2`` px, peak about 1."""
    rng = np.random.default_rng(seed)
    pad = int(np.ceil(amplitude)) + 8
    parts = [ndimage.gaussian_filter(rng.standard_normal((shape[0] + 2 * pad, shape[1] + 2 * pad)), grain / 2.0)
             for _ in range(2)]  # fmt: skip
    coef = [ndimage.spline_filter(p, order=3) for p in parts]

    def sample(points):
        rc = [points[:, 1] + pad, points[:, 0] + pad]
        a, b = (ndimage.map_coordinates(c, rc, order=3, prefilter=False) for c in coef)
        return (a * a + b * b).reshape(shape)

    grid = _pixel_grid(shape)
    ref, grad = sample(grid), sample(_inverse(grid, shape, amplitude))
    scale = np.percentile(ref, 99.5)
    return ref / scale + noise * rng.standard_normal(shape), grad / scale + noise * rng.standard_normal(shape)


def _draw_squares(shape, centres, sides):
    """Axis-aligned squares, each pixel covered by the area fraction, clipped at 1."""
    h, w = shape
    image = np.zeros(shape)
    span = int(np.ceil(sides.max())) + 2
    offsets = np.arange(-(span // 2) - 1, span // 2 + 2)
    for (cx, cy), s in zip(centres, sides, strict=True):
        cols = np.rint(cx).astype(int) + offsets
        rows = np.rint(cy).astype(int) + offsets
        ox = np.clip(np.minimum(cols + 0.5, cx + s / 2) - np.maximum(cols - 0.5, cx - s / 2), 0, None)
        oy = np.clip(np.minimum(rows + 0.5, cy + s / 2) - np.maximum(rows - 0.5, cy - s / 2), 0, None)
        keep_c, keep_r = (cols >= 0) & (cols < w), (rows >= 0) & (rows < h)
        image[np.ix_(rows[keep_r], cols[keep_c])] += np.outer(oy[keep_r], ox[keep_c])
    return np.minimum(image, 1.0)


def squares_pair(shape, *, seed, amplitude=1.5, sides=(2.0, 6.0), per_32x32=8.0, noise=0.01):
    """Random squares (side uniform in ``sides`` px, ``per_32x32`` per 32x32 px, overlapping freely) and
    the same squares each moved by :func:`field` at its centre."""
    rng = np.random.default_rng(seed)
    h, w = shape
    n = round(per_32x32 * h * w / 1024.0)
    centres = rng.uniform([-4.0, -4.0], [w + 4.0, h + 4.0], (n, 2))
    side = rng.uniform(*sides, n)
    ref = _draw_squares(shape, centres, side)
    grad = _draw_squares(shape, centres + field(centres, shape, amplitude), side)
    return ref + noise * rng.standard_normal(shape), grad + noise * rng.standard_normal(shape)


def dots_pair(shape, *, seed, amplitude=1.5, per_32x32=20.0, diameter=3.0, noise=0.01):
    """Integrated Gaussian dots at random positions at least one diameter apart, and moved by :func:`field`."""
    rng = np.random.default_rng(seed)
    h, w = shape
    n = round(per_32x32 * h * w / 1024.0)
    xy = rng.uniform([3.0, 3.0], [w - 4.0, h - 4.0], (2 * n, 2))
    close = cKDTree(xy).query_pairs(diameter, output_type="ndarray")
    drop = np.zeros(len(xy), dtype=bool)
    drop[close.max(axis=1)] = True
    xy = xy[~drop][:n]
    ref = draw_dots(shape, xy, diameter) + noise * rng.standard_normal(shape)
    grad = draw_dots(shape, xy + field(xy, shape, amplitude), diameter) + noise * rng.standard_normal(shape)
    return ref, grad


def score(table, shape, amplitude):
    """``(dots, valid, share of valid more than 0.5 px off, RMS error of u_cc over valid)`` against the
    drawn field at each dot's reference position."""
    ok = is_valid(table["status"])
    truth = field(np.stack([table["x"][ok], table["y"][ok]], axis=1), shape, amplitude)
    err = np.hypot(table["u_cc"][ok] - truth[:, 0], table["v_cc"][ok] - truth[:, 1])
    off = float((err > 0.5).mean()) if ok.any() else float("nan")
    rms = float(np.sqrt(np.mean(err**2))) if ok.any() else float("nan")
    return len(table), int(ok.sum()), off, rms


def _openpiv_rms(res, shape, amplitude):
    ok = res.valid
    truth = field(res.xy[ok], shape, amplitude)
    return float(np.sqrt(np.mean(np.sum((res.uv[ok] - truth) ** 2, axis=1)))), float(ok.mean())


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--amplitude", type=float, default=1.5, help="peak displacement, px")
    p.add_argument("--grain", type=float, default=3.0, help="speckle grain, px")
    p.add_argument("--repeat", type=int, default=3, help="timed calls per method; the best is reported")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    init_warp()
    shape = (args.size, args.size)
    amp = args.amplitude
    pairs = {
        "dots (3 px, 20 per 32x32 px)": dots_pair(shape, seed=args.seed, amplitude=amp),
        f"speckle ({args.grain:g} px grains)": speckle_pair(shape, seed=args.seed, amplitude=amp, grain=args.grain),
        "squares (2-6 px, 8 per 32x32 px)": squares_pair(shape, seed=args.seed, amplitude=amp),
        "squares (4-10 px, 4 per 32x32 px)": squares_pair(shape, seed=args.seed, amplitude=amp, sides=(4.0, 10.0),
                                                          per_32x32=4.0),
    }
    print(f"tracking-cc without a prior, {args.size}x{args.size} px, peak displacement {amp:g} px, 1 % noise")
    print(f"{'pattern':34s} {'check':>6s} {'dots':>7s} {'valid':>7s} {'yield':>6s} {'>0.5 px':>8s} {'RMS px':>7s}")
    for name, (ref, grad) in pairs.items():
        for label, tol in (("off", np.inf), ("on", 0.25)):
            tab = track_pair(ref, grad, settings=TrackingSettings(registration_tolerance=tol), device="cpu")
            n, valid, off, rms = score(tab, shape, amp)
            print(f"{name:34s} {label:>6s} {n:7d} {valid:7d} {valid / max(n, 1):6.3f} {off:8.2%} {rms:7.4f}")
    _timing(pairs, shape, amp, args.repeat)


def _timing(pairs, shape, amp, repeat):
    from synthbos.benchmarks.openpiv_method import run_openpiv

    print("\ntime on one CPU core (best of", repeat, "after a warm-up call), same pair, same process")
    print(f"{'pattern':34s} {'tracking-cc s':>14s} {'openpiv s':>10s} {'ratio':>6s} {'cpu ratio':>9s}  accuracy")
    for name, (ref, grad) in pairs.items():
        track_pair(ref, grad, device="cpu")
        wt, ct, tab = best_times(lambda ref=ref, grad=grad: track_pair(ref, grad, device="cpu"), repeat)
        run_openpiv(ref, grad)
        wo, co, res = best_times(lambda ref=ref, grad=grad: run_openpiv(ref, grad), repeat)
        _, valid, off, rms = score(tab, shape, amp)
        rms_o, valid_o = _openpiv_rms(res, shape, amp)
        print(f"{name:34s} {wt:14.2f} {wo:10.2f} {wt / wo:6.2f} {ct / co:9.2f}  tracking-cc RMS {rms:.4f} px "
              f"({valid} valid, {off:.2%} > 0.5 px), openpiv RMS {rms_o:.4f} px ({valid_o:.1%} valid)")


if __name__ == "__main__":
    main()
