"""Renderer speed: rays per second and ray-steps per second of the full render (trace + lens + deposit).

The paper configuration: 512 x 512 px, 10 um pixels, f = 105 mm, f/11, target at 1 m (M ~ 0.117),
Z_D = 250 mm, a 32 x 32 x 10 mm volume on a 256 x 256 grid, 20 dots per 32 x 32 px, 3 px dots,
10,000 rays per dot. Every device given is timed in the same process after a warm-up render that
compiles and loads the kernels; the table ends with each device's ratio to the first one and to the
published CUDA predecessor (about 2e6 rays/s).

    python -m synthbos.benchmarks.bench_render --devices cpu cuda:0 --rays 10000 --cpu-rays 100
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp
from synthbos.raytrace import render

from synthbos.device import init_warp

PREDECESSOR_RAYS_PER_S = 2e6


def paper_config(rays_per_dot: int) -> dict:
    """The paper's set-up (``raytrace/default.toml``, its one home) with ``rays_per_dot`` rays per dot."""
    return {"rays": {"per_dot": rays_per_dot, "chunk": 1 << 24}}


def time_device(device: str, rays_per_dot: int, repeats: int) -> dict:
    plan = render.plan_render(paper_config(rays_per_dot))
    warm = render.plan_render(paper_config(2))
    render.render_pair(warm, device=device)  # compile, load, allocate once
    best = None
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        render.trace_rays(plan, active=False, device=device)
        wp.synchronize_device(device)
        t1 = time.perf_counter()
        _, _, ok, _ = render.trace_rays(plan, active=True, device=device)
        wp.synchronize_device(device)
        t2 = time.perf_counter()
        if best is None or t2 - t0 < best[0]:
            best = (t2 - t0, t1 - t0, t2 - t1)
    total, t_ref, t_grad = best
    rays = plan.n_dots * plan.rays_per_dot
    steps = plan.steps_per_ray
    return {
        "device": device,
        "device_name": str(wp.get_device(device).name),
        "dots": plan.n_dots,
        "rays_per_dot": plan.rays_per_dot,
        "steps_per_ray": steps,
        "seconds_pair": total,
        "seconds_reference": t_ref,
        "seconds_gradient": t_grad,
        "rays_per_s": 2 * rays / total,
        "gradient_rays_per_s": rays / t_grad,
        "gradient_ray_steps_per_s": rays * steps / t_grad,
        "valid_fraction": float(np.mean(ok)),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", nargs="+", default=["cpu"])
    parser.add_argument("--rays", type=int, default=10_000, help="rays per dot on CUDA devices")
    parser.add_argument("--cpu-rays", type=int, default=100, help="rays per dot on the CPU (rates do not depend on it)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", help="write the results here too")
    args = parser.parse_args(argv)
    init_warp()
    rows = []
    for dev in args.devices:
        rays = args.cpu_rays if dev == "cpu" else args.rays
        rows.append(time_device(dev, rays, 1 if dev == "cpu" else args.repeats))
    base = rows[0]["rays_per_s"]
    print(f"\nrender speed, paper configuration ({rows[0]['dots']} dots, {rows[0]['steps_per_ray']} RK4 steps per ray)")
    print(f"{'device':<10} {'name':<26} {'rays/dot':>8} {'pair s':>9} {'rays/s':>10} {'grad ray-steps/s':>17} "
          f"{'vs first':>9} {'vs 2e6':>8}")
    for r in rows:
        print(f"{r['device']:<10} {r['device_name'][:26]:<26} {r['rays_per_dot']:>8} {r['seconds_pair']:>9.3f} "
              f"{r['rays_per_s']:>10.3e} {r['gradient_ray_steps_per_s']:>17.3e} {r['rays_per_s'] / base:>9.1f} "
              f"{r['rays_per_s'] / PREDECESSOR_RAYS_PER_S:>8.1f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"date": time.strftime("%Y-%m-%d"), "rows": rows}, f, indent=2)
    return rows


if __name__ == "__main__":
    main()
