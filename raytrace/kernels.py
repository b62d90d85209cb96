"""Warp kernels of the renderer: small typed functions, one job each.

Frames and units: metres; the target plane is z = 0 and the optical axis is +z. Inside the volume
rays are traced in the volume's local frame (origin at its centre) so that float32 keeps its
precision. Host code that allocates, launches and copies lives in ``raytrace.render``.

Ray equation. Fermat's equation d/ds (n dx/ds) = grad n is integrated for the position ``x`` and the
unit tangent ``t``: ``dx/ds = t``, ``dt/ds = (grad n - (t . grad n) t) / n`` (the same equation with
d/ds(n t) expanded), by classical 4th-order Runge-Kutta with the tangent renormalised after each step.
Where grad n vanishes the tangent never changes, so a uniform medium gives bit-identical rays to the
reference trace, whatever its density.

Media. ``render_rays`` is generic over the struct that holds the medium; the structs and how a ray's
stages read them live in ``raytrace.medium_kernels``.
"""

from typing import Any

import warp as wp

from synthbos.device import quiet_warp

from .medium_kernels import (
    Medium,
    MediumHalf,
    MediumHalfNodes,
    MediumStraight,
    MediumTexels,
    MediumTexture,
    MediumVec,
    MediumVec3D,
    node_coords,
    read_by_cell,
    sample_medium,
    step_medium,
)

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile

LENS_THIN = wp.constant(0)
LENS_THICK = wp.constant(1)

# Images and per-dot sums are accumulated in fixed point with integer atomics, so that the result does
# not depend on the order in which threads add (float atomics would make GPU renders differ in the last
# bits from run to run): intensities in units of 2^-40, positions in units of 2^-32 px.
IMAGE_SCALE = wp.constant(1099511627776.0)  # 2^40
POSITION_SCALE = wp.constant(4294967296.0)  # 2^32
# The sums of the products of a ray's offset from its dot's nominal position (second and third powers)
# take a scale per render (``raytrace.render.moment_scales``): a ray summed in them lies within
# MOMENT_RANGE_PX of the nominal position on both axes (a dot with a ray beyond has no moments).
MOMENT_RANGE_PX = wp.constant(256.0)

RAY_OK = wp.constant(0)
RAY_MISSED_LENS = wp.constant(1)
RAY_TIR = wp.constant(2)


@wp.struct
class Camera:
    lens: int  # LENS_THIN or LENS_THICK
    z_stop: float  # plane of the aperture stop (thin lens plane, or thick lens front vertex)
    aperture_radius: float
    focal_length: float  # thin lens
    z_sensor: float
    # thick lens: two spherical surfaces of radius r1 (front, centre c1) and r2 (back, centre c2)
    c1: float
    r1: float
    c2: float
    r2: float
    glass_index: float
    semi_diameter: float


@wp.struct
class Sensor:
    width: int
    height: int
    pitch: float
    cx: float  # pixel coordinates of the optical axis
    cy: float
    sigma_px: float  # Gaussian spot standard deviation (pixels)
    half_width: int  # deposit window half width (pixels)
    energy: float  # integrated intensity one ray deposits


@wp.func
def tangent_rate(m: Any, active: int, x: wp.vec3, t: wp.vec3):
    """dt/ds of Fermat's equation at local point x with unit tangent t."""
    if active == 0:
        return wp.vec3(0.0)
    s = sample_medium(m, x)
    g = wp.vec3(s[0], s[1], s[2])
    return (g - wp.dot(t, g) * t) / (1.0 + s[3])


@wp.func
def in_box(m: Any, p: wp.vec3, clamp: int):
    """``p`` itself, or with ``clamp = 1`` its x and y clamped into the box's sides."""
    if clamp == 0:
        return p
    return wp.vec3(wp.clamp(p[0], -m.half[0], m.half[0]), wp.clamp(p[1], -m.half[1], m.half[1]), p[2])


@wp.func
def rk4_step(m: Any, active: int, x: wp.vec3, t: wp.vec3, h: float, clamp: int):
    """One classical Runge-Kutta step of length h for (x, t); returns the new position and tangent.

    ``clamp = 1`` (a step known to stay inside the box, up to the ray's bending within it) reads the
    field at the stages' points clamped into the box's sides, where the field stops.
    """
    k1t = tangent_rate(m, active, x, t)
    t2 = t + 0.5 * h * k1t
    k2t = tangent_rate(m, active, in_box(m, x + 0.5 * h * t, clamp), t2)
    t3 = t + 0.5 * h * k2t
    k3t = tangent_rate(m, active, in_box(m, x + 0.5 * h * t2, clamp), t3)
    t4 = t + h * k3t
    k4t = tangent_rate(m, active, in_box(m, x + h * t3, clamp), t4)
    x_new = x + (h / 6.0) * (t + 2.0 * t2 + 2.0 * t3 + t4)
    t_new = wp.normalize(t + (h / 6.0) * (k1t + 2.0 * k2t + 2.0 * k3t + k4t))
    return x_new, t_new


