"""The default configuration, read once from ``default.toml`` (the paper's set-up, its one home)."""

import tomllib
from importlib import resources

__all__ = ["DEFAULT_CONFIG"]

DEFAULT_CONFIG = tomllib.loads(resources.files("synthbos.raytrace").joinpath("default.toml").read_text())
