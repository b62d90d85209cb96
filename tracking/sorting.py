"""Sorting networks: the compare-exchange pairs that put the middle of a set of values in place.

A network is fixed for a given count, so kernels can unroll it (the edge median of
:mod:`tracking.identify_kernels`) or read it from an array (the neighbour tests); it is made here, below every
module that uses it.
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = ["median_network"]


@functools.lru_cache(maxsize=16)
def median_network(n):
    """Compare-exchange pairs ``(a, b)`` (``a < b``) that bring the middle two of any ``n`` values to
    positions ``n // 2 - 1`` and ``n // 2`` (for odd n the median is the latter): Batcher's odd-even
    merge sort for the next power of two (Knuth, TAOCP vol. 3, 5.3.4), less the pairs that touch a
    position ``>= n`` (as if padded with +inf, which those pairs never move) and those that cannot reach
    the two middle positions. Used by the windows' edge median and the neighbour fit's median.

    Returns
    -------
    (K, 2) int32 array
    """
    m = 1
    while m < n:
        m *= 2
    pairs = []
    p = 1
    while p < m:
        k = p
        while k >= 1:
            for j in range(k % p, m - k, 2 * k):
                for i in range(min(k, m - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p) and i + j + k < n:
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    need = {n // 2 - 1, n // 2}
    kept = []
    for a, b in reversed(pairs):
        if a in need or b in need:
            kept.append((a, b))
            need |= {a, b}
    return np.array(kept[::-1], dtype=np.int32).reshape(-1, 2)
