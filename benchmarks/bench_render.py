"""Renderer speed: rays per second and ray-steps per second of the full render (trace + lens + deposit).

The paper configuration: 512 x 512 px, 10 um pixels, f = 105 mm, f/11, target at 1 m (M ~ 0.117),
Z_D = 250 mm, a 32 x 32 x 10 mm volume on a 256 x 256 grid, 20 dots per 32 x 32 px, 3 px dots,
10,000 rays per dot. Every device given is timed in the same process after a warm-up render that
compiles and loads the kernels, once per variant of the renderer's speed settings (``[rays]`` keys
``field``, ``dot_order``, ``rays_per_group``, ``block_dim``, ``max_registers``, or any other ``rays`` key such as
``step_mm``). Each variant's displacements are compared with those of the first variant on the same
device (the exact float32 default unless ``--variants`` says otherwise): launch settings and the exact
fields must give the same bits; the approximate fields report their max and RMS difference in px.

    python -m synthbos.benchmarks.bench_render --devices cuda:0 cpu --rays 10000 --cpu-rays 50

Profiling: ``--profile`` traces each variant's two images once (no warm-up, no repeats), one launch
each when ``--rays`` x dots fits in a chunk (2^24 rays), so Nsight Compute sees two ``render_rays``
launches per variant, in the order of ``--variants``:

    ncu --clock-control none -k regex:render_rays --set full -o $OUT/render \\
        python -m synthbos.benchmarks.bench_render --devices cuda:0 --rays 2000 --profile \\
        --variants default field=float32_vec,dot_order=morton,rays_per_group=8
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np
import warp as wp
from synthbos.raytrace import render
from synthbos.raytrace.medium import EXACT_FIELDS, to_warp

from synthbos import SynthbosError
from synthbos.device import init_warp

PREDECESSOR_RAYS_PER_S = 2e6
CHUNK = 1 << 24

# The variants timed by default: the exact float32 default first (the reference of the differences),
# then each lever alone and in combination. A variant is "key=value,key=value" over [rays] keys.
DEFAULT_VARIANTS = [
    "default",
    "dot_order=morton",
    "dot_order=morton,rays_per_group=8",
    "dot_order=morton,rays_per_group=32",
    *(
        f"field={field}" + ("" if group is None else f",dot_order=morton,rays_per_group={group}")
        for field in ("float32_vec", "texture_nearest", "float16", "float16_nodes", "texture", "texture16")
        for group in (None, 1, 8, 32)
    ),
    *(f"field={field},dot_order=morton,rays_per_group=8,step_mm=0.25" for field in ("float32_vec", "float16")),
    # Dot-major: every ray of a launch of one dot before the next dot.
    *(f"field={field},dot_order=morton,rays_per_group=65536" for field in ("float32_vec", "float16", "texture")),
    *(f"field={field},dot_order=morton,rays_per_group=8,max_registers=64"
      for field in ("float32", "float32_vec", "float16", "float16_nodes", "texture")),
    *(f"field={field},dot_order=morton,rays_per_group=8,max_registers=80"
      for field in ("float32_vec", "texture_nearest")),
    # Last: another block_dim compiles the whole kernel module again (Warp builds a module per block size).
    *(f"field={field},dot_order=morton,rays_per_group=8,block_dim=128" for field in ("float32_vec", "float16")),
]
# On the CPU (software textures are slow there, and the launch order matters little): a short list.
CPU_VARIANTS = [
    "default",
    "dot_order=morton,rays_per_group=8",
    *(f"field={field},dot_order=morton,rays_per_group=8"
      for field in ("float32_vec", "float16", "float16_nodes", "texture")),
]


#: The volumes ``--volume`` names: the paper's extruded slice (the default set-up), and two truly 3-D
#: 256 x 256 x 64 volumes, a Gaussian blob and a seeded turbulence cube read through the file loader.
VOLUMES = ("slice", "gaussian3d", "turbulence3d")
GRID_3D = (256, 256, 64)


def turbulence_cube(path, *, shape_xyz=GRID_3D, seed=0, amplitude_kg_m3=0.02, ambient_kg_m3=1.225):
    """Write a seeded 3-D density cube with a turbulence-like spectrum (amplitude ~ k^-11/6, an energy
    spectrum ~ k^-5/3, above the grid's two largest wavelengths) as an (nz, ny, nx) ``.npy`` file,
    density in kg/m^3 with an RMS fluctuation of ``amplitude_kg_m3``.

    Examples
    --------
    >>> import tempfile, os, numpy as np
    >>> path = os.path.join(tempfile.mkdtemp(), "cube.npy")
    >>> rho = np.load(turbulence_cube(path, shape_xyz=(16, 12, 8)))
    >>> rho.shape, round(float(rho.std()), 4), round(float(rho.mean()), 3)
    ((8, 12, 16), 0.02, 1.225)
    """
    nx, ny, nz = shape_xyz
    rng = np.random.default_rng(seed)
    k = np.sqrt(sum(np.meshgrid(np.fft.fftfreq(nz) ** 2, np.fft.fftfreq(ny) ** 2, np.fft.rfftfreq(nx) ** 2,
                                indexing="ij")))
    kmin = 2.0 / max(shape_xyz)
    amp = np.where(k >= kmin, np.maximum(k, kmin) ** (-11.0 / 6.0), 0.0)
    spec = amp * (rng.standard_normal(k.shape) + 1j * rng.standard_normal(k.shape))
    field = np.fft.irfftn(spec, s=(nz, ny, nx))
    field *= amplitude_kg_m3 / field.std()
    np.save(path, (ambient_kg_m3 + field - field.mean()).astype(np.float32))
    return path


def volume_config(volume: str, workdir: str) -> dict:
    """The ``[volume]`` table of ``--volume``: {} for the default slice."""
    if volume == "slice":
        return {}
    if volume == "gaussian3d":
        return {"volume": {"source": "gaussian", "grid": list(GRID_3D)}}
    if volume == "turbulence3d":
        path = os.path.join(workdir, "turbulence3d.npy")
        if not os.path.exists(path):
            turbulence_cube(path)
        return {"volume": {"source": "file", "path": path}}
    raise SynthbosError(f"--volume must be one of {', '.join(VOLUMES)}, got {volume!r}")


def paper_config(rays_per_dot: int, volume: dict | None = None) -> dict:
    """The paper's set-up (``raytrace/default.toml``, its one home) with ``rays_per_dot`` rays per dot,
    and ``volume`` (``volume_config``) instead of its slice when given."""
    return {"rays": {"per_dot": rays_per_dot, "chunk": CHUNK}, **(volume or {})}


def parse_variant(text: str) -> dict:
    """``"field=float16,rays_per_group=8"`` -> ``{"field": "float16", "rays_per_group": 8}``; "default" -> {}."""
    if text == "default":
        return {}
    out = {}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise SynthbosError(f"variant {text!r}: expected key=value items separated by commas")
        try:
            out[key] = int(value)
        except ValueError:
            try:
                out[key] = float(value)
            except ValueError:
                out[key] = value
    return out


def variant_config(rays_per_dot: int, variant: str, volume: dict | None = None) -> dict:
    cfg = paper_config(rays_per_dot, volume)
    cfg["rays"].update(parse_variant(variant))
    return cfg


def _trace_pair(plan, device):
    """Upload the medium, trace the reference (straight rays) and the gradient image through it, as
    ``render_pair`` does; returns the seconds of each and the results."""
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    medium = to_warp(plan.medium, device=device, field=plan.field)
    wp.synchronize_device(device)
    t1 = time.perf_counter()
    ref = render.trace_rays(plan, active=False, device=device)
    wp.synchronize_device(device)
    t2 = time.perf_counter()
    grad = render.trace_rays(plan, active=True, device=device, medium=medium)
    wp.synchronize_device(device)
    t3 = time.perf_counter()
    return (t1 - t0, t2 - t1, t3 - t2), ref, grad


def time_variant(device: str, rays_per_dot: int, variant: str, repeats: int, *, warm_up=True, volume=None) -> dict:
    """Best of ``repeats`` pair traces of one variant on one device, with its results for comparison."""
    plan = render.plan_render(variant_config(rays_per_dot, variant, volume))
    if warm_up:
        render.render_pair(render.plan_render(variant_config(2, variant, volume)), device=device)  # compile, load
    best, ref, grad = None, None, None
    for _ in range(repeats):
        times, ref, grad = _trace_pair(plan, device)
        if best is None or sum(times) < sum(best):
            best = times
    t_upload, t_ref, t_grad = best
    rays = plan.n_dots * plan.rays_per_dot
    n_steps = plan.steps_per_ray
    total = t_upload + t_ref + t_grad
    return {
        "variant": variant,
        "device": device,
        "device_name": str(wp.get_device(device).name),
        "field": plan.field,
        "exact": plan.field in EXACT_FIELDS,
        "dots": plan.n_dots,
        "rays_per_dot": plan.rays_per_dot,
        "steps_per_ray": n_steps,
        "seconds_pair": total,
        "seconds_upload": t_upload,
        "seconds_reference": t_ref,
        "seconds_gradient": t_grad,
        "rays_per_s": 2 * rays / total,
        "gradient_rays_per_s": rays / t_grad,
        "gradient_ray_steps_per_s": rays * n_steps / t_grad,
        "valid_fraction": float(np.mean(ref[2] & grad[2])),
        "_results": (ref, grad),
    }


def compare(row: dict, base: dict) -> None:
    """Add to ``row`` its displacement difference (px) and image equality against ``base``."""
    (ref, grad), (bref, bgrad) = row["_results"], base["_results"]
    ok = ref[2] & grad[2] & bref[2] & bgrad[2]
    diff = (grad[1] - ref[1])[ok] - (bgrad[1] - bref[1])[ok]
    row["max_diff_px"] = float(np.abs(diff).max()) if diff.size else float("nan")
    row["rms_diff_px"] = float(np.sqrt(np.mean(diff**2))) if diff.size else float("nan")
    row["identical"] = bool(
        np.array_equal(ref[0], bref[0]) and np.array_equal(grad[0], bgrad[0])
        and np.array_equal(grad[1], bgrad[1], equal_nan=True) and np.array_equal(ref[1], bref[1], equal_nan=True)
    )
    row["speedup_gradient"] = base["seconds_gradient"] / row["seconds_gradient"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", nargs="+", default=["cpu"])
    parser.add_argument("--rays", type=int, default=10_000, help="rays per dot on CUDA devices")
    parser.add_argument("--cpu-rays", type=int, default=100, help="rays per dot on the CPU (rates do not depend on it)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--variants", nargs="+",
                        help='"default" or key=value,... over [rays] keys; the first is the reference '
                             "(default: DEFAULT_VARIANTS)")
    parser.add_argument("--cpu-variants", nargs="+", default=None,
                        help="the variants timed on the CPU (default: a short list, or --variants when given)")
    parser.add_argument("--profile", action="store_true", help="one trace per image and variant, for ncu")
    parser.add_argument("--volume", choices=VOLUMES, default="slice",
                        help="the paper's extruded slice (default), or a 256 x 256 x 64 3-D Gaussian or "
                             "turbulence cube (the cube is written as .npy and read through the file loader)")
    parser.add_argument("--json", help="write the results here too")
    args = parser.parse_args(argv)
    workdir = tempfile.mkdtemp(prefix="synthbos-bench-render-")
    volume = volume_config(args.volume, workdir)
    variants = args.variants or DEFAULT_VARIANTS
    cpu_variants = args.cpu_variants or args.variants or CPU_VARIANTS
    init_warp()
    rows, failed = [], []
    for dev in args.devices:
        rays = args.cpu_rays if dev == "cpu" else args.rays
        repeats = 1 if dev == "cpu" or args.profile else args.repeats
        base = None
        for variant in cpu_variants if dev == "cpu" else variants:
            try:
                row = time_variant(dev, rays, variant, repeats, warm_up=not args.profile, volume=volume)
                row["volume"] = args.volume
            except Exception as exc:  # one failing variant must not lose the others' numbers
                print(f"{dev} {variant}: FAILED: {type(exc).__name__}: {exc}", flush=True)
                failed.append({"device": dev, "variant": variant, "error": f"{type(exc).__name__}: {exc}"})
                continue
            base = base or row
            compare(row, base)
            rows.append(row)
            print(f"{dev} {variant}: reference {row['seconds_reference']:.4f} s, gradient "
                  f"{row['seconds_gradient']:.4f} s, upload {row['seconds_upload']:.4f} s, pair "
                  f"{row['rays_per_s']:.3e} rays/s, gradient {row['gradient_ray_steps_per_s']:.3e} ray-steps/s, "
                  f"diff max {row['max_diff_px']:.2e} px rms {row['rms_diff_px']:.2e} px, "
                  f"{'identical' if row['identical'] else 'differs'}", flush=True)
            if args.json:
                _write_json(args.json, rows, failed)
        for row in rows:
            row.pop("_results", None)
    if not rows:
        raise SynthbosError(f"every variant failed: {failed}")
    r0 = rows[0]
    print(f"\nrender speed, paper configuration, volume {args.volume} ({r0['dots']} dots, "
          f"{r0['steps_per_ray']} RK4 steps per ray); "
          "diff: displacement against each device's first variant")
    print(f"{'device':<7} {'variant':<58} {'rays':>5} {'upload':>7} {'ref s':>7} {'grad s':>7} {'pair rays/s':>11} "
          f"{'grad steps/s':>12} {'speedup':>7} {'max diff':>9} {'rms diff':>9} {'same':>5} {'vs 2e6':>7}")
    for r in rows:
        print(f"{r['device']:<7} {r['variant'][:58]:<58} {r['rays_per_dot']:>5} {r['seconds_upload']:>7.3f} "
              f"{r['seconds_reference']:>7.3f} {r['seconds_gradient']:>7.3f} {r['rays_per_s']:>11.3e} "
              f"{r['gradient_ray_steps_per_s']:>12.3e} {r['speedup_gradient']:>7.2f} {r['max_diff_px']:>9.2e} "
              f"{r['rms_diff_px']:>9.2e} {'yes' if r['identical'] else 'no':>5} "
              f"{r['rays_per_s'] / PREDECESSOR_RAYS_PER_S:>7.1f}")
    for f in failed:
        print(f"{f['device']:<7} {f['variant'][:58]:<58} FAILED: {f['error']}")
    if args.json:
        _write_json(args.json, rows, failed)
    return rows


def _write_json(path, rows, failed):
    """Write the rows so far (without their result arrays): a run cut short still leaves its numbers."""
    with open(path, "w") as f:
        json.dump({"date": time.strftime("%Y-%m-%d"), "failed": failed,
                   "rows": [{k: v for k, v in r.items() if k != "_results"} for r in rows]}, f, indent=2)


if __name__ == "__main__":
    main()
