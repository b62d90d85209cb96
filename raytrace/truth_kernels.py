"""Warp kernels of the renderer's ground truths: Eq. 4's integral along straight lines through the
medium, per chief ray (``integrate_grad_n``) and summed over the rays the renderer traces for a dot
(``integrate_cone``); host code in ``raytrace.render`` (``chief_ray_truth``, ``cone_truth``).

They read the medium through the renderer's own ``sample_medium`` overloads and draw each ray's points
as ``render_rays`` does (``sample_disk``, ``group_member``), from :mod:`raytrace.kernels`.
"""

from typing import Any

import warp as wp

from .kernels import Camera, group_member, sample_disk
from .medium_kernels import Medium, MediumVec, sample_medium

wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile


@wp.func
def straight_ray_integrals(m: Any, origin: wp.vec3, aim: wp.vec3, n_samples: int):
    """Along the straight line from ``origin`` towards ``aim``, through the depth of the box (midpoint
    rule in z): Eq. 4's integral with each depth weighted by its own geometry, and the depth average
    of n - 1.

    The first is ``(1 + |u|^2) / Z_D * integral of z (grad_xy n - u dn/dz) dz`` (Z_D the box centre's
    distance from the target, u = t_xy / t_z the line's slope): in the weak-deflection limit the ray's
    apparent origin on the target moves by -(1 / n0) times the integral of z (grad_xy n - u dn/dz) /
    t_z^2 dz (a deflection at distance z from the target moves it by z times the change of slope, and
    d u / dz = (grad_xy n - u dn/dz) / (n t_z^2) by Fermat's equation), so that ``-(M Z_D / n0)`` times
    it is the image displacement. Where grad n does not vary along the line (a linear field) and the
    line is axial, this is Eq. 4's integral of (dn/dx, dn/dy) dz exactly; through an extruded slice it
    differs only by the line's lateral travel across the depth and the obliquity factor 1 + |u|^2.

    Where the line passes beside the box, n - 1 is read at the nearest point of the box's side (the
    volume's edge density continued outwards): the renderer sees no gradient there, so no jump either.
    Inside the box that point is the sample itself, which is read once.
    """
    t = wp.normalize(aim - origin)
    u = wp.vec2(t[0] / t[2], t[1] / t[2])
    z0 = m.centre[2] - m.half[2]
    dz = 2.0 * m.half[2] / float(n_samples)
    acc = wp.vec2(0.0)
    nm1 = wp.float32(0.0)  # a dynamic variable: it changes inside the loop
    for k in range(n_samples):
        z = z0 + (float(k) + 0.5) * dz
        p = origin + ((z - origin[2]) / t[2]) * t - m.centre
        s = sample_medium(m, p)
        acc = acc + (wp.vec2(s[0], s[1]) - u * s[2]) * (z * dz)
        edge = wp.vec3(wp.clamp(p[0], -m.half[0], m.half[0]), wp.clamp(p[1], -m.half[1], m.half[1]), p[2])
        if edge[0] == p[0] and edge[1] == p[1]:
            nm1 = nm1 + s[3]
        else:
            nm1 = nm1 + sample_medium(m, edge)[3]
    return acc * ((1.0 + wp.dot(u, u)) / m.centre[2]), nm1 / float(n_samples)


@wp.kernel
def integrate_grad_n(
    medium: Any,
    cam: Camera,
    dots: wp.array(dtype=wp.vec2),
    n_samples: int,
    out: wp.array(dtype=wp.vec2),
    out_nm1: wp.array(dtype=float),
):
    """Along the straight chief ray from each dot to the centre of the aperture: Eq. 4's integral of
    grad n dz, each depth weighted by its geometry, and the depth-averaged n - 1 (see
    ``straight_ray_integrals``)."""
    i = wp.tid()
    origin = wp.vec3(dots[i][0], dots[i][1], 0.0)
    acc, nm1 = straight_ray_integrals(medium, origin, wp.vec3(0.0, 0.0, cam.z_stop), n_samples)
    out[i] = acc
    out_nm1[i] = nm1


