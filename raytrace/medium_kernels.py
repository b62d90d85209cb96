"""Warp structs and functions of the renderer's media: the nodes of (grad n, n - 1) and how a ray's RK4
stages read them.

``raytrace.kernels.render_rays`` is generic over the struct that holds the medium; ``sample_medium`` has
one overload per struct (``raytrace.medium.FIELDS`` names them for the configuration): ``Medium``
(float32 nodes), ``MediumVec`` (the same, 128-bit loads; ``MediumVec3D`` for a truly 3-D field),
``MediumTexels`` (the same, point-sampled texture), ``MediumHalf`` / ``MediumHalfNodes`` (float16),
``MediumTexture`` (the texture unit's filter) and ``MediumStraight`` (no medium: the reference image).
All share ``node_coords``, ``in_grid``, ``cell_of`` and ``trilinear``.

A cell step (``raytrace.kernels.trace_volume``, ``stepping = "cells"``) stays inside one cell of the
nodes, so through a truly 3-D float32 field its four RK4 stages read that cell's eight nodes once
(``read_by_cell``, ``step_medium``: a ``MediumCell``) instead of eight a stage: ``Medium`` and
``MediumTexels`` where their planes differ, and ``MediumVec3D``, the default field's struct for such a
field. A planar field (the paper's slice, ``MediumVec``) and the other media are read at each stage, the
bits of before; the exact fields agree bit for bit on the CPU in each case.
"""

from typing import Any

import warp as wp

from synthbos.device import quiet_warp

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only functions: no adjoint code to compile


# Float16 node pair along x: (grad n, n - 1) of node i, then of node i + 1, both scaled (see MediumHalf).
vec8h = wp.types.vector(length=8, dtype=wp.float16)


@wp.struct
class Medium:
    # (nz, ny, nx) nodes holding (dn/dx, dn/dy, dn/dz, n - 1)
    field: wp.array3d(dtype=wp.vec4)
    planar: int  # 1 when every node plane along z holds the same values (a 2-D field through the depth)
    half: wp.vec3  # half extents of the box (local frame spans [-half, +half])
    inv_spacing: wp.vec3  # 1 / node spacing along x, y, z
    centre: wp.vec3  # box centre in the global frame


@wp.struct
class MediumStraight:
    # Only the box's placement: the reference image's rays (``active = 0``) never read the medium, and
    # a kernel compiled without its loads needs fewer registers.
    half: wp.vec3
    inv_spacing: wp.vec3
    centre: wp.vec3


@wp.struct
class MediumVec:
    # The same nodes as ``Medium``, read with one 128-bit load per node on CUDA (bitwise the same values).
    field: wp.array3d(dtype=wp.vec4)
    planar: int
    half: wp.vec3
    inv_spacing: wp.vec3
    centre: wp.vec3


@wp.struct
class MediumVec3D:
    # ``MediumVec`` for a truly 3-D field (``raytrace.medium.to_warp`` gives it where the node planes
    # differ): a cell step reads its cell once (``step_medium``), and the planar slice's kernel stays as
    # it was (one kernel holding both ways of reading ran the slice 7-9 % slower on an H100).
    field: wp.array3d(dtype=wp.vec4)
    planar: int
    half: wp.vec3
    inv_spacing: wp.vec3
    centre: wp.vec3


@wp.struct
class MediumHalf:
    # (nz, ny, nx - 1) records: nodes (k, j, i) and (k, j, i + 1) in float16, each channel multiplied by
    # a power of two (so weak fields stay clear of float16's subnormals); ``unscale`` undoes it.
    pairs: wp.array3d(dtype=vec8h)
    unscale: wp.vec4
    half: wp.vec3
    inv_spacing: wp.vec3
    centre: wp.vec3


@wp.struct
class MediumHalfNodes:
    # (nz, ny, nx) nodes in float16, scaled as in MediumHalf: half the bytes of ``Medium`` (the paper's
    # volume, 42 MB, fits in an H200's L2), eight 64-bit loads per sample.
    nodes: wp.array3d(dtype=wp.vec4h)
    unscale: wp.vec4
    half: wp.vec3
    inv_spacing: wp.vec3
    centre: wp.vec3


