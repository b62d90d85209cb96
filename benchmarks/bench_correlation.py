"""Speed and accuracy of ``correlation.correlate_pair`` against OpenPIV's ``windef``, on one CPU core.

Both processors get the same synthetic pairs (integrated Gaussian dots of 3 px, 20 dots per 32x32 px,
no noise) and the same passes: 32x32 px then 16x16 px windows, no overlap, symmetric image
deformation with cubic B-spline interpolation, three-point Gaussian peak fit. The RMS error is taken
over every vector of each one's own final grid against the exact field, and the wall time of a whole
call (after a warm-up call) is the best of ``--repeat`` runs. Run::

    python3 -m synthbos.benchmarks.bench_correlation [--sizes 512 1024] [--repeat 3]

OpenPIV (``pip install openpiv``, the ``bench`` extra) is only imported here.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402

import numpy as np  # noqa: E402
from synthbos.benchmarks.timing import best_time  # noqa: E402
from synthbos.correlation import CorrelationSettings, correlate_pair  # noqa: E402
from synthbos.raytrace.dots import draw_dots  # noqa: E402

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




def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)

    ours = {
        "synthbos (default)": CorrelationSettings(),
        "synthbos iter (2,1)": CorrelationSettings(iterations=(2, 1)),
        "synthbos iter (1,1)": CorrelationSettings(iterations=(1, 1)),
        "synthbos (1,1) keys": CorrelationSettings(iterations=(1, 1), interpolator="keys"),
    }
    op = openpiv_settings()
    print("synthbos default settings:", CorrelationSettings().as_dict())
    print(
        "synthbos iter (a,b): the default with iterations (a, b); (1,1) does OpenPIV's work: one deformation"
    )
    print(
        f"OpenPIV windef {__import__('openpiv').__version__}: windowsizes {op.windowsizes}, "
        f"overlap {op.overlap}, num_iterations {op.num_iterations}, subpixel {op.subpixel_method}, "
        f"deformation {op.deformation_method} order {op.interpolation_order}, {op.correlation_method} "
        f"correlation, sig2noise {op.sig2noise_method} (threshold {op.sig2noise_threshold}), "
        f"median threshold {op.median_threshold}, replace {op.filter_method}, smoothn {op.smoothn}, "
        f"backend {op.backend}"
    )
    print()
    header = (
        f"{'image':>9}  {'field':<8} {'processor':<20} {'rms [px]':>9} {'time [ms]':>9} "
        f"{'rms ratio':>9} {'speed-up':>8}"
    )
    print(header)
    print("-" * len(header))
    for n in args.sizes:
        for name, field in (("uniform", uniform_field()), ("bump", bump_field((n, n)))):
            a, b = synthetic_pair((n, n), field, seed=args.seed + n)
            t_op, res_op = best_time(lambda a=a, b=b: run_openpiv(a, b, op), args.repeat, warmup=True)
            e_op = rms_error(*res_op, field)
            row = f"{n:>4}x{n:<4}  {name:<8} {'OpenPIV windef':<20} {e_op:9.4f} {t_op * 1e3:9.0f}"
            print(f"{row} {1:9.2f} {1:7.1f}x")
            for label, settings in ours.items():
                t, res = best_time(lambda a=a, b=b, s=settings: run_synthbos(a, b, s), args.repeat, warmup=True)
                e = rms_error(*res, field)
                print(
                    f"{'':>9}  {'':<8} {label:<20} {e:9.4f} {t * 1e3:9.0f} {e / e_op:9.2f} {t_op / t:7.1f}x"
                )
    print()
    print("rms: over all vectors of each one's grid against the exact field; time: best of --repeat")
    print("whole calls on one core after a warm-up call; rms ratio = rms / OpenPIV rms;")
    print("speed-up = OpenPIV time / time.")


if __name__ == "__main__":
    main()