@wp.func
def n_steps(m: Any, t: wp.vec3, step: float):
    """Number of equal RK4 steps that carry a straight ray of tangent t through the box's depth."""
    length = 2.0 * m.half[2] / t[2]
    return wp.max(int(wp.ceil(length / step - 1.0e-4)), 1)


@wp.func
def face_distance(f: float, rate: float):
    """Path length to the next node plane ahead along one axis.

    ``f`` is the fractional node coordinate, ``rate`` its change per unit path length. A plane within
    1e-4 node ahead counts as crossed (the step goes on to the next one), so a step never has length ~0.
    """
    if rate > 0.0:
        return (wp.floor(f + 1.0e-4) + 1.0 - f) / rate
    if rate < 0.0:
        return (wp.ceil(f - 1.0e-4) - 1.0 - f) / rate
    return 1.0e30


@wp.func
def trace_volume(m: Any, active: int, x_global: wp.vec3, t: wp.vec3, step: float, cells: int):
    """Carry a ray from anywhere in front of the box to its back face.

    Straight to the front face plane, then RK4 across the whole depth of the box (rays never stop
    early at a face; outside the box's sides the gradient is zero and the ray runs straight). Returns
    global position, tangent.

    ``cells = 0``: equal steps of at most ``step`` that end exactly on the back face plane for a
    straight ray. ``cells = 1``: each step ends at the next node plane the ray crosses (along x, y or
    z), at the back face plane, or after ``step``, whichever comes first. Inside one cell the
    interpolated field is a smooth polynomial, which RK4 integrates to high order with long steps; a
    step across a node plane, where the field's derivatives jump, would cost RK4 its order (and at the
    box's sides, where the field itself stops, its convergence: equal steps err by O(step) there). A
    step beside the box is a straight line. Fewer steps also mean less float32 rounding: on the
    paper's flow, against a float64 trace with steps of an eighth of the grid, equal grid steps leave
    up to 1.4e-4 px (as the exit angle's image) and 4e-4 px of exit position, cell steps of at most a
    quarter of the depth 1.5e-5 and 2e-5 px. The undisturbed medium's straight rays (``active = 0``)
    take the same steps, so a uniform medium gives the reference image's bits.
    """
    z_front = m.centre[2] - m.half[2]
    s0 = (z_front - x_global[2]) / t[2]
    x = x_global + s0 * t - m.centre
    tt = t
    if cells == 0:
        n = n_steps(m, t, step)
        h = 2.0 * m.half[2] / t[2] / float(n)
        for _ in range(n):
            x, tt = rk4_step(m, active, x, tt, h, 0)
        return x + m.centre, tt
    depth = 2.0 * m.half[2]
    # A ray crosses each node plane once at most; the bound only guards against a runaway loop.
    limit = int(depth / step) + 2 * int(depth * (m.inv_spacing[0] + m.inv_spacing[1] + m.inv_spacing[2])) + 16
    k = int(0)  # noqa: UP018, RUF046 (a dynamic Warp variable, changed in the loop)
    while k < limit:
        remaining = (m.half[2] - x[2]) / tt[2]
        if remaining <= 1.0e-5 * depth:
            break
        f = node_coords(m.half, m.inv_spacing, x)
        h = wp.min(face_distance(f[0], tt[0] * m.inv_spacing[0]), face_distance(f[1], tt[1] * m.inv_spacing[1]))
        h = wp.min(wp.min(h, face_distance(f[2], tt[2] * m.inv_spacing[2])), wp.min(remaining, step))
        mid = x + (0.5 * h) * tt
        if wp.abs(mid[0]) > m.half[0] or wp.abs(mid[1]) > m.half[1]:
            # Beside the box (its start may lie on the box's side, where a sample would read the edge
            # nodes): no field, a straight line.
            x = x + h * tt
        elif read_by_cell(m) != 0:  # inside, in one cell of a 3-D field: its nodes read once for the stages
            x, tt = rk4_step(step_medium(m, mid), active, x, tt, h, 1)
        else:  # inside: the stages' points stay in the box, though the ray bends across its side a hair
            x, tt = rk4_step(m, active, x, tt, h, 1)
        k += 1
    return x + m.centre, tt