@wp.kernel
def integrate_cone(
    medium: Any,
    cam: Camera,
    dots: wp.array(dtype=wp.vec2),
    dot_radius: float,
    rays_per_dot: int,
    rays_per_thread: int,
    seed: int,
    n_samples: int,
    launch_order: wp.array(dtype=wp.int32),
    group: int,
    out: wp.array2d(dtype=wp.vec3),
):
    """Eq. 4's integral and the depth-averaged n - 1 summed over the rays the renderer traces for a dot.

    The rays of a dot are cut into chunks of ``rays_per_thread`` (chunk c: rays ``c * rays_per_thread
    ...``), one thread per chunk, in groups of ``group`` consecutive chunks of one dot: thread ``tid`` is
    in group ``g = tid // group``, which takes dot ``launch_order[g % n_dots]`` and chunks
    ``(g // n_dots) * group ...`` (threads past the last chunk do nothing), as ``render_rays`` groups
    rays. Each ray draws its emission point and aperture point exactly as ``render_rays`` does (same
    seed, same (dot, ray) stream), and is followed as the straight line of the undisturbed medium.
    ``out[c, dot]`` = (sum of integral dn/dx dz, sum of integral dn/dy dz, sum of depth-mean n - 1) over
    the chunk's rays, in ray order. The order and the group only decide which thread does which sum (a
    warp's threads follow rays of few dots, which read nearby nodes), never a bit of a sum.
    """
    n_dots = dots.shape[0]
    slot, c = group_member(wp.tid(), group, n_dots)
    r0 = c * rays_per_thread
    if r0 >= rays_per_dot:
        return
    dot = launch_order[slot]
    acc = wp.vec3(0.0)
    r1 = wp.min(r0 + rays_per_thread, rays_per_dot)
    for ray in range(r0, r1):
        state = wp.rand_init(seed, ray * n_dots + dot)
        e2 = dots[dot] + sample_disk(state, dot_radius)
        a2 = sample_disk(state, cam.aperture_radius)
        origin = wp.vec3(e2[0], e2[1], 0.0)
        g2, nm1 = straight_ray_integrals(medium, origin, wp.vec3(a2[0], a2[1], cam.z_stop), n_samples)
        acc = acc + wp.vec3(g2[0], g2[1], nm1)
    out[c, dot] = acc



# The truths read the exact float32 nodes, packed (``Medium``) or with 128-bit loads (``MediumVec``): their
# two kernels per medium in a Warp module of their own (``truth_module``), as ``render_rays``. This
# module's own overloads serve the tests.
TRUTH_MEDIA = (Medium, MediumVec)


def truth_module(medium: type) -> str:
    """The name of the Warp module that holds the truths' kernels for the struct ``medium``."""
    return f"{__name__}.truth_{medium.__name__}"


_TRUTH = {}
for _medium in TRUTH_MEDIA:
    wp.set_module_options({"enable_backward": False}, module=truth_module(_medium))
    for _kernel in (integrate_grad_n, integrate_cone):
        _TRUTH[_kernel.key, _medium] = wp.kernel(
            _kernel.func, name=f"{_kernel.key}_{_medium.__name__}", module=truth_module(_medium),
            enable_backward=False,
        )
        wp.overload(_TRUTH[_kernel.key, _medium], {"medium": _medium})
    wp.overload(integrate_grad_n, {"medium": _medium})
    wp.overload(integrate_cone, {"medium": _medium})


def truth_kernel(kernel, medium):
    """``kernel`` (``integrate_grad_n`` or ``integrate_cone``) for ``medium`` (one of the structs of
    ``TRUTH_MEDIA``, or an instance of one), in its medium's module."""
    struct = next(m for m in TRUTH_MEDIA if medium is m or isinstance(medium, m.instance_type))
    return _TRUTH[kernel.key, struct]
