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

from synthbos import SynthbosError

__all__ = ["hold_freed_memory", "on_device", "per_thread", "scratch"]

#: The share of a GPU's memory that its CUDA memory pool keeps when freed (:func:`hold_freed_memory`).
POOL_HOLD = 0.25

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


def on_device(a, dtype, ndim, device, name):
    """``a`` as a contiguous ``ndim``-D Warp array of ``dtype`` on ``device``: a Warp array as it is (it
    must have that type and lie there), anything NumPy takes uploaded (``wp.vec2d`` from ``(..., 2)``
    floats, ``wp.int32`` as 0/1 masks, other types from float64).

    ``device`` None: a Warp array's own device, else Warp's default. Raises ``SynthbosError`` naming
    ``name``.
    """
    if isinstance(a, wp.array):
        if a.dtype != dtype or a.ndim != ndim or not a.is_contiguous:
            raise SynthbosError(
                f"{name} must be a contiguous {ndim}-D Warp array of {wp.types.type_repr(dtype)}, got a "
                f"{a.ndim}-D {wp.types.type_repr(a.dtype)} one"
            )
        if device is not None and wp.get_device(device) != a.device:
            raise SynthbosError(f"{name} lies on {a.device}, not on {wp.get_device(device)}")
        return a
    if dtype == wp.vec2d:
        arr = np.asarray(a, dtype=np.float64)
        ok = arr.ndim == ndim + 1 and arr.shape[-1] == 2
    elif dtype == wp.int32:
        arr = (np.asarray(a) != 0).astype(np.int32)
        ok = arr.ndim == ndim
    else:
        arr = np.asarray(a, dtype=np.float64)
        ok = arr.ndim == ndim
    if not ok:
        pairs = " (x, y)" if dtype == wp.vec2d else ""
        raise SynthbosError(f"{name} must be a {ndim}-D array{pairs}, got shape {np.shape(a)}")
    return wp.array(np.ascontiguousarray(arr), dtype=dtype, device=wp.get_device(device))


def per_thread(shape, dtype, device, *, name=None):
    """A ``shape`` array whose first axis is the kernel's thread, each thread's part its own: ``name``, the
    thread's workspace (:func:`scratch`), else a new array.

    On the CPU it is contiguous: one thread walks its own part. On a GPU it is the memory of an array
    with that axis last, seen through a transposed view: the parts of a warp's threads lie side by side,
    so the warp reads and writes whole cache lines (the model fit's stamp profiles: 10.7 -> 1.1 ms for
    a 400-pair stack on an H100). The kernels index it the same either way.

    Examples
    --------
    >>> from synthbos.device import init_warp
    >>> init_warp()
    >>> a = per_thread((5, 6, 3), wp.float64, "cpu")
    >>> a.shape, a.is_contiguous
    ((5, 6, 3), True)
    """
    on_cpu = wp.get_device(device).is_cpu
    layout = tuple(shape) if on_cpu else (*shape[1:], shape[0])
    memory = wp.empty(layout, dtype=dtype, device=device) if name is None else scratch(name, layout, dtype, device)
    return memory if on_cpu else memory.transpose((len(shape) - 1, *range(len(shape) - 1)))


def hold_freed_memory(device):
    """Let ``device``'s CUDA memory pool keep up to ``POOL_HOLD`` of the GPU's memory once freed.

    A batch of pairs allocates and frees some GB per call. CUDA's pool returns freed memory to the
    driver at every synchronisation by default (release threshold 0), so each later allocation maps
    its pages afresh, which cost more than the kernels that use them. The threshold is only raised,
    never lowered; nothing happens on the CPU or where the device has no memory pool.
    """
    device = wp.get_device(device)
    if not device.is_cuda or not device.is_mempool_supported:
        return
    hold = int(POOL_HOLD * device.total_memory)
    if wp.get_mempool_release_threshold(device) < hold:
        wp.set_mempool_release_threshold(device, hold)