@wp.func
def aimed_ray(
    m: Any, active: int, cam: Camera, origin: wp.vec3, stop_point: wp.vec3, step: float, cells: int, iterations: int
):
    """Trace a ray from ``origin`` through the volume so that it crosses the stop plane at ``stop_point``.

    The first ray is aimed straight at the stop point; each iteration then re-aims it by the amount the
    refracted ray missed (ray aiming, as in lens design), so the rays that pass the stop sample it
    uniformly whatever the flow does to them. Returns the ray at the back face: position and tangent.
    """
    aim = stop_point
    t = wp.normalize(aim - origin)
    p, tt = trace_volume(m, active, origin, t, step, cells)
    for _ in range(iterations):
        s = (cam.z_stop - p[2]) / tt[2]
        miss = p + s * tt - stop_point
        aim = aim - wp.vec3(miss[0], miss[1], 0.0)
        t = wp.normalize(aim - origin)
        p, tt = trace_volume(m, active, origin, t, step, cells)
    return p, tt


@wp.func
def refract(t: wp.vec3, normal: wp.vec3, eta: float):
    """Vector Snell's law: unit tangent t crossing a surface with unit normal (against t), eta = n1/n2.

    Returns the refracted tangent and a flag that is 1 on total internal reflection (tangent then 0).
    """
    cos_i = -wp.dot(normal, t)
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    if sin2_t > 1.0:
        return wp.vec3(0.0), 1
    return wp.normalize(eta * t + (eta * cos_i - wp.sqrt(1.0 - sin2_t)) * normal), 0


@wp.func
def sphere_hit(p: wp.vec3, t: wp.vec3, zc: float, r: float, far: int):
    """Distance along the ray p + s t to the sphere of radius r centred on the axis at z = zc.

    ``far`` picks the second intersection. Returns -1 when the ray misses the sphere.
    """
    oc = p - wp.vec3(0.0, 0.0, zc)
    b = wp.dot(oc, t)
    c = wp.dot(oc, oc) - r * r
    disc = b * b - c
    if disc < 0.0:
        return -1.0
    q = wp.sqrt(disc)
    if far == 1:
        return -b + q
    return -b - q


@wp.func
def thin_lens_to_sensor(cam: Camera, p: wp.vec3, t: wp.vec3):
    """Ideal thin lens at z_stop (exact imaging in slope form: u' = u - x / f); sensor (x, y) in metres."""
    s = (cam.z_stop - p[2]) / t[2]
    xl = p + s * t
    ux = t[0] / t[2] - xl[0] / cam.focal_length
    uy = t[1] / t[2] - xl[1] / cam.focal_length
    dz = cam.z_sensor - cam.z_stop
    return wp.vec2(xl[0] + dz * ux, xl[1] + dz * uy), RAY_OK


@wp.func
def thick_lens_to_sensor(cam: Camera, p: wp.vec3, t: wp.vec3):
    """Biconvex spherical lens: refraction at both surfaces by Snell's law; sensor (x, y) in metres."""
    s1 = sphere_hit(p, t, cam.c1, cam.r1, 0)
    if s1 < 0.0:
        return wp.vec2(0.0), RAY_MISSED_LENS
    h1 = p + s1 * t
    if h1[0] * h1[0] + h1[1] * h1[1] > cam.semi_diameter * cam.semi_diameter:
        return wp.vec2(0.0), RAY_MISSED_LENS
    n1 = wp.normalize(h1 - wp.vec3(0.0, 0.0, cam.c1))  # outward normal points back towards the target
    t1, tir1 = refract(t, n1, 1.0 / cam.glass_index)
    if tir1 == 1:
        return wp.vec2(0.0), RAY_TIR
    s2 = sphere_hit(h1, t1, cam.c2, cam.r2, 1)
    if s2 < 0.0:
        return wp.vec2(0.0), RAY_MISSED_LENS
    h2 = h1 + s2 * t1
    if h2[0] * h2[0] + h2[1] * h2[1] > cam.semi_diameter * cam.semi_diameter:
        return wp.vec2(0.0), RAY_MISSED_LENS
    n2 = -wp.normalize(h2 - wp.vec3(0.0, 0.0, cam.c2))
    t2, tir2 = refract(t1, n2, cam.glass_index)
    if tir2 == 1:
        return wp.vec2(0.0), RAY_TIR
    s3 = (cam.z_sensor - h2[2]) / t2[2]
    return wp.vec2(h2[0] + s3 * t2[0], h2[1] + s3 * t2[1]), RAY_OK


