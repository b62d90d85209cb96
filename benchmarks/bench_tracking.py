"""Speed and accuracy of dot tracking with prior information, next to trackpy's ``locate``.

Run ``python3 -m synthbos.benchmarks.bench_tracking`` (trackpy and pandas come with the ``bench`` extra). It draws a
1024x1024 pair of 3 px dots at 20 dots per 32x32 px (random positions with a minimum centre distance of
one diameter, as a manufactured pattern has), displaced by a smooth field, with Gaussian noise; runs the
full method (prior identification with its iterations, centroid difference and correlation correction)
on ONE CPU core; and runs trackpy's ``locate`` on the same reference image, matching its features to the
truth to measure its sub-pixel position error. Everything in the table comes from this one run.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402
from synthbos.benchmarks.timing import best_time  # noqa: E402
from synthbos.raytrace.dots import draw_dots  # noqa: E402
from synthbos.tracking import TrackingSettings, is_valid, track_pair  # noqa: E402

from synthbos.device import init_warp  # noqa: E402


def dot_pattern(rng, shape, *, per_32x32=20.0, min_distance=3.0, margin=2.0):
    """Random dot centres with a minimum distance (later points of close pairs dropped)."""
    h, w = shape
    n = round(per_32x32 * h * w / 1024.0)
    xy = rng.uniform([margin, margin], [w - 1 - margin, h - 1 - margin], size=(int(n * 1.6) + 16, 2))
    pairs = cKDTree(xy).query_pairs(min_distance, output_type="ndarray")
    drop = np.zeros(len(xy), dtype=bool)
    drop[pairs.max(axis=1)] = True
    xy = xy[~drop]
    if len(xy) < n:
        raise RuntimeError(f"could only place {len(xy)} of {n} dots")
    return xy[:n]


def smooth_displacement(xy, shape, amplitude):
    """A smooth vortex-like field of the given peak amplitude (px), one period across the image."""
    h, w = shape
    x, y = xy[:, 0], xy[:, 1]
    u = amplitude * np.sin(2 * np.pi * y / h) * np.cos(2 * np.pi * x / w)
    v = amplitude * np.cos(2 * np.pi * x / w) * np.sin(2 * np.pi * y / h)
    return np.stack([u, v], axis=1)


def position_error(found_xy, true_xy, radius=1.0):
    """RMS distance of each true dot's nearest found feature (within radius) and the fraction found."""
    found_xy = found_xy[np.isfinite(found_xy).all(axis=1)]
    dist, _ = cKDTree(found_xy).query(true_xy, distance_upper_bound=radius)
    ok = np.isfinite(dist)
    return float(np.sqrt(np.mean(dist[ok] ** 2))), float(ok.mean())




def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--density", type=float, default=20.0, help="dots per 32x32 px")
    p.add_argument("--diameter", type=float, default=3.0)
    p.add_argument("--noise", type=float, default=0.02, help="noise sigma as a fraction of the dot peak")
    p.add_argument("--amplitude", type=float, default=1.5, help="peak displacement, px")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--backend", choices=("warp", "numpy"), default="warp")
    p.add_argument("--trackpy-diameter", type=int, default=5, help="odd feature size for trackpy.locate")
    p.add_argument("--trackpy-separation", type=float, default=3.0, help="trackpy.locate minimum separation")
    args = p.parse_args(argv)

    init_warp()
    rng = np.random.default_rng(args.seed)
    shape = (args.size, args.size)
    xy = dot_pattern(rng, shape, per_32x32=args.density, min_distance=args.diameter)
    disp = smooth_displacement(xy, shape, args.amplitude)
    ref = draw_dots(shape, xy, args.diameter) + args.noise * rng.standard_normal(shape)
    grad = draw_dots(shape, xy + disp, args.diameter) + args.noise * rng.standard_normal(shape)
    n = len(xy)

    settings = TrackingSettings(diameter=args.diameter, backend=args.backend)
    track_pair(ref, grad, prior_xy=xy, settings=settings, device="cpu")  # compile / warm up
    t_track, res = best_time(
        lambda: track_pair(ref, grad, prior_xy=xy, settings=settings, device="cpu"), args.repeat
    )
    ok = is_valid(res["status"])
    ex = np.hypot(res["x"] - xy[:, 0], res["y"] - xy[:, 1])[ok]
    eu = np.r_[res["u"] - disp[:, 0], res["v"] - disp[:, 1]][np.r_[ok, ok]]
    ec = np.r_[res["u_cc"] - disp[:, 0], res["v_cc"] - disp[:, 1]][np.r_[ok, ok]]
    crlb = 0.8 * args.noise  # per position component, for a dot of peak 1

    rows = [
        (
            "synthbos tracking (prior, iterations, u and u_cc)",
            n / t_track,
            ok.mean(),
            float(np.sqrt(np.mean(ex**2))),
            float(np.sqrt(np.mean(eu**2))),
            float(np.sqrt(np.mean(ec**2))),
        ),
    ]
    try:
        import trackpy as tp

        tp.quiet()
        feats_fn = lambda: tp.locate(  # noqa: E731
            ref, args.trackpy_diameter, minmass=0, separation=args.trackpy_separation, preprocess=True
        )
        t_tp, feats = best_time(feats_fn, args.repeat)
        fxy = np.stack([feats["x"].to_numpy(), feats["y"].to_numpy()], axis=1)
        err_tp, found_tp = position_error(fxy, xy)
        rows.append(("trackpy.locate (reference image only)", n / t_tp, found_tp, err_tp, np.nan, np.nan))
    except ImportError:
        print("trackpy not installed (pip install trackpy pandas): its row is left out")

    print(
        f"{args.size}x{args.size} pair, {n} dots of {args.diameter:g} px, noise {args.noise:g} of the peak, "
        f"displacement up to {args.amplitude:g} px, one CPU core, best of {args.repeat}"
    )
    print(
        f"position CRLB ~ 0.8 sigma_n / I0 = {crlb:.4f} px per component ({crlb * np.sqrt(2):.4f} px as a "
        f"2-D distance); displacement CRLB {crlb * np.sqrt(2):.4f} px per component"
    )
    head = f"{'method':52s} {'dots/s':>10s} {'yield':>7s} {'pos rms':>8s} {'u rms':>8s} {'u_cc rms':>8s}"
    print(head)
    print("-" * len(head))
    for name, rate, y, e, u, c in rows:
        print(f"{name:52s} {rate:10.0f} {y:7.4f} {e:8.4f} {u:8.4f} {c:8.4f}")
    if len(rows) == 2:
        print(
            f"speed ratio synthbos / trackpy: {rows[0][1] / rows[1][1]:.2f}; position error ratio "
            f"synthbos / trackpy: {rows[0][3] / rows[1][3]:.3f}; target 1e5 dots/s: "
            f"{'met' if rows[0][1] >= 1e5 else 'NOT met'}"
        )
    print("pos rms: 2-D distance to the true reference position; u rms, u_cc rms: per component.")


if __name__ == "__main__":
    main()
