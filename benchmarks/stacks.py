"""Stacks: a campaign's tracking items tracked many noisy image pairs at a time (``tracking.stack.track_pairs``).

On a GPU, ``track_pairs`` covers the dots of every pair of a stack with each kernel launch (0.34 ms per
pair in stacks of 400 on an H200 against 23 ms for one ``track_pair``, docs/benchmarks.md), so a
campaign that processes on a GPU groups its tracking items into stacks (``scheduling.run_pipeline``):
the noisy images of every noise level of up to ``stack`` pairs go to the device in one ``track_pairs``
call, made by the process that drives the device, and each item's result goes to the worker processes to
be scored and written, as the correlation's results do. A stack holds image pairs of one shape, one dot
count, one processing device and one set of settings (``registry.stack_settings``); the items of one
noisy image pair with the same settings (``tracking`` and ``tracking-cc``: two columns of one table)
share one image pair of the stack.

``track_pairs`` gives each pair what ``track_pair`` gives it to floating-point rounding (1e-11 px or
less on the campaign's pairs; the predictor's float32 correlations to 1e-6). Whatever else the stack
holds, a pair's table is the same bytes: the model fit's fixed-point sums take their scale from the
pair's own dots (``tests/tracking/test_stack.py``), and on a GPU the residual's stamps are summed in fixed
point. So a resumed campaign, which stacks only the missing items, and a campaign whose pairs several
processes took in another order (``drivers``: 600 of 600 score files the same bytes with one, two and
three on an H100, docs/benchmarks.md) write the same files; a campaign's ``results.csv`` is the same
stacked or not (``tests/benchmarks/test_stacks.py``; the score files agree with item-by-item tracking to
1e-9 px).
"""

from __future__ import annotations

import numpy as np
from synthbos.tracking.stack import pairs_per_call, track_pairs

from synthbos import SynthbosError

from .items import item_images, nominal_positions
from .registry import stack_settings, stacked_result

__all__ = ["DEFAULT_STACK", "Stacks", "check_stack", "default_stack", "describe_stacks", "split_stacked"]

#: Campaign pairs per stack on a GPU unless told (``--stack``): with the paper's four noise levels, 32
#: image pairs of 512 x 512 px and 5,120 dots (some 0.9 GB of device memory, ``pairs_per_call``) per call.
DEFAULT_STACK = 8


def default_stack(scores) -> int:
    """Pairs per stack when none is asked for: :data:`DEFAULT_STACK` where a campaign's tracking runs on a
    GPU, 0 (each item tracked by itself, in a worker process) on the CPU, where the workers already
    spread the pairs over the cores and ``track_pairs`` gains nothing over ``track_pair``.

    Score items are ``(pair path, method, noise, seeds, out, overrides, processing device)``.
    """
    cuda = any(str(args[-1]).startswith("cuda") for args in scores if stack_settings(args[1], args[5]) is not None)
    return DEFAULT_STACK if cuda else 0


def check_stack(stack, methods, overrides_for) -> None:
    """Refuse, in one line, ``stack`` pairs per stack that cannot be: a negative number, or stacks for
    methods none of which a stack tracks (``registry.stack_settings``; ``overrides_for(name)`` gives a
    method's settings overrides)."""
    if stack is None:
        return
    if isinstance(stack, bool) or not isinstance(stack, int) or stack < 0:
        raise SynthbosError(f"--stack must be a whole number of pairs, 0 or more, got {stack!r}")
    if stack and not any(stack_settings(m, overrides_for(m)) is not None for m in methods):
        raise SynthbosError(f"--stack {stack}: none of the methods ({', '.join(methods)}) is tracked in stacks; "
                            "stacks hold the trackers whose identification runs as kernels (tracking, "
                            "tracking-cc)")