@wp.func
def sensor_to_pixel(sen: Sensor, xs: wp.vec2):
    """Sensor metres to upright pixel coordinates (x = column, y = row, pixel centres at integers).

    The lens forms an inverted image; the pixel frame is flipped so that columns grow with target x
    and rows with target y.
    """
    return wp.vec2(sen.cx - xs[0] / sen.pitch, sen.cy - xs[1] / sen.pitch)


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return 0;
#else
return 1;
#endif
""")
def compiled_for_cpu() -> int:
    """1 in code compiled for the CPU, 0 on CUDA: a constant to each compiler, which drops the other branch."""
    ...


# The widest deposit window (2 half_width + 1 px) whose column weights the CPU keeps in an array: the largest
# spot a configuration allows (``checks.MAX_SPOT_PX``, half width 48 px); a wider one takes the plain loop.
DEPOSIT_WINDOW = wp.constant(97)


@wp.func
def deposit_gaussian(image: wp.array2d(dtype=wp.int64), sen: Sensor, px: wp.vec2, energy: float, turn: int):
    """Add a Gaussian spot of total ``energy`` centred at pixel coordinates px, integrated over each
    pixel with erf, into the fixed-point ``image`` (units of 1 / IMAGE_SCALE) with atomics: each pixel
    adds floor(energy * fx * fy * IMAGE_SCALE + 0.5), fx and fy half the difference of erf at its column's
    and row's edges. The CPU's ``deposit_gaussian_cached`` computes the same numbers with 16 erf calls
    instead of 112 (7 x 7 px); CUDA, where its array would live in local memory, keeps the plain loop,
    each row's columns from the ``turn``-th on (see ``deposit_gaussian_tiled``)."""
    if compiled_for_cpu() != 0 and 2 * sen.half_width + 1 <= DEPOSIT_WINDOW:
        deposit_gaussian_cached(image, sen, px, energy)
    else:
        deposit_gaussian_plain(image, sen, px, energy, turn)


@wp.func
def deposit_gaussian_plain(image: wp.array2d(dtype=wp.int64), sen: Sensor, px: wp.vec2, energy: float, turn: int):
    """``deposit_gaussian`` pixel by pixel (two erf calls for each pixel's fx, two for each row's fy), every
    pixel into the image: ``deposit_gaussian_tiled`` without a tile."""
    deposit_gaussian_tiled(image, sen, px, energy, 0, wp.vec2i(0, 0), 0, turn)


@wp.func
def deposit_gaussian_cached(image: wp.array2d(dtype=wp.int64), sen: Sensor, px: wp.vec2, energy: float):
    """``deposit_gaussian_plain``'s numbers, bit for bit (windows of at most DEPOSIT_WINDOW px a side): each
    column's ``energy * fx`` once a spot, not once a row, and each pixel edge's erf once (pixel i's upper
    edge float(i) + 0.5 is pixel i + 1's lower edge float(i + 1) - 0.5, both exact); the same products and
    roundings in the same order."""
    c0 = int(wp.round(px[0]))
    r0 = int(wp.round(px[1]))
    inv = 1.0 / (wp.sqrt(2.0) * sen.sigma_px)
    hw = sen.half_width
    efx = wp.zeros(shape=DEPOSIT_WINDOW, dtype=float)  # energy * fx of column c0 + dc at dc + hw
    lower = wp.float32(0.0)  # erf at the lower edge of the next pixel (a dynamic variable)
    started = int(0)  # noqa: UP018, RUF046 (a dynamic variable: it changes inside the loop)
    for dc in range(-hw, hw + 1):
        col = c0 + dc
        if col >= 0 and col < sen.width:
            if started == 0:  # the window's first column on the image
                lower = wp.erf((float(col) - 0.5 - px[0]) * inv)
                started = 1
            upper = wp.erf((float(col) + 0.5 - px[0]) * inv)
            efx[dc + hw] = energy * (0.5 * (upper - lower))
            lower = upper
    started_rows = int(0)  # noqa: UP018, RUF046 (a dynamic variable: it changes inside the loop)
    for dr in range(-hw, hw + 1):
        row = r0 + dr
        if row >= 0 and row < sen.height:
            if started_rows == 0:  # the window's first row on the image
                lower = wp.erf((float(row) - 0.5 - px[1]) * inv)
                started_rows = 1
            upper = wp.erf((float(row) + 0.5 - px[1]) * inv)
            fy = 0.5 * (upper - lower)
            lower = upper
            for dc in range(-hw, hw + 1):
                col = c0 + dc
                if col >= 0 and col < sen.width:
                    wp.atomic_add(image, row, col, wp.int64(wp.floor(efx[dc + hw] * fy * IMAGE_SCALE + 0.5)))


