"""Speed and accuracy of ``correlation.correlate_pair`` against OpenPIV's ``windef``, on one CPU core.

Both processors get the same synthetic pairs (integrated Gaussian dots of 3 px, 20 dots per 32x32 px,
no noise) and the same passes: 32x32 px then 16x16 px windows, no overlap, symmetric image
deformation with cubic B-spline interpolation, three-point Gaussian peak fit. The RMS error is taken
over every vector of each one's own final grid against the exact field, and the wall time of a whole
call (after a warm-up call) is the best of ``--repeat`` runs. Run::

    python3 -m benchmarks.bench_correlation [--sizes 512 1024] [--repeat 3]

OpenPIV (``pip install openpiv``, the ``bench`` extra) is only imported here.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from correlation import CorrelationSettings, correlate_pair  # noqa: E402
from raytrace.dots import draw_dots  # noqa: E402

DOT_DIAMETER = 3.0
DOTS_PER_PX = 20 / 32**2


def bump_field(shape, amplitude=2.0, offset=(0.6, -0.35)):
    """A BOS-like field: the gradient of a Gaussian bump (width a sixth of the image) plus a uniform shift."""
    h, w = shape
    cx, cy, s = (w - 1) / 2, (h - 1) / 2, min(h, w) / 6

    def field(x, y):
        g = np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        # -d/dx of g, scaled so the largest displacement is ``amplitude`` px
        k = amplitude * np.sqrt(np.e) / s
        return offset[0] + k * (x - cx) * g, offset[1] + k * (y - cy) * g

    return field


def uniform_field(u0=1.3, v0=-0.7):
    return lambda x, y: (np.full_like(x, u0), np.full_like(y, v0))


def synthetic_pair(shape, field, *, seed):
    """Dots at random midpoints m, drawn at m - f(m)/2 and m + f(m)/2: the truth at m is f(m) exactly."""
    rng = np.random.default_rng(seed)
    h, w = shape
    pad = 8
    n = rng.poisson(DOTS_PER_PX * (h + 2 * pad) * (w + 2 * pad))
    m = rng.uniform([-pad, -pad], [w + pad, h + pad], size=(n, 2))
    fu, fv = field(m[:, 0], m[:, 1])
    d = np.stack([fu, fv], axis=1)
    return draw_dots(shape, m - d / 2, DOT_DIAMETER), draw_dots(shape, m + d / 2, DOT_DIAMETER)


def rms_error(x, y, u, v, field):
    tu, tv = field(np.asarray(x, float), np.asarray(y, float))
    return float(np.sqrt(np.nanmean((u - tu) ** 2 + (v - tv) ** 2)))


def run_synthbos(a, b, settings):
    r = correlate_pair(a, b, settings=settings)
    return r.x, r.y, r.u, r.v


def openpiv_settings():
    from openpiv import windef

    s = windef.PIVSettings()
    s.windowsizes = (32, 16)
    s.overlap = (0, 0)
    s.num_iterations = 2
    s.subpixel_method = "gaussian"
    s.deformation_method = "symmetric"
    s.interpolation_order = 3
    s.correlation_method = "circular"
    s.normalized_correlation = False
    s.sig2noise_method = "peak2mean"
    s.sig2noise_validate = True
    s.validation_first_pass = True
    s.median_threshold = 3
    s.replace_vectors = True
    s.smoothn = False
    s.n_cpus = 1
    return s


def run_openpiv(a, b, settings):
    from openpiv import windef

    with contextlib.redirect_stdout(io.StringIO()):
        x, y, u, v, _ = windef.simple_multipass(a, b, settings)
    # back from OpenPIV's "physical" frame (y flipped, v negated) to image coordinates; OpenPIV
    # puts a window's centre at start + N/2 where pixel centres are at integers, the true centre is
    # start + (N - 1)/2
    return x - 0.5, y[::-1, :] - 0.5, u, -v


def best_time(fn, repeat):
    fn()  # warm-up (kernel compilation, FFT plans)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)

    ours_default = CorrelationSettings()
    ours_same = CorrelationSettings(iterations=(1, 1))
    op = openpiv_settings()
    print("synthbos default : ", ours_default.as_dict())
    print("synthbos 1+1 iter: iterations (1, 1), otherwise default")
    print(
        f"OpenPIV windef {__import__('openpiv').__version__}: windowsizes {op.windowsizes}, overlap {op.overlap}, "
        f"num_iterations {op.num_iterations}, subpixel {op.subpixel_method}, deformation {op.deformation_method} "
        f"order {op.interpolation_order}, {op.correlation_method} correlation, sig2noise {op.sig2noise_method} "
        f"(threshold {op.sig2noise_threshold}), median threshold {op.median_threshold}, "
        f"replace {op.filter_method}, smoothn {op.smoothn}, backend {op.backend}"
    )
    print()
    header = (
        f"{'image':>9} {'field':>8} | {'OpenPIV rms':>11} {'time':>8} | {'ours rms':>9} {'time':>8} "
        f"{'rms ratio':>9} {'speed-up':>8} | {'ours 1+1 rms':>12} {'time':>8} {'speed-up':>8}"
    )
    print(header)
    print("-" * len(header))
    for n in args.sizes:
        for name, field in (("uniform", uniform_field()), ("bump", bump_field((n, n)))):
            a, b = synthetic_pair((n, n), field, seed=args.seed + n)
            t_op, res_op = best_time(lambda a=a, b=b: run_openpiv(a, b, op), args.repeat)
            t_us, res_us = best_time(lambda a=a, b=b: run_synthbos(a, b, ours_default), args.repeat)
            t_u1, res_u1 = best_time(lambda a=a, b=b: run_synthbos(a, b, ours_same), args.repeat)
            e_op, e_us, e_u1 = (rms_error(*r, field) for r in (res_op, res_us, res_u1))
            print(
                f"{n:>4}x{n:<4} {name:>8} | {e_op:11.4f} {t_op * 1e3:6.0f}ms | {e_us:9.4f} {t_us * 1e3:6.0f}ms "
                f"{e_us / e_op:9.2f} {t_op / t_us:7.1f}x | {e_u1:12.4f} {t_u1 * 1e3:6.0f}ms {t_op / t_u1:7.1f}x"
            )
    print()
    print("rms in px over all vectors; time = best wall time of a whole call on one core; rms ratio = ours / OpenPIV;")
    print("speed-up = OpenPIV time / ours.")


if __name__ == "__main__":
    main()
