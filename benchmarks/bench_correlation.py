"""Speed and accuracy of ``correlation.correlate_pair`` against OpenPIV's ``windef``, on one CPU core.

Both processors get the same synthetic pairs (integrated Gaussian dots of 3 px, 20 dots per 32x32 px,
no noise) and the same passes: 32x32 px then 16x16 px windows, no overlap, symmetric image
deformation with cubic B-spline interpolation, three-point Gaussian peak fit. The RMS error is taken
over every vector of each one's own final grid against the exact field, and the wall time of a whole
call (after a warm-up call) is the best of ``--repeat`` runs.

Two sets of pairs: a uniform shift and a Gaussian-bump BOS field (``--sizes``), and turbulent
random-phase fields (``--turbulent-sizes``, ``--turbulent-pairs`` per size): a solenoidal field whose
displacement spectrum falls as k^-5/3 between wavelengths of half the image and 32 px, scaled to a
largest displacement of 3 px, evaluated exactly from its Fourier modes. There the vector grid (16 px)
barely resolves the field, which is where the validation has to tell rough vectors from wrong ones.
Run::

    python3 -m synthbos.benchmarks.bench_correlation [--sizes 512 1024] [--turbulent-sizes 256 1024]

OpenPIV (``pip install openpiv``, the ``bench`` extra) is only imported here.

With ``--devices`` the run compares the two paths of ``correlate_pair`` instead (no OpenPIV): the
NumPy path on the CPU (``backend="numpy"``, one core) and the Warp path (``backend="warp"``) on each
given device, on the same pairs and the default settings: per-pair time (best of ``--repeat`` after a
warm-up call; on CUDA the second call records the CUDA graph that later calls replay), the speed-up
over the NumPy path, and the largest difference of the vectors (px) and of the flags between them::

    python3 -m synthbos.benchmarks.bench_correlation --devices cpu cuda:0 --sizes 512 1024 --repeat 10
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402

import numpy as np  # noqa: E402
from synthbos.benchmarks.timing import best_time  # noqa: E402
from synthbos.correlation import CorrelationSettings, correlate_pair, count_vectors  # noqa: E402
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


def random_phase_field(shape, *, seed, max_displacement=3.0, shortest_wavelength=32.0, slope=-5.0 / 3.0):
    """A turbulent-like solenoidal displacement field with random phases, exact at any point.

    The stream function is a sum of the image's periodic Fourier modes with wave numbers from 2 (half the
    image) to ``size / shortest_wavelength`` cycles per image, amplitudes ``k^((slope - 3) / 2)``
    (so the displacement spectrum, summed over rings of wave number, falls as ``k^slope``) and random
    phases; ``u = dpsi/dy``, ``v = -dpsi/dx``, scaled so that the largest displacement on the pixel grid
    is ``max_displacement``.
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    kmax = min(h, w) / shortest_wavelength
    ky, kx = np.meshgrid(np.arange(-int(kmax), int(kmax) + 1), np.arange(0, int(kmax) + 1), indexing="ij")
    k = np.hypot(kx, ky)
    keep = (k >= 2) & (k <= kmax) & ((kx > 0) | (ky > 0))
    kx, ky, k = kx[keep].astype(float), ky[keep].astype(float), k[keep]
    amp = k ** ((slope - 3.0) / 2.0)
    phase = rng.uniform(0, 2 * np.pi, len(k))
    fx, fy = 2 * np.pi * kx / w, 2 * np.pi * ky / h

    def raw(x, y):
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        px, py = x.ravel(), y.ravel()
        u, v = np.empty(px.size), np.empty(px.size)
        for i in range(0, px.size, 2048):  # bounded memory: 2048 points x the modes at a time
            s = -amp * np.sin(px[i : i + 2048, None] * fx + py[i : i + 2048, None] * fy + phase)
            u[i : i + 2048], v[i : i + 2048] = s @ fy, -(s @ fx)
        return u.reshape(x.shape), v.reshape(x.shape)

    # the same sums on the whole pixel grid, by one inverse FFT each, for the scale
    spec_u = np.zeros((h, w), complex)
    spec_v = np.zeros((h, w), complex)
    iy, ix = ky.astype(int) % h, kx.astype(int) % w
    np.add.at(spec_u, (iy, ix), 1j * amp * fy * np.exp(1j * phase) * h * w)
    np.add.at(spec_v, (iy, ix), -1j * amp * fx * np.exp(1j * phase) * h * w)
    u0, v0 = np.fft.ifft2(spec_u).real, np.fft.ifft2(spec_v).real
    scale = max_displacement / float(np.hypot(u0, v0).max())

    def field(x, y):
        u, v = raw(x, y)
        return scale * u, scale * v

    return field