@wp.func
def sample_disk(state: wp.uint32, radius: float):
    """Area-uniform point on a disk of the given radius: r = R sqrt(U), phi = 2 pi U'."""
    r = radius * wp.sqrt(wp.randf(state))
    phi = 2.0 * wp.pi * wp.randf(state)
    return wp.vec2(r * wp.cos(phi), r * wp.sin(phi))


@wp.func
def group_member(tid: int, group: int, n_dots: int):
    """Thread ``tid``'s place when groups of ``group`` consecutive threads each work on one dot, the groups
    taking the dots in launch order, over and over: the dot's position in the launch order and the thread's
    index among all the threads of that dot (its ray, or its chunk of rays)."""
    g = tid / group
    block = g / n_dots
    return g - block * n_dots, block * group + (tid - g * group)


#: The int64 cells of a CUDA block's spot tiles in shared memory (32 KB): ``render_rays`` with ``tile_side > 0``
#: sums its block's spots there and adds each cell to the image once (``spot_tiles``).
SPOT_CELLS = 4096
#: The widest spot tile (cells a side) a group of threads gets, however few groups share the block.
SPOT_SIDE_MAX = 24
SPOT_ADD = wp.constant(0)
SPOT_READ = wp.constant(1)
SPOT_CLEAR = wp.constant(2)
SPOT_SYNC = wp.constant(3)


@wp.func_native(f"""
#if defined(__CUDA_ARCH__)
__shared__ long long spot_cells[{SPOT_CELLS}];
if (op == {SPOT_ADD}) {{
    atomicAdd((unsigned long long*)&spot_cells[idx], (unsigned long long)value);
    return 0;
}}
if (op == {SPOT_READ}) return spot_cells[idx];
if (op == {SPOT_CLEAR}) {{
    spot_cells[idx] = 0;
    return 0;
}}
__syncthreads();
return 0;
#else
return 0;
#endif
""")
def spot_cell(op: int, idx: int, value: wp.int64) -> wp.int64:
    """The block's shared spot cells on CUDA (one static array for every call): ``SPOT_ADD`` adds ``value``
    to cell ``idx`` (an atomic in shared memory), ``SPOT_READ`` returns it, ``SPOT_CLEAR`` sets it to 0,
    ``SPOT_SYNC`` waits for every thread of the block (every thread must call it). 0 on the CPU."""
    ...


@wp.func
def spot_tile_corner(nominal: wp.vec2, side: int) -> wp.vec2i:
    """The (column, row) of the first cell of a dot's spot tile: ``side`` cells a side centred on the
    pixel nearest its nominal position."""
    half = side / 2
    return wp.vec2i(int(wp.round(nominal[0])) - half, int(wp.round(nominal[1])) - half)


@wp.func
def deposit_gaussian_tiled(
    image: wp.array2d(dtype=wp.int64), sen: Sensor, px: wp.vec2, energy: float, base: int, corner: wp.vec2i,
    side: int, turn: int,
):
    """``deposit_gaussian_plain``'s numbers, each pixel's into its cell of the thread's spot tile in shared
    memory (``side`` x ``side`` cells from cell ``base``, its first at pixel ``corner``) where it falls in
    the tile, else into the image. Each row's columns are taken from the ``turn``-th on (modulo the
    window), so that the threads of a group, whose spots share cells, add to different cells at a time
    (atomics on one address from a warp's threads run one after another)."""
    c0 = int(wp.round(px[0]))
    r0 = int(wp.round(px[1]))
    inv = 1.0 / (wp.sqrt(2.0) * sen.sigma_px)
    hw = sen.half_width
    n = 2 * hw + 1
    for dr in range(-hw, hw + 1):
        row = r0 + dr
        if row >= 0 and row < sen.height:
            fy = 0.5 * (wp.erf((float(row) + 0.5 - px[1]) * inv) - wp.erf((float(row) - 0.5 - px[1]) * inv))
            tr = row - corner[1]
            for k in range(n):
                col = c0 + (k + turn) % n - hw
                if col >= 0 and col < sen.width:
                    fx = 0.5 * (wp.erf((float(col) + 0.5 - px[0]) * inv) - wp.erf((float(col) - 0.5 - px[0]) * inv))
                    v = wp.int64(wp.floor(energy * fx * fy * IMAGE_SCALE + 0.5))
                    tc = col - corner[0]
                    if tr >= 0 and tr < side and tc >= 0 and tc < side:
                        spot_cell(SPOT_ADD, base + tr * side + tc, v)
                    else:
                        wp.atomic_add(image, row, col, v)


