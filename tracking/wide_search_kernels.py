"""Warp kernels of the wide second search over a stack of pairs: the dots that the narrow window around
their prediction missed, the wide window's result merged in, and the blobs two dots ended up on given to
the one nearer its prediction.

Kernels and ``@wp.func`` steps only; the host code is :func:`tracking.wide_search.wide_search_stack`. Dots
are held flat: dot ``i`` of a call belongs to pair ``i // per_frame``. The blobs are claimed on the claim
board of identification (:mod:`tracking.claim_kernels`: ``claim_key``, ``release_claims``).
"""

import warp as wp

from synthbos.device import quiet_warp

from .claim_kernels import claim_key
from .kernel_constants import AMBIGUOUS

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile


@wp.kernel
def list_misses(
    x_g: wp.array(dtype=wp.float64),
    x_r: wp.array(dtype=wp.float64),
    per_frame: int,
    count: wp.array(dtype=wp.int32),
    ids: wp.array(dtype=wp.int32),
    pair_has_miss: wp.array(dtype=wp.int32),
):
    """Dots found in the reference image but not by the narrow window in the gradient image (any order:
    each is measured on its own)."""
    i = wp.tid()
    if wp.isfinite(x_r[i]) and not wp.isfinite(x_g[i]):
        slot = wp.atomic_add(count, 0, 1)
        ids[slot] = i
        pair_has_miss[i // per_frame] = 1


@wp.kernel
def merge_wide(
    ids: wp.array(dtype=wp.int32),
    x2: wp.array(dtype=wp.float64),
    y2: wp.array(dtype=wp.float64),
    eta2: wp.array(dtype=wp.float64),
    i02: wp.array(dtype=wp.float64),
    iteration2: wp.array(dtype=wp.int32),
    root2: wp.array2d(dtype=wp.int32),
    flags2: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    eta: wp.array(dtype=wp.float64),
    i0: wp.array(dtype=wp.float64),
    iteration: wp.array(dtype=wp.int32),
    root: wp.array2d(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """The wide window's result replaces the narrow one's for the dots it looked for (flags add up)."""
    i = ids[wp.tid()]
    x[i] = x2[i]
    y[i] = y2[i]
    eta[i] = eta2[i]
    i0[i] = i02[i]
    iteration[i] = iteration2[i]
    root[i, 0] = root2[i, 0]
    root[i, 1] = root2[i, 1]
    flags[i] = flags[i] | flags2[i]


@wp.func
def distance_to(x: wp.float64, y: wp.float64, p: wp.vec2d) -> wp.float64:
    dx = x - p[0]
    dy = y - p[1]
    return wp.sqrt(dx * dx + dy * dy)


@wp.kernel
def claim_shared_blobs(
    per_frame: int,
    pair_has_miss: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    root: wp.array2d(dtype=wp.int32),
    pred: wp.array(dtype=wp.vec2d),
    w: int,
    hp: int,
    wp_: int,
    key: wp.array(dtype=wp.int32),
    claim_dist: wp.array(dtype=wp.float64),
):
    """Two dots on one blob, first half: the distance of the dot nearest its prediction
    on each blob."""
    i = wp.tid()
    f = i // per_frame
    key[i] = -1
    if pair_has_miss[f] == 0 or not wp.isfinite(x[i]):
        return
    k = claim_key(f, root[i, 1], root[i, 0], w, hp, wp_)
    key[i] = k
    wp.atomic_min(claim_dist, k, distance_to(x[i], y[i], pred[i]))


@wp.kernel
def claim_shared_nearest(
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    pred: wp.array(dtype=wp.vec2d),
    key: wp.array(dtype=wp.int32),
    claim_dist: wp.array(dtype=wp.float64),
    claim_id: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    k = key[i]
    if k >= 0 and distance_to(x[i], y[i], pred[i]) == claim_dist[k]:
        wp.atomic_min(claim_id, k, i)


@wp.kernel
def drop_shared_losers(
    key: wp.array(dtype=wp.int32),
    claim_id: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    eta: wp.array(dtype=wp.float64),
    i0: wp.array(dtype=wp.float64),
    iteration: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """Two dots on one blob, second half: the others on a blob are not found (AMBIGUOUS)."""
    i = wp.tid()
    k = key[i]
    if k >= 0 and claim_id[k] != i:
        nan = wp.float64(wp.nan)
        x[i] = nan
        y[i] = nan
        eta[i] = nan
        i0[i] = nan
        iteration[i] = 0
        flags[i] = flags[i] | AMBIGUOUS
