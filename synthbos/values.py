"""The one home of value checks every package shares, and of the one-line error message.

``number`` checks one setting (a configuration key, a command-line option) against its allowed range
and names the key and the range when it refuses it; ``optional_number`` and ``numbers`` are its
forms for "None or a number" and for a list of numbers; ``check_ranges`` applies a table of such
bounds to a settings object. ``shorten`` cuts a long value for a message, and ``error_line`` makes
the one line the command line prints for a ``SynthbosError`` (at most ``MAX_LINE`` characters, long
values cut with an ellipsis).
"""

from __future__ import annotations

import math
import re

from synthbos import SynthbosError

__all__ = [
    "MAX_LINE",
    "check_ranges",
    "cut",
    "error_line",
    "number",
    "numbers",
    "optional_number",
    "shorten",
]

#: Longest line the command line prints for an error (a longer message is cut, its values first).
MAX_LINE = 200
#: Longest value a message quotes whole (a longer one keeps its start and end around an ellipsis).
MAX_VALUE = 60


def shorten(value, limit: int = MAX_VALUE) -> str:
    """``repr(value)`` cut to ``limit`` characters (see :func:`cut`), for a value quoted in a message."""
    return cut(_safe_repr(value, limit), limit)


def cut(text: str, limit: int = MAX_VALUE) -> str:
    """A text of at most about ``limit`` characters: a longer one keeps its first two thirds and its
    last third of ``limit`` around ``"..."`` and says how long it was, so a 100 MB string or a list of a
    thousand values stays readable."""
    if len(text) <= limit:
        return text
    head, tail = (2 * limit) // 3, limit // 3
    return f"{text[:head]}...{text[-tail:]} ({len(text):,} characters)"


def _safe_repr(value, limit):
    """``repr`` of a value, without building the whole text of a huge sequence first."""
    if isinstance(value, list | tuple) and len(value) > limit:
        return f"a {type(value).__name__} of {len(value):,} values starting {list(value[:4])!r}"
    return repr(value)


def _fmt(v):
    return f"{v:g}" if isinstance(v, float) else str(v)


def _range_text(minimum=None, maximum=None, above=None, below=None):
    low = f"> {_fmt(above)}" if above is not None else (f">= {_fmt(minimum)}" if minimum is not None else "")
    high = f"< {_fmt(below)}" if below is not None else (f"<= {_fmt(maximum)}" if maximum is not None else "")
    return " and ".join(s for s in (low, high) if s)


def number(name, value, *, integer=False, minimum=None, maximum=None, above=None, below=None, why="",
           infinite=False):
    """Check one setting and return it as float (or int with ``integer``).

    Parameters
    ----------
    name : str
        The key as the user wrote it, ``table.key`` (or ``table.key[i]``).
    value : object
        The value read.
    integer : bool
        A whole number is required (returned as int; floats such as 3.0 are accepted).
    minimum, maximum : float, optional
        Inclusive bounds.
    above, below : float, optional
        Exclusive bounds (``above=0`` for "> 0").
    why : str
        The reason for the range, appended to the message.
    infinite : bool
        ``+inf`` is allowed (a setting where it means "no limit"); NaN never is.

    Raises
    ------
    SynthbosError
        Not a number (booleans and strings included), not finite, not whole, or out of range; the
        message names ``name`` and the allowed range.
    """
    rng = _range_text(minimum, maximum, above, below)
    allowed = f" ({rng})" if rng else ""
    if isinstance(value, bool) or (not isinstance(value, int | float) and not _is_numpy_number(value)):
        raise SynthbosError(f"{name} must be a number{allowed}, got {shorten(value)}")
    if not isinstance(value, int):
        value = float(value)
    if isinstance(value, float) and not math.isfinite(value) and not (infinite and value == math.inf):
        raise SynthbosError(f"{name} must be finite{allowed}, got {value!r}")
    if integer and (not math.isfinite(value) or int(value) != value):
        raise SynthbosError(f"{name} must be a whole number{allowed}, got {shorten(value)}")
    bad = (
        (above is not None and not value > above)
        or (below is not None and not value < below)
        or (minimum is not None and value < minimum)
        or (maximum is not None and value > maximum)
    )
    if bad:
        raise SynthbosError(f"{name} must be {rng}, got {shorten(value)}{why}")
    return int(value) if integer else float(value)


