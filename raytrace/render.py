"""Host code of the renderer: allocate, launch the kernels of ``raytrace.kernels``, copy back.

``render_pair(config)`` traces every ray of every dot twice, through the undisturbed medium (the
reference image) and through the density volume (the gradient image), with the same random ray set,
and returns the images and per-dot ground truth as a ``Pair``.
"""

from __future__ import annotations

import math
import time

import numpy as np
import warp as wp
from tqdm.auto import tqdm

import synthbos
from synthbos import SynthbosError
from synthbos.device import check_device, init_warp

from . import checks, kernels, medium_kernels, sources, truth_kernels
from .camera import CameraModel, camera_from_config
from .config import config_to_toml, load_config
from .medium import EXACT_FIELDS, MediumData, medium_from_config, medium_struct, straight_to_warp, to_warp
from .pairfile import Pair
from .pattern import grid_pattern, random_pattern

__all__ = [
    "RenderPlan", "central_moments", "chief_ray_truth", "cone_truth", "moment_scales", "morton_order", "plan_render",
    "render_modules", "render_pair", "trace_rays",
]

_INT32_MAX = 2**31 - 1


class RenderPlan:
    """Everything a render needs, resolved from a configuration on the host (no device work)."""

    def __init__(self, cfg: dict):
        self.cfg = cfg
        self.camera: CameraModel = camera_from_config(cfg)
        self.medium: MediumData = medium_from_config(cfg)
        tgt, rays, sen = cfg["target"], cfg["rays"], cfg["sensor"]
        W, H = self.camera.pixels
        M, pitch = self.camera.magnification, self.camera.pitch
        if tgt["pattern"] == "grid":
            px = grid_pattern(W, H, tgt["dots_per_32px"])
        else:
            spacing = tgt["min_spacing_px"] if tgt["min_spacing_px"] is not None else tgt["dot_diameter_px"]
            px = random_pattern(W, H, tgt["dots_per_32px"], min_spacing=spacing, seed=tgt["seed"])
        self.nominal_px = px
        depth, z_mid = self.medium.size[2], self.medium.centre[2]
        if z_mid - depth / 2.0 <= 0.0 or z_mid + depth / 2.0 >= self.camera.z_stop:
            raise SynthbosError(
                f"the volume's depth from its data ({depth * 1e3:.2f} mm) around "
                f"volume.distance_from_target_mm={z_mid * 1e3:g} reaches the target or the lens"
            )
        self.target_xy = self.camera.pixel_to_target(px)
        self.dot_radius = 0.0 if tgt["dot_model"] == "point" else float(0.5 * tgt["dot_diameter_px"] * pitch / M)
        spot = sen["spot_diameter_px"]
        if spot == "auto":
            spot = tgt["dot_diameter_px"] if tgt["dot_model"] == "point" else "diffraction"
        if spot == "diffraction":
            spot = self.camera.diffraction_spot_diameter / pitch
        self.spot_diameter_px = float(spot)
        self.sigma_px = self.spot_diameter_px / 4.0
        self.half_width = max(1, math.ceil(3.0 * self.sigma_px))
        self.rays_per_dot = rays["per_dot"]
        # Each dot's energy is that of a point dot's spot of peak I0: I0 * 2 pi sigma^2.
        self.energy_per_ray = sen["peak_intensity"] * 2.0 * math.pi * self.sigma_px**2 / self.rays_per_dot
        aim = rays["aim_iterations"]
        self.aim_iterations = (1 if self.camera.lens == "thick" else 0) if aim == "auto" else int(aim)
        step = rays["step_mm"]
        self.step = min(self.medium.spacing) if step == "grid" else step * 1e-3
        self.field = rays["field"]
        self.cells = rays["stepping"] == "cells"
        # The longest RK4 step: step_mm, or with "cells" stepping and step_mm = "grid" a quarter of the depth.
        self.ray_step = self.medium.size[2] / 4.0 if self.cells and step == "grid" else self.step
        self.rays_per_group = rays["rays_per_group"]
        self.rays_per_thread = rays["rays_per_thread"]
        self.block_dim = rays["block_dim"]
        self.max_registers = rays["max_registers"]
        self.launch_order = morton_order(px) if rays["dot_order"] == "morton" else np.arange(len(px), dtype=np.int32)
        if self.n_dots * self.rays_per_dot > _INT32_MAX:
            raise SynthbosError(
                f"{self.n_dots} dots x {self.rays_per_dot} rays exceeds 2^31 rays per image; use fewer rays.per_dot"
            )
        self._check_field_of_view()
        checks.check_render_plan(self)

    @property
    def n_dots(self) -> int:
        return len(self.nominal_px)

    @property
    def steps_per_ray(self) -> int:
        """RK4 steps of an axial ray across the volume at ``step`` (off-axis rays take the same or one more):
        the "fixed" stepping's count, and an upper bound for "cells" stepping through a field that varies
        on the grid's scale (used for the resource limits and the ground truths' sampling)."""
        return max(1, math.ceil(self.medium.size[2] / self.step - 1e-4))

    def _check_field_of_view(self):
        """The volume must intersect the bundle of rays from the imaged part of the target."""
        cam, med = self.camera, self.medium
        W, H = cam.pixels
        half_fov = np.array([W, H]) * cam.pitch / cam.magnification / 2.0
        z_mid = med.centre[2]
        # Rays from the field |X| < half_fov towards an aperture of radius a at z_stop cross plane z at
        # |x| < half_fov (1 - z / z_stop) + a z / z_stop.
        reach = half_fov * (1.0 - z_mid / cam.z_stop) + cam.aperture_radius * z_mid / cam.z_stop
        lo = np.array(med.centre[:2]) - np.array(med.size[:2]) / 2.0
        hi = np.array(med.centre[:2]) + np.array(med.size[:2]) / 2.0
        if np.any(lo > reach) or np.any(hi < -reach):
            raise SynthbosError(
                "the volume misses the field of view entirely: at its mid-plane the camera sees "
                f"|x| < {reach[0] * 1e3:.1f} mm, |y| < {reach[1] * 1e3:.1f} mm, but the volume spans "
                f"x in [{lo[0] * 1e3:.1f}, {hi[0] * 1e3:.1f}] mm, y in [{lo[1] * 1e3:.1f}, {hi[1] * 1e3:.1f}] mm"
            )


