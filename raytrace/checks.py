"""The one home of value checks of the renderer: a configuration number, and a density field.

``number`` checks every number of a configuration (``raytrace.config`` for the fixed tables,
``raytrace.sources`` for each source's own keys); ``check_density`` checks every density array,
whether it comes from a file (``raytrace.loaders``), a source or the medium (``raytrace.medium``).
Both raise ``SynthbosError`` naming the key or the file.

Resource limits (``[limits]`` table of a configuration) are checked here too, with ``check_memory``:
see ``raytrace.config`` for the keys and their defaults.
"""

from __future__ import annotations

import math
import os

import numpy as np

from synthbos import SynthbosError
from synthbos.values import number  # the one home of a checked number; here for the renderer's modules

__all__ = [
    "BYTES_PER_NODE",
    "MAX_DENSITY_KG_M3",
    "MAX_SPOT_PX",
    "check_density",
    "check_file_memory",
    "check_memory",
    "check_ray_steps",
    "check_render_plan",
    "default_memory_gb",
    "number",
    "vector",
]

# Densest thing a BOS medium can be (osmium is 22.6e3 kg/m^3); beyond it a value is a unit mistake.
MAX_DENSITY_KG_M3 = 1.0e5
# Host memory per node of a density grid from reading to the packed medium (float64 copies of the raw,
# scaled and extruded data, the gradient, the packed float32 field): a deliberate over-estimate.
BYTES_PER_NODE = 128


def vector(name, value, sizes, **bounds):
    """A list of numbers of one of the lengths ``sizes``, each checked by ``number`` (as floats)."""
    if not isinstance(value, list | tuple) or len(value) not in sizes:
        raise SynthbosError(f"{name} must be a list of {' or '.join(map(str, sizes))} numbers, got {value!r}")
    return [number(f"{name}[{i}]", v, **bounds) for i, v in enumerate(value)]


def check_density(data, *, where, ndim=(2, 3), min_nodes=2, hint=""):
    """Check density data: real numbers, the right dimensionality, finite, > 0 and physically dense at most.

    Parameters
    ----------
    data : array_like
    where : str
        What to name in the error message (a file, ``volume``, a source).
    ndim : tuple of int
        Allowed numbers of dimensions.
    min_nodes : int
        Least number of nodes along every axis.
    hint : str
        What to change, appended to the message of a value out of range.

    Returns
    -------
    float64 ndarray

    Raises
    ------
    SynthbosError
        Non-numeric, empty, wrong dimensionality, fewer than ``min_nodes`` along an axis, NaN/inf,
        a value <= 0 or above ``MAX_DENSITY_KG_M3``; the first offending index is named.
    """
    arr = np.asarray(data)
    if arr.dtype.kind not in "fiu":
        raise SynthbosError(f"{where}: density must be real numbers, got dtype {arr.dtype}")
    if arr.size == 0:
        raise SynthbosError(f"{where}: density array is empty")
    if arr.ndim not in ndim:
        want = " or ".join(f"{n}-D" for n in ndim)
        raise SynthbosError(f"{where}: density must be {want}, got shape {arr.shape}")
    if min(arr.shape) < min_nodes:
        raise SynthbosError(f"{where}: need at least {min_nodes} nodes along every axis, got shape {arr.shape}")
    arr = arr.astype(np.float64, copy=False)
    bad = ~np.isfinite(arr)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise SynthbosError(f"{where}: density has {int(bad.sum())} NaN/inf value(s), first at index {idx}")
    low = arr <= 0
    if low.any():
        idx = tuple(int(i) for i in np.argwhere(low)[0])
        raise SynthbosError(
            f"{where}: density must be > 0 everywhere; {int(low.sum())} value(s) <= 0, "
            f"minimum {arr.min():.6g} (first at index {idx}){hint}"
        )
    high = arr > MAX_DENSITY_KG_M3
    if high.any():
        idx = tuple(int(i) for i in np.argwhere(high)[0])
        raise SynthbosError(
            f"{where}: density reaches {arr.max():.6g} kg/m^3 (first at index {idx}); more than "
            f"{MAX_DENSITY_KG_M3:g} kg/m^3 is no fluid (check the units and volume.density_scale_kg_m3){hint}"
        )
    return arr


