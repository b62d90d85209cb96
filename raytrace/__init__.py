"""The renderer: ray-traced synthetic BOS image pairs with exact per-dot ground truth.

Main entry points: ``render_pair`` (configuration in, ``Pair`` out), ``load_config``,
``write_pair`` / ``read_pair`` (the HDF5 pair file) and ``add_noise`` (seeded sensor noise).
"""

from .config import DEFAULT_CONFIG, SETUPS, config_to_toml, load_config, setup_tables
from .pairfile import SIGN_CONVENTION, Pair, read_pair, write_pair
from .render import RenderPlan, plan_render, render_pair
from .sensor import add_noise

__all__ = [
    "DEFAULT_CONFIG",
    "SETUPS",
    "SIGN_CONVENTION",
    "Pair",
    "RenderPlan",
    "add_noise",
    "config_to_toml",
    "load_config",
    "plan_render",
    "read_pair",
    "render_pair",
    "setup_tables",
    "write_pair",
]