@wp.struct
class MediumTexture:
    # The nodes as a 4-channel 3D texture (float32, or float16 scaled like MediumHalf), unnormalised
    # coordinates, clamped, read through the texture unit's trilinear filter (on CUDA its weights have
    # 8 fractional bits).
    tex: wp.Texture3D
    unscale: wp.vec4
    half: wp.vec3
    inv_spacing: wp.vec3
    centre: wp.vec3


@wp.struct
class MediumTexels:
    # The float32 nodes as a point-sampled texture: eight texel fetches and the arithmetic of ``Medium``.
    tex: wp.Texture3D
    planar: int
    half: wp.vec3
    inv_spacing: wp.vec3
    centre: wp.vec3


@wp.func
def node_coords(half: wp.vec3, inv_spacing: wp.vec3, p: wp.vec3):
    """Fractional node coordinates (x, y, z) of local point p."""
    return wp.vec3(
        (p[0] + half[0]) * inv_spacing[0], (p[1] + half[1]) * inv_spacing[1], (p[2] + half[2]) * inv_spacing[2]
    )


@wp.func
def in_grid(f: wp.vec3, nx: int, ny: int, nz: int):
    """1 if fractional node coordinates f lie in the grid (with a margin of 1e-4 node), else 0."""
    eps = 1.0e-4
    if f[0] < -eps or f[1] < -eps or f[2] < -eps:
        return 0
    if f[0] > float(nx - 1) + eps or f[1] > float(ny - 1) + eps or f[2] > float(nz - 1) + eps:
        return 0
    return 1


@wp.func
def cell_of(f: wp.vec3, nx: int, ny: int, nz: int):
    """The cell (i, j, k) holding f (edges clamped) and the weights of its far corner along x, y, z."""
    i = wp.clamp(int(wp.floor(f[0])), 0, nx - 2)
    j = wp.clamp(int(wp.floor(f[1])), 0, ny - 2)
    k = wp.clamp(int(wp.floor(f[2])), 0, nz - 2)
    a = wp.vec3(
        wp.clamp(f[0] - float(i), 0.0, 1.0), wp.clamp(f[1] - float(j), 0.0, 1.0), wp.clamp(f[2] - float(k), 0.0, 1.0)
    )
    return i, j, k, a


@wp.func
def bilinear(c00: wp.vec4, c10: wp.vec4, c01: wp.vec4, c11: wp.vec4, a: wp.vec3):
    """Bilinear blend of a cell face's corners c(x)(y) with far-corner weights a[0], a[1]."""
    c0 = c00 * (1.0 - a[0]) + c10 * a[0]
    c1 = c01 * (1.0 - a[0]) + c11 * a[0]
    return c0 * (1.0 - a[1]) + c1 * a[1]


@wp.func
def trilinear(
    c000: wp.vec4, c100: wp.vec4, c010: wp.vec4, c110: wp.vec4,
    c001: wp.vec4, c101: wp.vec4, c011: wp.vec4, c111: wp.vec4, a: wp.vec3,
):
    """Trilinear blend of a cell's corners c(x)(y)(z) with far-corner weights a."""
    c0 = bilinear(c000, c100, c010, c110, a)
    c1 = bilinear(c001, c101, c011, c111, a)
    return c0 * (1.0 - a[2]) + c1 * a[2]


@wp.func_native("""
#if defined(__CUDA_ARCH__)
const float4 v = __ldg(reinterpret_cast<const float4*>(wp::address(field, k, j, i)));
return wp::vec4(v.x, v.y, v.z, v.w);
#else
return wp::index(field, k, j, i);
#endif
""")
def load_node(field: wp.array3d(dtype=wp.vec4), k: int, j: int, i: int) -> wp.vec4:
    """Node (k, j, i) of a vec4 array, in one 128-bit read-only load on CUDA."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
const uint4 v = __ldg(reinterpret_cast<const uint4*>(wp::address(pairs, k, j, i)));
wp::vec_t<8, wp::half> out;
memcpy(&out, &v, 16);
return out;
#else
return wp::index(pairs, k, j, i);
#endif
""")
def load_pair(pairs: wp.array3d(dtype=vec8h), k: int, j: int, i: int) -> vec8h:
    """Record (k, j, i) of a float16 pair array, in one 128-bit read-only load on CUDA."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
const uint2 v = __ldg(reinterpret_cast<const uint2*>(wp::address(nodes, k, j, i)));
wp::vec_t<4, wp::half> out;
memcpy(&out, &v, 8);
return out;
#else
return wp::index(nodes, k, j, i);
#endif
""")
def load_half_node(nodes: wp.array3d(dtype=wp.vec4h), k: int, j: int, i: int) -> wp.vec4h:
    """Node (k, j, i) of a float16 node array, in one 64-bit read-only load on CUDA."""
    ...