def describe_stacks(log, stack=None) -> str:
    """One line on the ``track_pairs`` calls of a :class:`Stacks` ``log``: how many, on which devices, and
    the largest stack in pairs and in noisy image pairs; ``stack`` is the pairs per stack asked for (None:
    the default).

    Examples
    --------
    >>> describe_stacks([{"pairs": 8, "images": 32, "device": "cuda:0"}, {"pairs": 2, "images": 8, "device": "cuda:0"}])
    'tracking in stacks: 2 track_pairs calls on cuda:0, up to 8 pairs (32 image pairs) per call (stack 8, the default)'
    """
    devices = ", ".join(sorted({entry["device"] for entry in log}))
    asked = f"stack {DEFAULT_STACK}, the default" if stack is None else f"stack {stack}"
    return (f"tracking in stacks: {len(log)} track_pairs call{'s' if len(log) != 1 else ''} on {devices}, up to "
            f"{max(e['pairs'] for e in log)} pairs ({max(e['images'] for e in log)} image pairs) per call ({asked})")


def split_stacked(run) -> tuple[list, list]:
    """Split score items into those a stack tracks (``registry.stack_settings``) and the others."""
    stacked = [args for args in run if stack_settings(args[1], args[5]) is not None]
    return stacked, [args for args in run if stack_settings(args[1], args[5]) is None]


class Stacks:
    """The open stacks of a campaign: pair after pair goes in (:meth:`add`); a stack full of ``size``
    pairs (or of as many image pairs as one ``track_pairs`` call holds on the device, ``pairs_per_call``)
    is tracked at once, the rest by :meth:`flush`; :meth:`take` hands out the measured items.

    ``log``: a list that receives, for each ``track_pairs`` call, ``{"pairs", "images", "device"}``.
    """

    def __init__(self, size: int, *, log=None):
        self.size = int(size)
        self.log = log
        self.open: dict = {}  # key -> [(tag, [(reference, gradient, prior, items)])], one entry per pair
        self.done: list = []  # (tag, host tuples of one noisy image pair), in order

    def add(self, tag, pair, runs) -> None:
        """Add pair ``pair`` (``tag``: what :meth:`take` returns with its items) with its ``runs``:
        ``(noisy images, stacked score items)`` of each noisy image pair; track the stacks that are full."""
        prior = None
        mine: dict = {}
        for images, items in runs:
            if not items:
                continue
            prior = nominal_positions(pair) if prior is None else prior
            images = item_images(pair, items[0]) if images is None else images
            by_settings: dict = {}
            for args in items:
                by_settings.setdefault(stack_settings(args[1], args[5]), []).append(args)
            for settings, group in by_settings.items():
                key = (settings, str(group[0][-1]), np.shape(images[0]), len(prior))
                mine.setdefault(key, []).append((*images, prior, group))
        for key, entries in mine.items():
            held = self.open.setdefault(key, [])
            if held and sum(len(e) for _, e in held) + len(entries) > self._limit(key):
                self._track(key)
                held = self.open.setdefault(key, [])
            held.append((tag, entries))
            if len(held) >= self.size:
                self._track(key)

    def flush(self) -> None:
        """Track every open stack."""
        for key in list(self.open):
            self._track(key)

    def take(self) -> list:
        """The measured items so far, and forget them: ``[(tag, [finish_item arguments])]``, one entry per
        noisy image pair, in the order the pairs came."""
        done, self.done = self.done, []
        return done

    @staticmethod
    def _limit(key) -> float:
        _, device, shape, dots = key
        return pairs_per_call(shape, dots, device, on_device=False) or float("inf")

    def _track(self, key) -> None:
        held = self.open.pop(key, [])
        if not held:
            return
        settings, device = key[:2]
        entries = [e for _, pair_entries in held for e in pair_entries]
        refs, grads, priors = (np.stack([e[i] for e in entries]) for i in range(3))
        try:
            tables = track_pairs(refs, grads, prior_xy=priors, settings=settings, device=device)
        except SynthbosError as err:
            paths = sorted({args[0] for e in entries for args in e[3]})
            raise SynthbosError(f"tracking the stack of {', '.join(paths)}: {err}") from None
        rows = iter(tables)
        for tag, pair_entries in held:
            for *_, items in pair_entries:
                table = next(rows).copy()
                self.done.append((tag, [(a[0], a[1], stacked_result(a[1], table, settings), a[4], a[-1])
                                        for a in items]))
        if self.log is not None:
            self.log.append({"pairs": len(held), "images": len(entries), "device": device})
