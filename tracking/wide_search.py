"""The wide second search: the dots that the narrow window around their prediction missed, looked for
again in the paper's wide window around the same prediction.

With the correlation predictor, the gradient image's dots are first looked for in the narrow window of
``TrackingSettings.prior_radius`` around their predicted positions; a dot found in the reference image
but missed there is looked for again in the wide window (``max_displacement`` plus a margin, or
``search_radius``), whose result replaces the narrow one's (the flags add up). Two dots may then end
up on one blob (peak pixel): the one nearer its prediction keeps it, the others are not found and
flagged AMBIGUOUS. :func:`wide_search_stack` takes these steps for every pair of a stack on one Warp
device, on identification's claim board (kernels in :mod:`tracking.wide_search_kernels`).
"""

from __future__ import annotations

import warp as wp

from . import wide_search_kernels as wk
from .claim_kernels import release_claims

__all__ = ["wide_search_stack"]

#: The per-dot results of an identification, in the order the merge kernel takes them.
_FIELDS = ("x", "y", "eta", "i0", "iteration", "root", "flags")


def wide_search_stack(identify, r, g, pred, *, per_frame, pairs, window, board, device):
    """The wide second search of every pair of a stack, in place in ``g``: its result replaces the narrow
    one's, and where two dots ended up on one blob the one nearer its prediction keeps it.

    Parameters
    ----------
    identify : callable
        ``identify(ids, n_ids)``: the wide window's identification in the gradient images around ``pred``
        for the ``n_ids`` dots ``ids`` (an int32 Warp array), returning fresh per-dot Warp arrays
        (``tracking.stack``'s ``_Stack.identify`` with ``wide=True``).
    r, g : dict of (M,) Warp arrays
        The reference images' dots and the gradient images' dots of the narrow search (``_FIELDS``, and
        the host's ``"dotmap"`` where identification keeps them).
    pred : (M,) wp.vec2d Warp array
        The predicted gradient-image positions.
    per_frame, pairs : int, keyword-only
        Dots per pair and pairs (``M = per_frame * pairs``).
    window : int, keyword-only
        The wide window's side (px), the stride of the claim keys.
    board : tuple, keyword-only
        Identification's claim board ``(hp, wpad, claim_dist, claim_id)``: the padded frame's height and
        width, and the distance and dot of each blob's claim (left as it was found: released).
    device : warp.context.Device or str, keyword-only

    Notes
    -----
    The host waits for the device once, for the number of dots missed; with none, nothing else runs.
    """
    m = per_frame * pairs
    hp, wpad, claim_dist, claim_id = board
    count = wp.zeros(1, dtype=wp.int32, device=device)
    miss = wp.empty(m, dtype=wp.int32, device=device)
    has_miss = wp.zeros(pairs, dtype=wp.int32, device=device)

    def launch(kernel, dim, inputs):
        if dim:
            wp.launch(kernel, dim=dim, inputs=inputs, device=device)

    launch(wk.list_misses, m, [g["x"], r["x"], per_frame, count, miss, has_miss])
    n_miss = int(count.numpy()[0])
    if not n_miss:
        return
    g2 = identify(miss, n_miss)
    launch(wk.merge_wide, n_miss, [miss, *(g2[k] for k in _FIELDS), *(g[k] for k in _FIELDS)])
    if "dotmap" in g:  # the paper's correction's dot maps, on the host (identification's host engine)
        rows = miss.numpy()[:n_miss]
        g["dotmap"][rows] = g2["dotmap"][rows]
    key = wp.empty(m, dtype=wp.int32, device=device)
    launch(
        wk.claim_shared_blobs,
        m,
        [per_frame, has_miss, g["x"], g["y"], g["root"], pred, window, hp, wpad, key, claim_dist],
    )
    launch(wk.claim_shared_nearest, m, [g["x"], g["y"], pred, key, claim_dist, claim_id])
    launch(wk.drop_shared_losers, m, [key, claim_id, g["x"], g["y"], g["eta"], g["i0"], g["iteration"], g["flags"]])
    launch(release_claims, m, [key, claim_dist, claim_id])