def default_memory_gb() -> float:
    """Default ``limits.memory_gb``: 80 % of this machine's memory, at most 64 GB."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9
    except (AttributeError, OSError, ValueError):
        total = 16.0 / 0.8
    return min(64.0, 0.8 * total)


def check_memory(nbytes, what, *, memory_gb=None):
    """Refuse work whose estimated memory ``nbytes`` exceeds ``limits.memory_gb``."""
    limit = default_memory_gb() if memory_gb is None else float(memory_gb)
    if nbytes > limit * 1e9:
        raise SynthbosError(
            f"{what} needs about {nbytes / 1e9:.3g} GB of memory, over the limit of {limit:.3g} GB "
            "(raise limits.memory_gb in the configuration if this machine has the memory)"
        )


# Working copies of a dataset read from a file (as stored, float64, the arrays built from it): a
# deliberate over-estimate of the memory reading a file and working on its contents takes.
COPIES_PER_READ = 4


def check_file_memory(datasets, what, *, memory_gb=None):
    """Refuse to read HDF5 datasets whose declared shapes need more than ``limits.memory_gb``.

    Parameters
    ----------
    datasets : iterable of h5py.Dataset
        The datasets about to be read; only their declared shape and type are looked at, so a file
        declaring a 1e6 x 1e6 image (chunked, nearly empty on disk) is refused before any allocation.
    what : str
        The file, for the message.
    memory_gb : float, optional
        The limit (default: ``default_memory_gb()``).
    """
    total, largest = 0, None
    for d in datasets:
        n = math.prod(int(k) for k in d.shape) * max(int(d.dtype.itemsize), 8)
        total += n
        if largest is None or n > largest[0]:
            largest = (n, d.name, tuple(int(k) for k in d.shape))
    if largest is not None:
        check_memory(COPIES_PER_READ * total,
                     f"{what} (its {largest[1]} declares shape {largest[2]})", memory_gb=memory_gb)


# Largest spot (image diameter of a dot, px): beyond it a "dot" covers a whole interrogation window and
# each ray's deposit (a (6 sigma)^2 px square) makes a render needlessly slow.
MAX_SPOT_PX = 64.0


def check_render_plan(plan):
    """Checks of a resolved render plan before any ray is traced: spot size, steps per ray, total work.

    Parameters
    ----------
    plan : raytrace.render.RenderPlan

    Raises
    ------
    SynthbosError
        The sensor spot (given, or the diffraction spot) exceeds ``MAX_SPOT_PX``, or a ray would take
        more than ``limits.steps_per_ray`` RK4 steps (the messages name the keys to change). The total
        work, which depends on the device, is checked by ``check_ray_steps``.
    """
    cfg = plan.cfg
    limits = cfg["limits"]
    if not 0.1 <= plan.spot_diameter_px <= MAX_SPOT_PX:
        given = cfg["sensor"]["spot_diameter_px"]
        cause = (
            f"sensor.spot_diameter_px = {given!r} gives the diffraction spot 2.44 lambda f# (1 + M) of "
            f"camera.wavelength_nm = {cfg['camera']['wavelength_nm']:g} at camera.f_number = "
            f"{cfg['camera']['f_number']:g}"
        )
        raise SynthbosError(
            f"{cause}: {plan.spot_diameter_px:.4g} px, outside 0.1..{MAX_SPOT_PX:g} px; "
            "change the f-number or give the spot diameter in px"
        )
    steps = plan.steps_per_ray
    depth_mm = plan.medium.size[2] * 1e3
    step_key = "rays.step_mm" if cfg["rays"]["step_mm"] != "grid" else 'rays.step_mm = "grid" (the grid spacing)'
    if steps > limits["steps_per_ray"]:
        raise SynthbosError(
            f"{step_key} = {plan.step * 1e3:.4g} mm takes {steps} RK4 steps across the volume's depth of "
            f"{depth_mm:.4g} mm, more than limits.steps_per_ray = {limits['steps_per_ray']}; use a larger "
            "rays.step_mm (or a coarser grid), or raise limits.steps_per_ray"
        )


# Default limits.ray_steps: about 10 minutes of Warp's one-thread CPU backend (~1e7 ray-steps/s), or
# about 3 minutes of an H200 (~5e9 ray-steps/s).
RAY_STEPS_CPU = 1.0e10
RAY_STEPS_CUDA = 1.0e12


def check_ray_steps(plan, device=None):
    """Refuse a render whose rays x RK4 steps exceed ``limits.ray_steps``.

    Parameters
    ----------
    plan : raytrace.render.RenderPlan
    device : str, optional
        The Warp device that will render (Warp's default if None): the default limit is
        ``RAY_STEPS_CUDA`` on a GPU and ``RAY_STEPS_CPU`` on the CPU.
    """
    limit = plan.cfg["limits"]["ray_steps"]
    if limit is None:
        import warp as wp

        from synthbos.device import init_warp

        init_warp()  # quietly: no missing-driver warning on a machine without a GPU
        limit = RAY_STEPS_CUDA if wp.get_device(device).is_cuda else RAY_STEPS_CPU
    steps = plan.steps_per_ray
    total = 2.0 * plan.n_dots * plan.rays_per_dot * steps * (1 + plan.aim_iterations)
    if total > limit:
        raise SynthbosError(
            f"the render needs about {total:.3g} ray-steps (2 images x {plan.n_dots} dots x "
            f"{plan.rays_per_dot} rays.per_dot x {steps} steps x {1 + plan.aim_iterations} aim passes), more "
            f"than limits.ray_steps = {limit:.3g} on this device; use fewer rays or a larger rays.step_mm, "
            "or raise limits.ray_steps"
        )