@wp.func
def half_node(nodes: wp.array3d(dtype=wp.vec4h), k: int, j: int, i: int):
    """Node (k, j, i) of a float16 node array as float32."""
    v = load_half_node(nodes, k, j, i)
    return wp.vec4(float(v[0]), float(v[1]), float(v[2]), float(v[3]))


@wp.func
def pair_nodes(r: vec8h):
    """The two nodes of a float16 pair record as float32 (node i, node i + 1)."""
    lo = wp.vec4(float(r[0]), float(r[1]), float(r[2]), float(r[3]))
    hi = wp.vec4(float(r[4]), float(r[5]), float(r[6]), float(r[7]))
    return lo, hi


@wp.func
def sample_medium(m: Medium, p: wp.vec3):
    """Trilinear sample of (grad n, n - 1) at local point p; zero outside the box."""
    nz = m.field.shape[0]
    ny = m.field.shape[1]
    nx = m.field.shape[2]
    f = node_coords(m.half, m.inv_spacing, p)
    if in_grid(f, nx, ny, nz) == 0:
        return wp.vec4(0.0)
    i, j, k, a = cell_of(f, nx, ny, nz)
    if m.planar != 0:  # every plane holds these values: the blend along z is the identity
        return bilinear(m.field[0, j, i], m.field[0, j, i + 1], m.field[0, j + 1, i], m.field[0, j + 1, i + 1], a)
    return trilinear(
        m.field[k, j, i], m.field[k, j, i + 1], m.field[k, j + 1, i], m.field[k, j + 1, i + 1],
        m.field[k + 1, j, i], m.field[k + 1, j, i + 1], m.field[k + 1, j + 1, i], m.field[k + 1, j + 1, i + 1], a,
    )


@wp.func
def sample_medium(m: MediumStraight, p: wp.vec3):  # noqa: F811 (an overload)
    """The undisturbed medium: no gradient anywhere (the reference image)."""
    return wp.vec4(0.0)


@wp.func
def sample_medium(m: MediumVec, p: wp.vec3):  # noqa: F811 (an overload)
    """``sample_medium`` of ``Medium`` with 128-bit node loads: the same numbers."""
    return sample_vec(m, p)


@wp.func
def sample_medium(m: MediumVec3D, p: wp.vec3):  # noqa: F811 (an overload)
    """As ``MediumVec`` (the stages of the fixed steps, which may cross cells)."""
    return sample_vec(m, p)


@wp.func
def sample_vec(m: Any, p: wp.vec3):
    """``sample_medium`` of ``Medium`` with 128-bit node loads, for ``MediumVec`` and ``MediumVec3D``."""
    nz = m.field.shape[0]
    ny = m.field.shape[1]
    nx = m.field.shape[2]
    f = node_coords(m.half, m.inv_spacing, p)
    if in_grid(f, nx, ny, nz) == 0:
        return wp.vec4(0.0)
    i, j, k, a = cell_of(f, nx, ny, nz)
    if m.planar != 0:
        return bilinear(
            load_node(m.field, 0, j, i), load_node(m.field, 0, j, i + 1),
            load_node(m.field, 0, j + 1, i), load_node(m.field, 0, j + 1, i + 1), a,
        )
    return trilinear(
        load_node(m.field, k, j, i), load_node(m.field, k, j, i + 1),
        load_node(m.field, k, j + 1, i), load_node(m.field, k, j + 1, i + 1),
        load_node(m.field, k + 1, j, i), load_node(m.field, k + 1, j, i + 1),
        load_node(m.field, k + 1, j + 1, i), load_node(m.field, k + 1, j + 1, i + 1), a,
    )