@wp.func
def flush_spot_tiles(
    image: wp.array2d(dtype=wp.int64), nominal_px: wp.array(dtype=wp.vec2), launch_order: wp.array(dtype=wp.int32),
    tid: int, lane: int, block_dim: int, group: int, side: int,
):
    """Add every non-zero cell of the block's spot tiles to the image (after ``SPOT_SYNC``): the block's
    threads take the cells in turn; tile ``s`` is that of the block's group ``s``, whose dot gives its
    corner. Only pixels on the image were summed into a cell."""
    n_dots = launch_order.shape[0]
    area = side * side
    first = tid - lane
    for k in range(lane, (block_dim / group) * area, block_dim):
        v = spot_cell(SPOT_READ, k, wp.int64(0))
        if v != wp.int64(0):
            s = k / area
            cell = k - s * area
            slot, _ = group_member(first + s * group, group, n_dots)
            corner = spot_tile_corner(nominal_px[launch_order[slot]], side)
            wp.atomic_add(image, corner[1] + cell / side, corner[0] + cell - (cell / side) * side, v)


@wp.func
def fixed(value: wp.float64, scale: wp.float64):
    """``value`` in fixed point: the nearest integer to value * scale."""
    return wp.int64(wp.floor(value * scale + wp.float64(0.5)))


#: A ray's seven fixed-point products [xx, yy, xy, xxx, xxy, xyy, yyy] (see ``moment_terms``).
vec7l = wp.types.vector(length=7, dtype=wp.int64)


@wp.func
def moment_terms(d: wp.vec2, scale2: wp.float64, scale3: wp.float64):
    """A ray's offset ``d`` (px, from its dot's nominal position) as its products in fixed point:
    xx, yy, xy in units of 1 / scale2, then xxx, xxy, xyy, yyy in units of 1 / scale3, formed in
    float64 from the float32 offset (the values ``sum_x``, ``sum_y`` hold). Returns the products and
    0, or zeros and 1 for an offset beyond MOMENT_RANGE_PX (its powers could overflow the sums; it
    counts in ``far`` instead)."""
    if wp.abs(d[0]) > MOMENT_RANGE_PX or wp.abs(d[1]) > MOMENT_RANGE_PX:
        return vec7l(), 1
    x = wp.float64(d[0])
    y = wp.float64(d[1])
    xx = x * x
    yy = y * y
    xy = x * y
    terms = vec7l(fixed(xx, scale2), fixed(yy, scale2), fixed(xy, scale2), fixed(xx * x, scale3),
                  fixed(xx * y, scale3), fixed(xy * y, scale3), fixed(yy * y, scale3))
    return terms, 0


@wp.func
def trace_one_ray(
    medium: Any, active: int, cam: Camera, dots: wp.array(dtype=wp.vec2), dot: int, ray: int, n_dots: int,
    dot_radius: float, step: float, cells: int, aim_iterations: int, seed: int,
):
    """Ray ``ray`` of dot ``dot``: emitted from a point of the dot towards a point of the aperture (both
    drawn from the (seed, dot, ray) stream alone), traced through the medium and the lens to the sensor.
    Returns its sensor position and status (RAY_OK, or why it was lost)."""
    state = wp.rand_init(seed, ray * n_dots + dot)
    e2 = dots[dot] + sample_disk(state, dot_radius)
    a2 = sample_disk(state, cam.aperture_radius)
    origin = wp.vec3(e2[0], e2[1], 0.0)
    p, t = aimed_ray(medium, active, cam, origin, wp.vec3(a2[0], a2[1], cam.z_stop), step, cells, aim_iterations)
    xs = wp.vec2(0.0)
    status = RAY_OK
    if cam.lens == LENS_THIN:
        xs, status = thin_lens_to_sensor(cam, p, t)
    else:
        xs, status = thick_lens_to_sensor(cam, p, t)
    return xs, status


