"""Per-thread scratch arrays of the tracking kernels, kept from one call to the next.

A 1024x1024 pair needs some 60 MB of working arrays (the fit's fixed-point model images and pixel
profiles, the predictor's moved image). Allocated afresh on every call, their pages are mapped and
cleared by the operating system on first touch, which costs more than some of the kernels that use
them; each thread therefore keeps one flat array per name and device, grown when a call needs more.
Their content is undefined: every user writes (or clears) what it reads. Only views that do not
outlive the call may be handed out (results are copied out of them).
"""

from __future__ import annotations

import threading

import numpy as np
import warp as wp

__all__ = ["scratch"]

_local = threading.local()


def scratch(name, shape, dtype, device):
    """A Warp array of ``shape`` and ``dtype`` on ``device``, reused by later calls with the same ``name``.

    Parameters
    ----------
    name : str
        What the array is for; arrays in use at the same time need different names.
    shape : tuple of int
    dtype : Warp scalar type
    device : str or None
        Warp device; Warp's default when None.

    Returns
    -------
    warp.array
        A contiguous view of the thread's array (undefined content).
    """
    key = (str(wp.get_device(device)), dtype)
    need = int(np.prod(shape, dtype=np.int64))
    store = _local.__dict__.setdefault("arrays", {})
    have = store.get(name)
    if have is None or have[0] != key or have[1].shape[0] < need:
        store[name] = have = (key, wp.empty(max(need, 1), dtype=dtype, device=device))
    return have[1][:need].reshape(tuple(int(s) for s in shape))