@wp.func
def sample_medium(m: MediumHalf, p: wp.vec3):  # noqa: F811 (an overload)
    """``sample_medium`` from float16 node pairs: four 128-bit loads per sample."""
    nz = m.pairs.shape[0]
    ny = m.pairs.shape[1]
    nx = m.pairs.shape[2] + 1
    f = node_coords(m.half, m.inv_spacing, p)
    if in_grid(f, nx, ny, nz) == 0:
        return wp.vec4(0.0)
    i, j, k, a = cell_of(f, nx, ny, nz)
    c000, c100 = pair_nodes(load_pair(m.pairs, k, j, i))
    c010, c110 = pair_nodes(load_pair(m.pairs, k, j + 1, i))
    c001, c101 = pair_nodes(load_pair(m.pairs, k + 1, j, i))
    c011, c111 = pair_nodes(load_pair(m.pairs, k + 1, j + 1, i))
    return wp.cw_mul(trilinear(c000, c100, c010, c110, c001, c101, c011, c111, a), m.unscale)


@wp.func
def sample_medium(m: MediumHalfNodes, p: wp.vec3):  # noqa: F811 (an overload)
    """``sample_medium`` from float16 nodes: the numbers of ``MediumHalf``, eight 64-bit loads."""
    nz = m.nodes.shape[0]
    ny = m.nodes.shape[1]
    nx = m.nodes.shape[2]
    f = node_coords(m.half, m.inv_spacing, p)
    if in_grid(f, nx, ny, nz) == 0:
        return wp.vec4(0.0)
    i, j, k, a = cell_of(f, nx, ny, nz)
    c = trilinear(
        half_node(m.nodes, k, j, i), half_node(m.nodes, k, j, i + 1),
        half_node(m.nodes, k, j + 1, i), half_node(m.nodes, k, j + 1, i + 1),
        half_node(m.nodes, k + 1, j, i), half_node(m.nodes, k + 1, j, i + 1),
        half_node(m.nodes, k + 1, j + 1, i), half_node(m.nodes, k + 1, j + 1, i + 1), a,
    )
    return wp.cw_mul(c, m.unscale)


@wp.func
def sample_medium(m: MediumTexture, p: wp.vec3):  # noqa: F811 (an overload)
    """``sample_medium`` through the texture unit's trilinear filter: one fetch per sample."""
    f = node_coords(m.half, m.inv_spacing, p)
    if in_grid(f, m.tex.width, m.tex.height, m.tex.depth) == 0:
        return wp.vec4(0.0)
    return wp.cw_mul(wp.texture_sample(m.tex, f + wp.vec3(0.5), dtype=wp.vec4), m.unscale)


@wp.func
def texel(m: MediumTexels, i: int, j: int, k: int):
    """Node (k, j, i) of a point-sampled texture (texel centres at integer + 0.5)."""
    return wp.texture_sample(m.tex, wp.vec3(float(i) + 0.5, float(j) + 0.5, float(k) + 0.5), dtype=wp.vec4)


@wp.func
def sample_medium(m: MediumTexels, p: wp.vec3):  # noqa: F811 (an overload)
    """``sample_medium`` of ``Medium`` from eight texel fetches: the same numbers."""
    nz = m.tex.depth
    ny = m.tex.height
    nx = m.tex.width
    f = node_coords(m.half, m.inv_spacing, p)
    if in_grid(f, nx, ny, nz) == 0:
        return wp.vec4(0.0)
    i, j, k, a = cell_of(f, nx, ny, nz)
    if m.planar != 0:
        return bilinear(texel(m, i, j, 0), texel(m, i + 1, j, 0), texel(m, i, j + 1, 0), texel(m, i + 1, j + 1, 0), a)
    return trilinear(
        texel(m, i, j, k), texel(m, i + 1, j, k), texel(m, i, j + 1, k), texel(m, i + 1, j + 1, k),
        texel(m, i, j, k + 1), texel(m, i + 1, j, k + 1),
        texel(m, i, j + 1, k + 1), texel(m, i + 1, j + 1, k + 1), a,
    )


# --- one cell read once for a step's four stages -------------------------------------------------------


@wp.struct
class MediumCell:
    # The eight nodes c(x)(y)(z) of one cell of a 3-D float32 medium, read once for the RK4 stages of a
    # step that stays inside it; ``origin``: the node coordinates of its corner c000.
    c000: wp.vec4
    c100: wp.vec4
    c010: wp.vec4
    c110: wp.vec4
    c001: wp.vec4
    c101: wp.vec4
    c011: wp.vec4
    c111: wp.vec4
    origin: wp.vec3
    half: wp.vec3
    inv_spacing: wp.vec3