def morton_order(px) -> np.ndarray:
    """Indices of the points ``px`` (N, 2) along a Z-order (Morton) curve over the image.

    Consecutive points of the curve are neighbours on the image, so threads that take the dots in
    this order read nearby nodes of the volume.
    """
    q = np.asarray(px, dtype=np.float64)
    q = np.clip(np.round(q - q.min(axis=0)), 0, 2**16 - 1).astype(np.uint64)
    code = np.zeros(len(q), dtype=np.uint64)
    for bit in range(16):
        code |= ((q[:, 0] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(2 * bit)
        code |= ((q[:, 1] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(2 * bit + 1)
    return np.argsort(code, kind="stable").astype(np.int32)


def plan_render(config=None) -> RenderPlan:
    """Resolve a configuration (dict, path or None for the defaults) into a render plan."""
    return RenderPlan(load_config(config))


def _camera_struct(cam: CameraModel) -> kernels.Camera:
    c = kernels.Camera()
    c.lens = 0 if cam.lens == "thin" else 1
    c.z_stop = cam.z_stop
    c.aperture_radius = cam.aperture_radius
    c.focal_length = cam.focal_length
    c.z_sensor = cam.z_sensor
    c.c1, c.r1, c.c2, c.r2 = cam.c1, cam.r1, cam.c2, cam.r2
    c.glass_index = cam.glass_index
    c.semi_diameter = cam.semi_diameter
    return c


def _sensor_struct(plan: RenderPlan) -> kernels.Sensor:
    s = kernels.Sensor()
    s.width, s.height = plan.camera.pixels
    s.pitch = plan.camera.pitch
    s.cx, s.cy = plan.camera.principal_point
    s.sigma_px = plan.sigma_px
    s.half_width = plan.half_width
    s.energy = plan.energy_per_ray
    return s


def trace_rays(plan: RenderPlan, *, active: bool, device=None, progress=None, label="", medium=None):
    """Trace every ray of every dot once and deposit it.

    Parameters
    ----------
    plan : RenderPlan
    active : bool
        False for the reference (undisturbed medium, straight rays), True through the volume.
    device : str, optional
        Warp device ("cpu", "cuda:0"); Warp's default if None.
    progress : tqdm or None
        A bar to advance by the number of rays traced.
    medium : optional
        The plan's medium already on ``device`` (``to_warp(plan.medium, field=plan.field)``) for the
        gradient image, uploaded here if None. The reference image reads no medium: its rays run
        through ``straight_to_warp(plan.medium)``, the box's placement alone.

    Returns
    -------
    image : (H, W) float32
    mean_px : (N, 2) float64 ray-mean position of each dot (x = column, y = row)
    ok : (N,) bool, every ray of the dot reached the sensor
    n_tir : int, rays lost to total internal reflection
    covariance_px2 : (N, 3) float64 [var_x, var_y, cov_xy] of the dot's landing positions about their mean
    third_moment_px3 : (N, 4) float64 [m30, m21, m12, m03], their central third moments
        (both NaN for a dot with no ray on the sensor plane or a ray beyond ``kernels.MOMENT_RANGE_PX``;
        see :func:`central_moments`)

    Notes
    -----
    The plan's speed settings (``rays.field``, ``rays.dot_order``, ``rays.rays_per_group``,
    ``rays.rays_per_thread``, ``rays.block_dim``, ``rays.max_registers``) choose how the medium is stored
    and read and which thread traces which ray; only ``field`` can change the result (see ``raytrace.medium.FIELDS``).
    """
    init_warp()
    W, H = plan.camera.pixels
    n = plan.n_dots
    if not active:
        medium = straight_to_warp(plan.medium)
    elif medium is None:
        medium = to_warp(plan.medium, device=device, field=plan.field)
    cam = _camera_struct(plan.camera)
    sen = _sensor_struct(plan)
    dots = wp.array(plan.target_xy.astype(np.float32), dtype=wp.vec2, device=device)
    nominal = wp.array(plan.nominal_px.astype(np.float32), dtype=wp.vec2, device=device)
    order = wp.array(plan.launch_order, dtype=wp.int32, device=device)
    image = wp.zeros((H, W), dtype=wp.int64, device=device)
    sum_x = wp.zeros(n, dtype=wp.int64, device=device)
    sum_y = wp.zeros(n, dtype=wp.int64, device=device)
    sums = wp.zeros((n, 7), dtype=wp.int64, device=device)
    far = wp.zeros(n, dtype=wp.int32, device=device)
    scale2, scale3 = moment_scales(plan.rays_per_dot)
    hits = wp.zeros(n, dtype=wp.int32, device=device)
    lost = wp.zeros(n, dtype=wp.int32, device=device)
    tir = wp.zeros(n, dtype=wp.int32, device=device)
    # A register cap is a CUDA setting: the CPU runs the plain kernel (the same bits either way).
    on_cuda = wp.get_device(device).is_cuda
    cap = register_cap(plan.max_registers, active=active, planar=plan.medium.planar) if on_cuda else 0
    kernel = kernels.render_kernel(medium, cap)
    per_thread, group = launch_shape(plan, active=active)
    rays_per_launch = max(per_thread, plan.cfg["rays"]["chunk"] // n)
    group = min(group, -(-rays_per_launch // per_thread))  # at most every chunk of a launch: dot-major order
    if rays_per_launch > group * per_thread:
        rays_per_launch -= rays_per_launch % (group * per_thread)  # whole groups, except in the last launch
    # spot tiles where the rays are cheap and the spots are the cost: a planar medium's few steps (through a
    # truly 3-D medium even the reference image's straight rays step across every node plane, and tiles
    # made its render slower: 0.052 against 0.044 s on an H100, 2026-11-27)
    planar = plan.medium.planar
    side = spot_tile_side(plan.block_dim, group, plan.half_width, per_thread) if on_cuda and planar else 0
    for start in range(0, plan.rays_per_dot, rays_per_launch):
        count = min(rays_per_launch, plan.rays_per_dot - start)
        chunks = -(-count // per_thread)
        threads = -(-chunks // group) * group * n
        if side:  # whole blocks: every thread of a block meets its barriers
            threads = -(-threads // plan.block_dim) * plan.block_dim
        wp.launch(
            kernel, dim=threads,
            inputs=[medium, int(active), cam, sen, dots, nominal, order, plan.dot_radius, plan.ray_step,
                    int(plan.cells), plan.aim_iterations, plan.cfg["rays"]["seed"], start, count, group,
                    per_thread, wp.float64(scale2), wp.float64(scale3), plan.block_dim, side],
            outputs=[image, sum_x, sum_y, sums, far, hits, lost, tir], device=device, block_dim=plan.block_dim,
        )
        if progress is not None:
            wp.synchronize_device(device)
            progress.update(count * n)
    hits_np = hits.numpy()
    safe = np.maximum(hits_np, 1)
    scale = float(kernels.POSITION_SCALE)
    mean = np.stack([sum_x.numpy() / scale / safe, sum_y.numpy() / scale / safe], axis=1) + plan.nominal_px
    mean[hits_np == 0] = np.nan
    ok = (lost.numpy() == 0) & (hits_np == plan.rays_per_dot)
    cov, third = central_moments(sum_x.numpy(), sum_y.numpy(), sums.numpy(), hits_np, far.numpy(),
                                 scales=(scale2, scale3))
    return fixed_to_image(image.numpy()), mean, ok, int(tir.numpy().sum()), cov, third


#: ``rays.rays_per_thread`` and ``rays.rays_per_group`` = "auto": (rays a thread, chunks a group) where
#: every ray of a launch takes about the same number of steps (straight rays; planar media, whose cell
#: steps are few and alike), and through a truly 3-D medium, where a thread's rays cross different
#: numbers of node planes (the longest holds its warp up: one ray a thread) and a warp whose rays read
#: nearby nodes gains (more chunks a group). Measured on an H100, 2026-11-27: the slice 1.26e9 -> 1.49e9
#: pair rays/s at 8 rays a thread, 1.47e9 at 8 chunks a group against 1.39e9 at 32; a 256 x 256 x 64
#: Gaussian 4.10e8 at 1 ray a thread, 3.88e8 at 4, 2.74e8 at 16, and 4.04e8 at 8 chunks a group, 4.42e8
#: at 32, 4.48e8 at 64.
AUTO_LAUNCH_ALIKE = (8, 8)
#: The fewest rays a thread must trace for its block to sum its spots in shared memory (``spot_tile_side``).
SPOT_TILE_RAYS = 4
AUTO_LAUNCH_3D = (1, 64)
#: ``rays.max_registers = "auto"``: the register cap of a CUDA render for straight rays and planar media,
#: and through a truly 3-D medium, whose cell steps hold a cell's eight nodes (docs/benchmarks.md).
AUTO_REGISTERS_ALIKE = 64
AUTO_REGISTERS_3D = 80


def launch_shape(plan: RenderPlan, *, active: bool) -> tuple[int, int]:
    """How ``render_rays`` splits a launch: the consecutive rays of one dot each thread traces
    (``rays.rays_per_thread``) and the chunks of one dot's rays consecutive threads take
    (``rays.rays_per_group``), "auto" resolved by the medium.

    Examples
    --------
    >>> plan = plan_render({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 4}})
    >>> launch_shape(plan, active=True), launch_shape(plan, active=False)  # the slice is planar
    ((8, 8), (8, 8))
    >>> blob = plan_render({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 4},
    ...                     "volume": {"source": "gaussian", "grid": [16, 16, 8]}})
    >>> launch_shape(blob, active=True), launch_shape(blob, active=False)  # a 3-D medium; straight rays
    ((1, 64), (8, 8))
    """
    auto = AUTO_LAUNCH_ALIKE if not active or plan.medium.planar else AUTO_LAUNCH_3D
    settings = (plan.rays_per_thread, plan.rays_per_group)
    return tuple(a if v == "auto" else int(v) for a, v in zip(auto, settings, strict=True))


def spot_tile_side(block_dim: int, group: int, half_width: int, rays_per_thread: int) -> int:
    """The side (cells) of each group's spot tile in a CUDA block's shared memory (``kernels.SPOT_CELLS``
    shared by the ``block_dim / group`` groups, at most ``kernels.SPOT_SIDE_MAX``), or 0 (no tiles) where
    groups do not tile the block, a tile would not hold a spot (``2 half_width + 1`` px) with a pixel of
    play each way, or a thread traces fewer than ``SPOT_TILE_RAYS`` rays (a block's tiles, cleared and
    read once, then hold too few spots to pay for themselves: a 3-D medium's one ray a thread).

    Examples
    --------
    >>> spot_tile_side(256, 8, 3, 8), spot_tile_side(256, 6, 3, 8), spot_tile_side(256, 8, 5, 8)
    (11, 0, 0)
    >>> spot_tile_side(256, 64, 3, 1), spot_tile_side(256, 64, 3, 8)
    (0, 24)
    """
    if block_dim % group or rays_per_thread < SPOT_TILE_RAYS:
        return 0
    side = min(kernels.SPOT_SIDE_MAX, math.isqrt(kernels.SPOT_CELLS // (block_dim // group)))
    return side if side >= 2 * half_width + 3 else 0


def register_cap(max_registers, *, active: bool, planar: bool) -> int:
    """The register cap of a CUDA render (``rays.max_registers``; "auto": ``AUTO_REGISTERS_3D`` for the
    gradient image through a truly 3-D medium, else ``AUTO_REGISTERS_ALIKE``).

    Examples
    --------
    >>> register_cap("auto", active=True, planar=False), register_cap("auto", active=False, planar=False)
    (80, 64)
    >>> register_cap(0, active=True, planar=False)
    0
    """
    if max_registers != "auto":
        return int(max_registers)
    return AUTO_REGISTERS_3D if active and not planar else AUTO_REGISTERS_ALIKE


def moment_scales(rays_per_dot: int) -> tuple[float, float]:
    """Fixed-point scales of the sums of second and third powers of the rays' offsets (see
    ``kernels.add_moments``), chosen so that no sum can overflow an int64.

    A summed offset lies within R = ``kernels.MOMENT_RANGE_PX`` of the nominal position on each axis,
    so a sum of N rays' products of order k is at most N R^k; each scale is the largest power of two
    (at most 2^32) with N R^k scale <= 2^62, each rounding to the nearest integer adding at most half
    a unit. With R = 256 px, at 1,000 rays per dot the units are 2^-32 px^2 and 2^-28 px^3; at 10^4,
    2^-32 and 2^-24; at 10^6, 2^-26 and 2^-18; at the configuration's limit of 10^8 rays, 2^-19 px^2
    and 2^-11 px^3 (a dot's moment, a mean of N roundings of mean zero, errs far less than one unit).

    Examples
    --------
    >>> [math.log2(s) for s in moment_scales(1000)]
    [32.0, 28.0]
    """
    r = float(kernels.MOMENT_RANGE_PX)
    scales = []
    for power in (2, 3):
        exponent = math.floor(62 - math.log2(rays_per_dot * r**power))
        scales.append(math.ldexp(1.0, min(32, exponent)))
    return scales[0], scales[1]


def central_moments(sum_x, sum_y, sums, hits, far, *, scales):
    """Covariance and central third moments of each dot's landing positions from its fixed-point sums.

    Parameters
    ----------
    sum_x, sum_y : (N,) int64
        Sums of the offsets from the nominal position, units of 1 / ``kernels.POSITION_SCALE`` px.
    sums : (N, 7) int64
        Sums of xx, yy, xy (units 1 / scales[0]) and xxx, xxy, xyy, yyy (units 1 / scales[1]).
    hits, far : (N,) int
        Rays summed, and rays beyond ``kernels.MOMENT_RANGE_PX`` (left out of ``sums``).
    scales : (float, float)
        From :func:`moment_scales`.

    Returns
    -------
    covariance : (N, 3) float64
        [var_x, var_y, cov_xy], px^2.
    third : (N, 4) float64
        [m30, m21, m12, m03] = E[dx^3], E[dx^2 dy], E[dx dy^2], E[dy^3] about the mean, px^3.
        Both NaN where ``hits`` is 0 or ``far`` is not.

    Notes
    -----
    The raw moments about the nominal position (E[x] = mx, E[xx], ...) are exact integer sums, read
    in float64, and shifted to the mean: var_x = E[xx] - mx^2, m30 = E[xxx] - 3 mx E[xx] + 2 mx^3, ...
    The offsets from the nominal position are the displacement plus the spread, and the shift loses
    about 2^-52 of E[x^k] (1e-14 px^2 for 10 px displacements); the fixed point's roundings, at most
    half a unit per ray, move a moment by less than that unit (:func:`moment_scales`).
    """
    n = np.asarray(hits, dtype=np.float64)
    safe = np.maximum(n, 1.0)[:, None]
    position = float(kernels.POSITION_SCALE)
    mx = np.asarray(sum_x, dtype=np.float64) / position / safe[:, 0]
    my = np.asarray(sum_y, dtype=np.float64) / position / safe[:, 0]
    sums = np.asarray(sums, dtype=np.float64)
    e2 = sums[:, :3] / scales[0] / safe  # E[xx], E[yy], E[xy]
    e3 = sums[:, 3:] / scales[1] / safe  # E[xxx], E[xxy], E[xyy], E[yyy]
    cov = e2 - np.stack([mx * mx, my * my, mx * my], axis=1)
    third = np.stack([
        e3[:, 0] - 3.0 * mx * e2[:, 0] + 2.0 * mx**3,
        e3[:, 1] - 2.0 * mx * e2[:, 2] - my * e2[:, 0] + 2.0 * mx * mx * my,
        e3[:, 2] - 2.0 * my * e2[:, 2] - mx * e2[:, 1] + 2.0 * mx * my * my,
        e3[:, 3] - 3.0 * my * e2[:, 1] + 2.0 * my**3,
    ], axis=1)
    missing = (np.asarray(hits) == 0) | (np.asarray(far) != 0)
    cov[missing] = np.nan
    third[missing] = np.nan
    return cov, third


def fixed_to_image(fixed):
    """Fixed-point image accumulator (units 2^-40) to float32 intensities."""
    return (fixed.astype(np.float64) / float(kernels.IMAGE_SCALE)).astype(np.float32)


def _eq4_px(plan: RenderPlan, integral):
    """Eq. 4 in pixels from its integral of grad n dz: dX = -(M Z_D / n0) * integral / pitch.

    ``integral`` is ``truth_kernels.straight_ray_integrals``'s: each depth weighted by its lever arm z / Z_D
    and the ray's obliquity, which is Eq. 4's plain integral where grad n does not vary along the ray.
    """
    m, z_d = plan.camera.magnification, plan.medium.centre[2]
    return -(m * z_d / plan.medium.n0) * np.asarray(integral, dtype=np.float64) / plan.camera.pitch


def _n_samples(plan: RenderPlan, samples_per_step=1):
    return max(8, samples_per_step * plan.steps_per_ray)


def truth_medium(plan: RenderPlan, *, device=None, medium=None):
    """The medium the ground truths read: the exact float32 nodes on ``device``.

    ``medium`` (an uploaded medium, e.g. the gradient image's ``to_warp(plan.medium, field=plan.field)``)
    is reused where it holds them (``medium_kernels.Medium``, ``MediumVec``, ``MediumVec3D``); otherwise (None, or an
    approximate field) the nodes are uploaded as "float32_vec".
    """
    mk = medium_kernels
    if not isinstance(medium, (mk.Medium.instance_type, mk.MediumVec.instance_type, mk.MediumVec3D.instance_type)):
        medium = to_warp(plan.medium, device=device, field="float32_vec")
    if isinstance(medium, mk.MediumVec3D.instance_type):  # the same nodes (no copy), read as MediumVec
        m = mk.MediumVec()
        m.field, m.planar, m.half, m.inv_spacing, m.centre = (
            medium.field, medium.planar, medium.half, medium.inv_spacing, medium.centre)
        return m
    return medium


def chief_ray_truth(plan: RenderPlan, *, device=None, samples_per_step=1, medium=None):
    """Eq. 4 and the depth-averaged density along each dot's chief ray (dot centre to aperture centre).

    ``medium``: the plan's medium already on ``device`` (see :func:`truth_medium`), uploaded if None.

    Returns
    -------
    theory_px : (N, 2) float64
        Eq. 4: dX = -(M Z_D / n0) * integral of grad n dz along the chief ray, in pixels, each depth z
        weighted by its own lever arm z / Z_D and the ray's obliquity (see
        ``truth_kernels.straight_ray_integrals``): the displacement of a pinhole camera's dot in the
        weak-deflection limit, for 3-D fields too.
    density : (N,) float64
        The density averaged over the volume's depth along the chief ray, kg/m^3 (the volume's edge
        density continued where the ray passes beside the volume).
    """
    init_warp()
    medium = truth_medium(plan, device=device, medium=medium)
    cam = _camera_struct(plan.camera)
    dots = wp.array(plan.target_xy.astype(np.float32), dtype=wp.vec2, device=device)
    out = wp.zeros(plan.n_dots, dtype=wp.vec2, device=device)
    out_nm1 = wp.zeros(plan.n_dots, dtype=float, device=device)
    wp.launch(truth_kernels.truth_kernel(truth_kernels.integrate_grad_n, medium), dim=plan.n_dots,
              inputs=[medium, cam, dots, _n_samples(plan, samples_per_step)],
              outputs=[out, out_nm1], device=device)
    k = plan.medium.gladstone_dale
    return _eq4_px(plan, out.numpy()), out_nm1.numpy().astype(np.float64) / k


def cone_truth(plan: RenderPlan, *, device=None, rays_per_thread=64, samples_per_step=1, medium=None, group=8):
    """Eq. 4 and the depth-averaged density averaged over the rays the renderer traces for each dot.

    Every ray of a dot is drawn as ``kernels.render_rays`` draws it (the same seed, emission point on
    the dot and point on the aperture) and followed as the straight line of the undisturbed medium,
    the reference image's ray. The mean over those rays of Eq. 4 is what the ray-traced displacement
    tends to when deflections are weak: the camera's finite aperture averages the flow over the cone.
    Along each ray a deflection at distance z from the target counts with its own lever arm z (not
    the mid-plane's Z_D) and the ray's slope u adds -u dn/dz and the factor 1 + |u|^2 (see
    ``truth_kernels.straight_ray_integrals``); on a 3-D field (a sinusoid along (1, 0, 1), 256 x 256 px)
    Eq. 4 with one Z_D for every depth left 5.5 % RMS between traced and cone truth, the lever arms
    alone 0.9 %, both 0.11 %.
    ``medium``: the plan's medium already on ``device`` (see :func:`truth_medium`), uploaded if None.
    ``group``: consecutive threads take this many chunks of ``rays_per_thread`` rays of one dot (the
    dots in the plan's launch order), so a warp's rays read nearby nodes; it never changes a bit.

    Returns
    -------
    theory_cone_px : (N, 2) float64
        Mean over the dot's rays of Eq. 4's displacement, pixels.
    density_cone : (N,) float64
        Mean over the dot's rays of the depth-averaged density, kg/m^3.
    """
    init_warp()
    n = plan.n_dots
    medium = truth_medium(plan, device=device, medium=medium)
    cam = _camera_struct(plan.camera)
    dots = wp.array(plan.target_xy.astype(np.float32), dtype=wp.vec2, device=device)
    chunks = -(-plan.rays_per_dot // rays_per_thread)
    out = wp.zeros((chunks, n), dtype=wp.vec3, device=device)
    order = wp.array(plan.launch_order, dtype=wp.int32, device=device)
    group = max(1, min(int(group), chunks))
    wp.launch(truth_kernels.truth_kernel(truth_kernels.integrate_cone, medium), dim=-(-chunks // group) * group * n,
              inputs=[medium, cam, dots, plan.dot_radius, plan.rays_per_dot, rays_per_thread,
                      plan.cfg["rays"]["seed"], _n_samples(plan, samples_per_step), order, group],
              outputs=[out], device=device)
    sums = out.numpy().astype(np.float64).sum(axis=0) / plan.rays_per_dot  # fixed order: deterministic
    return _eq4_px(plan, sums[:, :2]), sums[:, 2] / plan.medium.gladstone_dale


def render_modules(config=None, *, device=None) -> list[str]:
    """The Warp modules :func:`render_pair` launches for ``config`` on ``device``: ``render_rays`` for the
    configuration's medium (``rays.field``) and for the reference image's, and the truths' kernels.

    Each is a module of its own (``kernels.render_module``, ``truth_kernels.truth_module``), so a campaign
    can build the ones it needs, and only those, before its work starts.

    Examples
    --------
    >>> render_modules(device="cpu")  # the defaults: float32 nodes read with 128-bit loads
    ['synthbos.raytrace.kernels.render_MediumStraight', 'synthbos.raytrace.kernels.render_MediumVec', \
'synthbos.raytrace.truth_kernels.truth_MediumVec']
    """
    cfg = load_config(config)
    rays = cfg["rays"]
    init_warp()
    on_cuda = wp.get_device(check_device(device)).is_cuda
    # whether the medium is planar picks the default field's struct and the automatic register cap; a
    # campaign asks for every pair, so a slice is not built to be told
    needs = rays["field"] == "float32_vec" or (on_cuda and rays["max_registers"] == "auto")
    planar = not needs or sources.extruded(cfg["volume"]) or medium_from_config(cfg).planar
    cap, straight_cap = ((register_cap(rays["max_registers"], active=a, planar=planar) if on_cuda else 0)
                         for a in (True, False))
    struct = medium_struct(rays["field"], planar)
    exact = rays["field"] in EXACT_FIELDS and struct in truth_kernels.TRUTH_MEDIA
    truth = struct if exact else medium_kernels.MediumVec
    straight = medium_kernels.MediumStraight
    return sorted({kernels.render_module(struct, cap), kernels.render_module(straight, straight_cap),
                   truth_kernels.truth_module(truth)})


def render_pair(config=None, *, device=None, progress=False) -> Pair:
    """Render a BOS image pair with its ground truth.

    Parameters
    ----------
    config : None, dict, str or Path
        Configuration (see ``raytrace.config``); None for the defaults.
    device : str, optional
        Warp device: "cpu" or "cuda:0"; Warp's default device if None.
    progress : bool
        Show a tqdm bar over the rays.

    Returns
    -------
    Pair
        Images (noise-free float32), dot positions and displacements (see ``raytrace.pairfile``).

    Examples
    --------
    >>> import numpy as np
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> pair.reference.shape, pair.n_dots  # a 64 x 64 px camera, 80 dots
    ((64, 64), 80)
    >>> shift = pair.gradient_px - pair.reference_px  # each dot's ray-traced displacement, px
    >>> bool(np.array_equal(shift, pair.displacement_px)), bool(np.abs(shift[pair.valid]).max() < 1.0)
    (True, True)
    """
    device = check_device(device)
    plan = config if isinstance(config, RenderPlan) else plan_render(config)
    checks.check_ray_steps(plan, device)
    init_warp()
    device_name = str(wp.get_device(device))
    total = 2 * plan.n_dots * plan.rays_per_dot
    bar = tqdm(total=total, unit="ray", unit_scale=True, desc="render", disable=not progress)
    t0 = time.perf_counter()
    with bar:
        medium = to_warp(plan.medium, device=device, field=plan.field)  # uploaded once for all three
        ref_img, ref_px, ref_ok, tir_ref, ref_cov, _ = trace_rays(plan, active=False, device=device, progress=bar)
        grad_img, grad_px, grad_ok, tir_grad, grad_cov, grad_third = trace_rays(
            plan, active=True, device=device, progress=bar, medium=medium
        )
        medium = truth_medium(plan, device=device, medium=medium)
        theory, density_chief = chief_ray_truth(plan, device=device, medium=medium)
        theory_cone, density_cone = cone_truth(plan, device=device, medium=medium)
        wp.synchronize_device(device)
    seconds = time.perf_counter() - t0
    if tir_ref + tir_grad:
        raise SynthbosError(
            f"{tir_ref + tir_grad} rays met total internal reflection in the thick lens; "
            "reduce the aperture (camera.f_number) or the field of view"
        )
    if not (np.isfinite(ref_img).all() and np.isfinite(grad_img).all()) or not ref_img.max() > 0:
        raise SynthbosError("the render deposited no light or non-finite intensities; check sensor.peak_intensity")
    # A dot is valid only where every number of its ground truth is finite.
    finite = np.all(np.isfinite(theory), axis=1) & np.all(np.isfinite(grad_px - ref_px), axis=1)
    attrs = {
        "config": config_to_toml(plan.cfg),
        "magnification": plan.camera.magnification,
        "version": synthbos.__version__,
        "device": device_name,
        "render_seconds": seconds,
        "n0": plan.medium.n0,
        "spot_diameter_px": plan.spot_diameter_px,
        "rays_per_dot": plan.rays_per_dot,
        "steps_per_ray": plan.steps_per_ray,
        "z_d_m": plan.medium.centre[2],
        "pixel_pitch_m": plan.camera.pitch,
        "peak_intensity": plan.cfg["sensor"]["peak_intensity"],
        "z_stop_m": plan.camera.z_stop,
        "principal_point_x_px": float(plan.camera.principal_point[0]),
        "principal_point_y_px": float(plan.camera.principal_point[1]),
        "volume_depth_m": float(plan.medium.size[2]),
        "volume_centre_x_m": float(plan.medium.centre[0]),
        "volume_centre_y_m": float(plan.medium.centre[1]),
        "gladstone_dale_m3_per_kg": plan.medium.gladstone_dale,
        "ambient_density_kg_m3": float(plan.medium.density.ambient),
    }
    return Pair(
        reference=ref_img, gradient=grad_img, target_xy_m=plan.target_xy, reference_px=ref_px,
        gradient_px=grad_px, displacement_px=grad_px - ref_px, theory_px=theory,
        valid=ref_ok & grad_ok & finite, theory_cone_px=theory_cone, density_cone_kg_m3=density_cone,
        density_chief_kg_m3=density_chief, ray_covariance_px2=grad_cov, ray_covariance_reference_px2=ref_cov,
        ray_third_moment_px3=grad_third, attrs=attrs,
    )