def rms_error(x, y, u, v, field):
    tu, tv = field(np.asarray(x, float), np.asarray(y, float))
    return float(np.sqrt(np.nanmean((u - tu) ** 2 + (v - tv) ** 2)))


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




def _compare(a, b, field, op, ours, repeat, first_cell):
    """One pair: OpenPIV then each synthbos variant; one printed row each."""
    t_op, res_op = best_time(lambda: run_openpiv(a, b, op), repeat, warmup=True)
    e_op = rms_error(*res_op, field)
    rows = [("OpenPIV windef", e_op, t_op, None)]
    for label, settings in ours.items():
        t, r = best_time(lambda s=settings: correlate_pair(a, b, settings=s), repeat, warmup=True)
        e = rms_error(r.x, r.y, r.u, r.v, field)
        c = count_vectors(r.flags)
        rows.append((label, e, t, c))
    for k, (label, e, t, c) in enumerate(rows):
        counts = "" if c is None else f"{c['measured']}/{c['replaced']}/{c['failed']}"
        print(f"{first_cell if k == 0 else '':<24} {label:<32} {e:9.4f} {t * 1e3:9.0f} {e / e_op:9.2f} "
              f"{t_op / t:7.1f}x  {counts}")
    return rows


def compare_backends(sizes, devices, *, repeat, seed, settings=None):
    """Time the NumPy path (CPU) and the Warp path on each device on the same pairs; print one row each.

    Returns
    -------
    list of dict
        One per pair and path: ``pair``, ``path``, ``time_s``, ``speedup`` (NumPy time / time),
        ``max_diff_px`` (largest |u| or |v| difference to the NumPy path), ``flags_differ`` (count).
    """
    from dataclasses import replace

    base = settings or CorrelationSettings()
    print("settings:", base.as_dict())
    header = (
        f"{'pair':<18} {'path':<22} {'time [ms]':>10} {'speed-up':>9} {'max |d| [px]':>13} "
        f"{'flags differ':>12}  measured/replaced/failed"
    )
    print(header)
    print("-" * len(header))
    rows = []
    for n in sizes:
        for name, field in (("uniform", uniform_field()), ("bump", bump_field((n, n))),
                            ("turbulent", random_phase_field((n, n), seed=seed + n))):
            a, b = synthetic_pair((n, n), field, seed=seed + n)
            pair = f"{n}x{n} {name}"
            paths = [("numpy, cpu", replace(base, backend="numpy", device="cpu"))]
            paths += [(f"warp, {dev}", replace(base, backend="warp", device=dev)) for dev in devices]
            ref = None
            for label, s in paths:
                t, r = best_time(lambda a=a, b=b, s=s: correlate_pair(a, b, settings=s), repeat, warmup=True)
                if ref is None:
                    ref, t_ref = r, t
                diff = float(max(np.nanmax(np.abs(r.u - ref.u)), np.nanmax(np.abs(r.v - ref.v))))
                flags_differ = int(np.sum(r.flags != ref.flags))
                c = count_vectors(r.flags)
                print(f"{pair if label.startswith('numpy') else '':<18} {label:<22} {t * 1e3:10.2f} "
                      f"{t_ref / t:8.1f}x {diff:13.2e} {flags_differ:12d}  "
                      f"{c['measured']}/{c['replaced']}/{c['failed']}")
                rows.append({"pair": pair, "path": label, "time_s": t, "speedup": t_ref / t,
                             "max_diff_px": diff, "flags_differ": flags_differ})
    print()
    print("time: best of --repeat whole calls (images in, vectors out) after a warm-up call; speed-up =")
    print("NumPy-path time / time; max |d|: largest difference of u or v to the NumPy path's vectors.")
    return rows