@wp.func
def sample_medium(m: MediumCell, p: wp.vec3):  # noqa: F811 (an overload)
    """``sample_medium`` of the medium the cell was read from, at a point p inside the cell: the same
    weights and blend (a stage a hair outside, where a ray bends across a node plane, takes the value on
    the cell's face)."""
    f = node_coords(m.half, m.inv_spacing, p) - m.origin
    a = wp.vec3(wp.clamp(f[0], 0.0, 1.0), wp.clamp(f[1], 0.0, 1.0), wp.clamp(f[2], 0.0, 1.0))
    return trilinear(m.c000, m.c100, m.c010, m.c110, m.c001, m.c101, m.c011, m.c111, a)


@wp.func
def grid_node(m: Medium, k: int, j: int, i: int):
    """Node (k, j, i) of a float32 medium."""
    return m.field[k, j, i]


@wp.func
def grid_node(m: MediumVec3D, k: int, j: int, i: int):  # noqa: F811 (an overload)
    """Node (k, j, i), one 128-bit load on CUDA."""
    return load_node(m.field, k, j, i)


@wp.func
def grid_node(m: MediumTexels, k: int, j: int, i: int):  # noqa: F811 (an overload)
    """Node (k, j, i) of the point-sampled texture."""
    return texel(m, i, j, k)


@wp.func
def grid_shape(m: Any):
    """Nodes along x, y, z of a medium held in ``field``."""
    return m.field.shape[2], m.field.shape[1], m.field.shape[0]


@wp.func
def grid_shape(m: MediumTexels):  # noqa: F811 (an overload)
    """Nodes along x, y, z of the point-sampled texture."""
    return m.tex.width, m.tex.height, m.tex.depth


@wp.func
def cell_at(m: Any, p: wp.vec3):
    """The cell of ``m``'s nodes that holds local point p (``cell_of``: edges clamped), read into a
    ``MediumCell``."""
    nx, ny, nz = grid_shape(m)
    i, j, k, _a = cell_of(node_coords(m.half, m.inv_spacing, p), nx, ny, nz)
    c = MediumCell()
    c.c000 = grid_node(m, k, j, i)
    c.c100 = grid_node(m, k, j, i + 1)
    c.c010 = grid_node(m, k, j + 1, i)
    c.c110 = grid_node(m, k, j + 1, i + 1)
    c.c001 = grid_node(m, k + 1, j, i)
    c.c101 = grid_node(m, k + 1, j, i + 1)
    c.c011 = grid_node(m, k + 1, j + 1, i)
    c.c111 = grid_node(m, k + 1, j + 1, i + 1)
    c.origin = wp.vec3(float(i), float(j), float(k))
    c.half = m.half
    c.inv_spacing = m.inv_spacing
    return c


@wp.func
def read_by_cell(m: Any) -> int:
    """Whether a cell step through ``m`` reads its cell once (``step_medium``); 0: at each stage (a
    constant, so the kernel of such a medium holds only the reads at each stage)."""
    return 0


@wp.func
def read_by_cell(m: Medium) -> int:  # noqa: F811 (an overload)
    """Where the field is truly 3-D (a planar one keeps the bilinear reads of ``MediumVec``'s slice)."""
    return 1 - m.planar


@wp.func
def read_by_cell(m: MediumTexels) -> int:  # noqa: F811 (an overload)
    """As ``Medium``."""
    return 1 - m.planar


@wp.func
def read_by_cell(m: MediumVec3D) -> int:  # noqa: F811 (an overload)
    """Always (a truly 3-D field)."""
    return 1


@wp.func
def step_medium(m: Any, p: wp.vec3):
    """What the stages of a cell step around local point p read: the medium itself (read at each stage)."""
    return m


@wp.func
def step_medium(m: Medium, p: wp.vec3):  # noqa: F811 (an overload)
    """The cell around p."""
    return cell_at(m, p)


@wp.func
def step_medium(m: MediumVec3D, p: wp.vec3):  # noqa: F811 (an overload)
    """The cell around p."""
    return cell_at(m, p)


@wp.func
def step_medium(m: MediumTexels, p: wp.vec3):  # noqa: F811 (an overload)
    """The cell around p."""
    return cell_at(m, p)
