"""The default configuration, read once from ``default.toml`` (the paper's set-up, its one home), and the
named set-ups: small TOML files beside it that hold only what they change from the default."""

import tomllib
from importlib import resources

from synthbos import SynthbosError

__all__ = ["DEFAULT_CONFIG", "SETUPS", "setup_tables"]

DEFAULT_CONFIG = tomllib.loads(resources.files("synthbos.raytrace").joinpath("default.toml").read_text())

#: The named set-ups (``synthbos render|paper|sweep --setup NAME``): name -> (package file, what it is).
#: ``docs/fig5.md`` tells why each exists and what it gives.
SETUPS = {
    "default": ("default.toml", "the paper's set-up (section 4) at f/11: the finite aperture averages the flow"),
    "narrow": ("narrow.toml", "the default at f/32: a narrow cone, under which the paper's Figure 5 ordering holds"),
}


def setup_tables(name: str) -> dict:
    """The configuration tables a named set-up changes from the default (``{}`` for ``"default"``).

    Parameters
    ----------
    name : str
        A key of ``SETUPS``.

    Returns
    -------
    dict
        Tables of keys, to merge over ``DEFAULT_CONFIG`` (``load_config(..., setup=name)`` does it).

    Examples
    --------
    >>> setup_tables("default")
    {}
    >>> setup_tables("narrow")
    {'camera': {'f_number': 32.0}}
    """
    if name not in SETUPS:
        raise SynthbosError(f"unknown set-up {name!r}; named set-ups: {', '.join(SETUPS)}")
    if name == "default":
        return {}
    return tomllib.loads(resources.files("synthbos.raytrace").joinpath(SETUPS[name][0]).read_text())