def profile_kernels(size, device, *, seed, settings=None):
    """Per-kernel CUDA times of one Warp-path call (kernels launched one by one, no CUDA graph)."""
    from dataclasses import replace

    import warp as wp
    from synthbos.correlation import device_pass

    s = replace(settings or CorrelationSettings(), backend="warp", device=device)
    a, b = synthetic_pair((size, size), bump_field((size, size)), seed=seed)
    correlate_pair(a, b, settings=s)  # compiled and loaded
    graph, device_pass.USE_CUDA_GRAPH = device_pass.USE_CUDA_GRAPH, False
    try:
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        correlate_pair(a, b, settings=s)
        results = wp.timing_end()
    finally:
        device_pass.USE_CUDA_GRAPH = graph
    print(f"\nper-kernel CUDA times, one {size}x{size} pair on {device}, kernels launched one by one:")
    wp.timing_print(results)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[512, 1024])
    parser.add_argument("--turbulent-sizes", type=int, nargs="*", default=[256, 1024])
    parser.add_argument("--turbulent-pairs", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--devices", nargs="*", default=None,
                        help="compare the NumPy path with the Warp path on these devices (no OpenPIV)")
    parser.add_argument("--profile", action="store_true",
                        help="with --devices: per-kernel CUDA times of one pair of the first size per CUDA device")
    args = parser.parse_args(argv)
    if args.devices:
        compare_backends(args.sizes, args.devices, repeat=args.repeat, seed=args.seed)
        if args.profile:
            for dev in args.devices:
                if dev.startswith("cuda"):
                    profile_kernels(args.sizes[0], dev, seed=args.seed)
        return

    ours = {
        "synthbos (default)": CorrelationSettings(),
        "synthbos iter (2,1)": CorrelationSettings(iterations=(2, 1)),
        "synthbos iter (1,1)": CorrelationSettings(iterations=(1, 1)),
        "synthbos (1,1) keys": CorrelationSettings(iterations=(1, 1), interpolator="keys"),
    }
    turbulent = {
        "synthbos (default)": CorrelationSettings(),
        "synthbos, replace all failures": CorrelationSettings(confirm_tolerance=0.0),
        "synthbos (1,1) keys": CorrelationSettings(iterations=(1, 1), interpolator="keys"),
    }
    op = openpiv_settings()
    print("synthbos default settings:", CorrelationSettings().as_dict())
    print(
        "synthbos iter (a,b): the default with iterations (a, b); (1,1) does OpenPIV's work: one deformation"
    )
    print("synthbos, replace all failures: confirm_tolerance = 0, every vector failing the median test is replaced")
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
        f"{'pair':<24} {'processor':<32} {'rms [px]':>9} {'time [ms]':>9} "
        f"{'rms ratio':>9} {'speed-up':>8}  measured/replaced/failed"
    )
    print(header)
    print("-" * len(header))
    for n in args.sizes:
        for name, field in (("uniform", uniform_field()), ("bump", bump_field((n, n)))):
            a, b = synthetic_pair((n, n), field, seed=args.seed + n)
            _compare(a, b, field, op, ours, args.repeat, f"{n}x{n} {name}")
    summary = []
    for n in args.turbulent_sizes:
        totals = {}
        for k in range(args.turbulent_pairs):
            field = random_phase_field((n, n), seed=args.seed + 100 * k + n)
            a, b = synthetic_pair((n, n), field, seed=args.seed + 100 * k + n + 1)
            for label, e, t, _ in _compare(a, b, field, op, turbulent, args.repeat, f"{n}x{n} turbulent #{k + 1}"):
                totals.setdefault(label, []).append((e * e, t))
        for label, vals in totals.items():
            e2, t = np.array(vals).T
            summary.append((f"{n}x{n} turbulent, {len(vals)} pairs", label, float(np.sqrt(e2.mean())), t.mean()))
    if summary:
        print()
        print("turbulent pairs: rms over all vectors of all pairs, mean time")
        print(f"{'pairs':<28} {'processor':<32} {'rms [px]':>9} {'time [ms]':>9}")
        for pairs, label, e, t in summary:
            print(f"{pairs:<28} {label:<32} {e:9.4f} {t * 1e3:9.0f}")
    print()
    print("rms: over all vectors of each one's grid against the exact field; time: best of --repeat")
    print("whole calls on one core after a warm-up call; rms ratio = rms / OpenPIV rms;")
    print("speed-up = OpenPIV time / time; measured/replaced/failed: synthbos's vector counts.")


if __name__ == "__main__":
    main()
