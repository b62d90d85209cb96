"""Per-thread scratch arrays of the tracking kernels, kept from one call to the next.

A 1024x1024 pair needs some 60 MB of working arrays (the fit's fixed-point model images and pixel
profiles, the predictor's moved image). Allocated afresh on every call, their pages are mapped and
cleared by the operating system on first touch, which costs more than some of the kernels that use
them; each thread therefore keeps one flat array per name and device, grown when a call needs more.
Their content is undefined: every user writes (or clears) what it reads (or, through
:func:`zeroed_scratch`, finds them zero and leaves them zero). Only views that do not outlive the call
may be handed out (results are copied out of them).
"""

from __future__ import annotations

import threading
from contextlib import contextmanager

import numpy as np
import warp as wp

__all__ = ["scratch", "zeroed_scratch"]

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
    return _flat(name, shape, dtype, device)[: _size(shape)].reshape(tuple(int(s) for s in shape))


def _size(shape):
    return int(np.prod(shape, dtype=np.int64))


def _flat(name, shape, dtype, device):
    """The thread's whole flat array of this name, grown (undefined content) where it is too small."""
    key = (str(wp.get_device(device)), dtype)
    need = _size(shape)
    store = _local.__dict__.setdefault("arrays", {})
    have = store.get(name)
    if have is None or have[0] != key or have[1].shape[0] < need:
        store[name] = have = (key, wp.empty(max(need, 1), dtype=dtype, device=device))
        _local.__dict__.setdefault("clean", set()).discard(name)
    return have[1]


@contextmanager
def zeroed_scratch(name, shape, dtype, device):
    """Like :func:`scratch`, but all zero on entry; the user leaves it all zero again on leaving.

    Users that touch little of a large array (the fit's model images: each dot draws a small stamp)
    clear what they wrote instead of the whole array. The whole array is cleared only when it is new
    or when its last user left it by an exception.

    Yields
    ------
    warp.array
        A contiguous view of the thread's array, all zero.
    """
    flat = _flat(name, shape, dtype, device)
    clean = _local.__dict__.setdefault("clean", set())
    if name not in clean:
        flat.zero_()
    clean.discard(name)  # in use: not known to be zero until the user is done
    yield flat[: _size(shape)].reshape(tuple(int(s) for s in shape))
    clean.add(name)