@wp.kernel
def render_rays(
    medium: Any,
    active: int,
    cam: Camera,
    sen: Sensor,
    dots: wp.array(dtype=wp.vec2),
    nominal_px: wp.array(dtype=wp.vec2),
    launch_order: wp.array(dtype=wp.int32),
    dot_radius: float,
    step: float,
    cells: int,
    aim_iterations: int,
    seed: int,
    ray_start: int,
    ray_count: int,
    group: int,
    rays_per_thread: int,
    scale2: wp.float64,
    scale3: wp.float64,
    block_dim: int,
    tile_side: int,
    image: wp.array2d(dtype=wp.int64),
    sum_x: wp.array(dtype=wp.int64),
    sum_y: wp.array(dtype=wp.int64),
    sums: wp.array2d(dtype=wp.int64),
    far: wp.array(dtype=wp.int32),
    hits: wp.array(dtype=wp.int32),
    lost: wp.array(dtype=wp.int32),
    tir: wp.array(dtype=wp.int32),
):
    """A thread per ``rays_per_thread`` consecutive rays of one dot: emit, trace, image, deposit, accumulate.

    Rays ``ray_start .. ray_start + ray_count - 1`` of every dot are cut into chunks of ``rays_per_thread``;
    consecutive threads take ``group`` chunks of one dot: thread ``tid`` is in group ``g = tid // group``,
    which takes dot ``launch_order[g % n_dots]`` and chunks ``(g // n_dots) * group ...`` (threads past
    ``ray_count`` do nothing). ``group = 1`` with the identity order is one chunk of each dot in turn; a
    spatial ``launch_order`` and a larger group make a warp's rays read nearby nodes. Each spot goes into
    the image as its ray lands; a thread sums its rays' per-dot counts and moments and adds them to the
    dot's sums once (one atomic per sum and chunk instead of per ray: the dot's rays all add to the same
    addresses). Neither the order nor the chunks change anything else: a ray's random numbers depend only
    on (seed, dot, ray), and the images and sums are accumulated in fixed point, so every order gives
    the same bits.

    On CUDA with ``tile_side > 0`` (``spot_tile_side``; launched in whole blocks of ``block_dim`` threads,
    a multiple of ``group``), each group's spots are summed in a ``tile_side``-square tile of the block's
    shared memory centred on its dot's nominal pixel, and each tile's cells are added to the image once at
    the end (``flush_spot_tiles``): a few atomics in the image per dot and block instead of one per pixel
    of every spot. Pixels off the tile go to the image directly. The same integer sums, so the same bits.

    Per dot: ``sum_x``, ``sum_y`` (offsets of the landing positions from the nominal position, units
    of 1 / POSITION_SCALE px), ``sums`` (N, 7): the sums of their products (see ``moment_terms``).
    """
    n_dots = dots.shape[0]
    tid = wp.tid()
    slot, chunk = group_member(tid, group, n_dots)
    r0 = chunk * rays_per_thread
    tiled = compiled_for_cpu() == 0 and tile_side > 0
    if r0 >= ray_count and not tiled:
        return
    dot = launch_order[slot]
    r1 = wp.min(r0 + rays_per_thread, ray_count)  # r1 <= r0: a tiled launch's idle thread
    lane = tid % block_dim
    base = (lane / group) * tile_side * tile_side
    corner = spot_tile_corner(nominal_px[dot], tile_side)
    if tiled:
        for k in range(lane, (block_dim / group) * tile_side * tile_side, block_dim):
            spot_cell(SPOT_CLEAR, k, wp.int64(0))
        spot_cell(SPOT_SYNC, 0, wp.int64(0))
    acc_x = wp.int64(0)
    acc_y = wp.int64(0)
    acc = vec7l()
    n_hit = int(0)  # noqa: UP018, RUF046 (a dynamic variable: it changes inside the loop)
    n_lost = int(0)  # noqa: UP018, RUF046 (a dynamic variable: it changes inside the loop)
    n_tir = int(0)  # noqa: UP018, RUF046 (a dynamic variable: it changes inside the loop)
    n_far = int(0)  # noqa: UP018, RUF046 (a dynamic variable: it changes inside the loop)
    for local in range(r0, r1):
        xs, status = trace_one_ray(medium, active, cam, dots, dot, ray_start + local, n_dots, dot_radius, step,
                                   cells, aim_iterations, seed)
        if status == RAY_TIR:
            n_tir += 1
        if status != RAY_OK:
            n_lost += 1
            continue
        px = sensor_to_pixel(sen, xs)
        if px[0] < -0.5 or px[1] < -0.5 or px[0] > float(sen.width) - 0.5 or px[1] > float(sen.height) - 0.5:
            n_lost += 1
        if tiled:
            deposit_gaussian_tiled(image, sen, px, sen.energy, base, corner, tile_side, lane % group)
        else:
            deposit_gaussian(image, sen, px, sen.energy, lane % group)
        d = px - nominal_px[dot]
        acc_x += wp.int64(wp.floor(d[0] * POSITION_SCALE + 0.5))
        acc_y += wp.int64(wp.floor(d[1] * POSITION_SCALE + 0.5))
        terms, beyond = moment_terms(d, scale2, scale3)
        acc += terms
        n_far += beyond
        n_hit += 1
    if n_hit > 0:
        wp.atomic_add(sum_x, dot, acc_x)
        wp.atomic_add(sum_y, dot, acc_y)
        for k in range(7):
            wp.atomic_add(sums, dot, k, acc[k])
        wp.atomic_add(hits, dot, n_hit)
    if n_far > 0:
        wp.atomic_add(far, dot, n_far)
    if n_lost > 0:
        wp.atomic_add(lost, dot, n_lost)
    if n_tir > 0:
        wp.atomic_add(tir, dot, n_tir)
    if tiled:
        spot_cell(SPOT_SYNC, 0, wp.int64(0))
        flush_spot_tiles(image, nominal_px, launch_order, tid, lane, block_dim, group, tile_side)


