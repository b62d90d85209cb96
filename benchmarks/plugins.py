"""Methods from installed packages: the ``synthbos.methods`` entry-point group.

A package adds a method by naming it in its ``pyproject.toml``::

    [project.entry-points."synthbos.methods"]
    phase-correlation = "synthbos_phasecorr:METHOD"

The entry point's name is the method's name; its object is a ``method_api.Method``, or a function
without arguments that returns one. The registry (``registry.METHODS``) loads the plugins when a
method outside the built-in ones is asked for (only the entry point of that name) or when every
method is listed (all of them). A plugin that fails to import, or whose method is malformed
(``method_api.check_method``), or whose name is taken, is skipped with one :class:`PluginWarning`
naming the entry point and its package; the other methods still work. A plugin never joins the
default campaign, so installing one changes no result of ``paper``, ``sweep`` or ``regress`` until
it is named with ``--methods``.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from importlib.metadata import entry_points

from synthbos import SynthbosError

from .method_api import Method, check_method

__all__ = ["GROUP", "PluginWarning", "load_plugins"]

GROUP = "synthbos.methods"


class PluginWarning(UserWarning):
    """A method plugin was skipped (it failed to import, or its method is malformed)."""


def _origin(ep) -> tuple[str, str]:
    dist = getattr(ep, "dist", None)
    if dist is None:
        return "an unknown package", ""
    return dist.metadata["Name"] or dist.name, dist.version


def _load(ep, taken) -> Method:
    obj = ep.load()
    method = obj if isinstance(obj, Method) or not callable(obj) else obj()
    check_method(method, taken=taken)
    if method.name != ep.name:
        raise SynthbosError(f"the entry point is named {ep.name!r} but its method {method.name!r}")
    return method


def load_plugins(*, taken=(), name=None) -> tuple[dict[str, Method], dict[str, str]]:
    """The methods of the installed plugins, and what went wrong with the others.

    Parameters
    ----------
    taken : collection of str
        Names already registered (the built-in methods): a plugin of such a name is refused.
    name : str, optional
        Load only the entry points of this name.

    Returns
    -------
    methods : dict
        Name -> ``Method`` (with ``source`` set to its package and version and ``in_default_campaign``
        off), in the order of the names.
    problems : dict
        Name -> one line for each skipped plugin; each was also issued as a :class:`PluginWarning`.
    """
    found = entry_points(group=GROUP) if name is None else entry_points(group=GROUP, name=name)
    methods, problems = {}, {}
    for ep in sorted(found, key=lambda e: (e.name, _origin(e)[0])):
        package, version = _origin(ep)
        try:
            if ep.name in methods:
                raise SynthbosError(f"{methods[ep.name].source} registers {ep.name!r} already")
            method = _load(ep, taken)
        except Exception as err:  # any fault of someone else's package skips it, with a warning
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            problems[ep.name] = f"method plugin {ep.name!r} ({package} {version}) skipped: {reason}".replace(" )", ")")
            warnings.warn(problems[ep.name], PluginWarning, stacklevel=2)
            continue
        methods[ep.name] = replace(method, source=f"{package} {version}".strip(), in_default_campaign=False)
    return methods, problems