def _is_numpy_number(value):
    kind = getattr(getattr(value, "dtype", None), "kind", None)
    return kind in ("i", "u", "f") and getattr(value, "ndim", 1) == 0


def optional_number(name, value, **bounds):
    """``None`` (kept), or a number checked by :func:`number`."""
    return None if value is None else number(name, value, **bounds)


def numbers(name, value, *, sizes=None, max_size=None, **bounds):
    """A list of numbers, each checked by :func:`number` (``name[i]``); returns a tuple.

    ``sizes``: the allowed lengths; ``max_size``: the longest list allowed (with ``sizes`` unset).
    """
    if isinstance(value, str | bytes) or not hasattr(value, "__len__"):
        raise SynthbosError(f"{name} must be a list of numbers, got {shorten(value)}")
    n = len(value)
    if sizes is not None and n not in sizes:
        want = " or ".join(map(str, sizes))
        raise SynthbosError(f"{name} must be a list of {want} numbers, got {n}: {shorten(value)}")
    if max_size is not None and not 1 <= n <= max_size:
        raise SynthbosError(f"{name} must be a list of 1 to {max_size} numbers, got {n}")
    return tuple(number(f"{name}[{i}]", v, **bounds) for i, v in enumerate(value))


def check_ranges(obj, ranges: dict, prefix: str) -> None:
    """Check the attributes of a settings object against a table ``{field: bounds}``.

    Each ``bounds`` is a dict of :func:`number`'s keywords, plus ``optional=True`` (None is allowed)
    and ``list=dict(sizes=..., max_size=...)`` (a list of such numbers). The message names the key as
    ``prefix`` + field (``tracking.max_displacement``).
    """
    for field, bounds in ranges.items():
        bounds = dict(bounds)
        optional = bounds.pop("optional", False)
        listing = bounds.pop("list", None)
        value = getattr(obj, field)
        if optional and value is None:
            continue
        name = f"{prefix}{field}"
        if listing is not None:
            numbers(name, value, **listing, **bounds)
        else:
            number(name, value, **bounds)


#: Longest word (a path, a value) an error line keeps whole.
MAX_WORD = 120
def error_line(err) -> str:
    """The line printed for a ``SynthbosError``: ``synthbos: error: ...``, at most ``MAX_LINE`` characters.

    Line breaks become spaces; while the line is too long, its long words (paths, values) are cut in the
    middle, first to ``MAX_WORD`` characters, then shorter; whatever is still too long is cut at the end
    with ``"..."``.
    """
    text = str(err)
    if len(text) > 100 * MAX_LINE:  # never split a 100 MB message into words
        text = f"{text[: 50 * MAX_LINE]} ... {text[-50 * MAX_LINE:]}"
    text = " ".join(text.split())
    line = f"synthbos: error: {text}"
    for limit in (MAX_WORD, 80, 50, 30):  # long words (paths, values) give way first, keeping their ends
        if len(line) <= MAX_LINE:
            break
        line = re.sub(rf"\S{{{limit + 1},}}", lambda m, n=limit: _cut_word(m.group(0), n), line)
    if len(line) > MAX_LINE:
        line = line[: MAX_LINE - 3] + "..."
    return line


def _cut_word(word: str, limit: int) -> str:
    """A word of ``limit`` characters: its first third and last two thirds around ``"..."`` (a path keeps
    the file's name)."""
    head = limit // 3
    return f"{word[:head]}...{word[-(limit - head - 3):]}"