@wp.kernel
def trace_to_exit(
    medium: Any,
    active: int,
    origins: wp.array(dtype=wp.vec3),
    tangents: wp.array(dtype=wp.vec3),
    step: float,
    cells: int,
    out_x: wp.array(dtype=wp.vec3),
    out_t: wp.array(dtype=wp.vec3),
):
    """Trace given rays through the volume only (used by tests and diagnostics); see ``trace_volume``."""
    i = wp.tid()
    p, t = trace_volume(medium, active, origins[i], tangents[i], step, cells)
    out_x[i] = p
    out_t[i] = t


@wp.kernel
def deposit_spots(
    sen: Sensor,
    px: wp.array(dtype=wp.vec2),
    energy: wp.array(dtype=float),
    image: wp.array2d(dtype=wp.int64),
):
    """Deposit one Gaussian spot per entry (used by tests to compare against the NumPy reference)."""
    i = wp.tid()
    deposit_gaussian(image, sen, px[i], energy[i], i)


# ``render_rays`` for each medium struct, held to at most 80 or 64 registers a thread on CUDA or not
# (``rays.max_registers``: with 256-thread blocks, 3 or 4 blocks per SM instead of 2 for kernels above 80
# registers, at the price of spills to local memory), each in a Warp module of its own (named by
# ``render_module``): a run compiles only the media it launches, on a first run two of the 21 (the
# paper's medium and the reference image's). The generic ``render_rays`` itself is compiled for none.
MEDIA = (Medium, MediumStraight, MediumVec, MediumVec3D, MediumHalf, MediumHalfNodes, MediumTexture, MediumTexels)
REGISTER_CAPS = (0, 80, 64)  # 0: no cap


def render_module(medium: type, max_registers: int = 0) -> str:
    """The name of the Warp module that holds ``render_rays`` for the struct ``medium`` held to
    ``max_registers`` registers (0: no cap)."""
    return f"{__name__}.render_{medium.__name__}" + (f"_r{max_registers}" if max_registers else "")


_RENDER = {}
for _medium in MEDIA:
    for _cap in REGISTER_CAPS:
        wp.set_module_options({"enable_backward": False}, module=render_module(_medium, _cap))
        _RENDER[_medium, _cap] = wp.kernel(
            render_rays.func, name=f"render_rays_{_medium.__name__}" + (f"_r{_cap}" if _cap else ""),
            module=render_module(_medium, _cap), cuda_max_registers=_cap or None, enable_backward=False,
        )
        wp.overload(_RENDER[_medium, _cap], {"medium": _medium})


def render_kernel(medium, max_registers: int = 0):
    """``render_rays`` for ``medium`` (one of the structs of ``MEDIA``, or an instance of one), held to
    ``max_registers`` registers (one of ``REGISTER_CAPS``; 0: no cap)."""
    struct = next(m for m in MEDIA if medium is m or isinstance(medium, m.instance_type))
    return _RENDER[struct, max_registers]


# ``trace_to_exit`` on the float32 medium serves the tests.
wp.overload(trace_to_exit, {"medium": Medium})
