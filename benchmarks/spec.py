"""What a campaign is: the render configuration, the methods, the noise levels and the seeds.

The paper's set-up (Rajendran, Bane & Vlachos 2019, section 4) has one home, ``raytrace/default.toml``;
a campaign spec stores only what it changes on top of it (``config``), so every campaign, sweep and
benchmark starts from the same file.
"""

from __future__ import annotations

import copy
import zlib
from dataclasses import asdict, dataclass, field, replace

from synthbos.raytrace import DEFAULT_CONFIG

from .registry import default_methods

__all__ = ["FULL", "QUICK", "REGRESS", "CampaignSpec"]


@dataclass(frozen=True)
class CampaignSpec:
    """What a campaign renders, how it processes, and the seeds that make it repeatable.

    ``config`` holds configuration tables merged over the default (the paper's set-up); ``correlation``
    and ``tracking`` hold settings overrides of those methods (field -> value).
    """

    name: str
    snapshots: tuple = (0, 1, 2, 3, 4)
    pairs_per_snapshot: int = 10
    noise_percent: tuple = (0.0, 1.0, 3.0, 5.0)
    methods: tuple = field(default_factory=default_methods)
    config: dict = field(default_factory=lambda: {"rays": {"per_dot": 10_000}})
    seed: int = 2019
    correlation: dict = field(default_factory=dict)  # CorrelationSettings overrides
    tracking: dict = field(default_factory=dict)  # TrackingSettings overrides

    def as_dict(self) -> dict:
        d = asdict(self)
        d["snapshots"], d["noise_percent"], d["methods"] = (
            list(self.snapshots), list(self.noise_percent), list(self.methods))
        return d

    def with_config(self, overrides: dict) -> CampaignSpec:
        """A copy whose render configuration has ``overrides`` (tables of keys) merged in."""
        cfg = copy.deepcopy(self.config)
        for table, values in overrides.items():
            cfg.setdefault(table, {}).update(values)
        return replace(self, config=cfg)

    def overrides_for(self, method) -> dict:
        """The settings overrides of a registry ``Method`` (by its ``settings_key``)."""
        return dict(getattr(self, method.settings_key, {}) or {})

    def pair_keys(self):
        return [(s, p) for s in self.snapshots for p in range(self.pairs_per_snapshot)]

    def pair_config(self, snapshot: int, pair: int) -> dict:
        cfg = copy.deepcopy(self.config)
        source = cfg.get("volume", {}).get("source", DEFAULT_CONFIG["volume"]["source"])
        if source == "slice":
            cfg.setdefault("volume", {})["snapshot"] = snapshot
        cfg.setdefault("target", {})["seed"] = self._seed("pattern", snapshot, pair)
        cfg.setdefault("rays", {})["seed"] = self._seed("rays", snapshot, pair)
        return cfg

    def noise_seed(self, snapshot: int, pair: int, noise: float, frame: str) -> int:
        return self._seed(f"noise-{noise:g}-{frame}", snapshot, pair)

    def _seed(self, what: str, snapshot: int, pair: int) -> int:
        return zlib.crc32(f"{self.seed}/{what}/{snapshot}/{pair}".encode()) & 0x7FFFFFFF


# The paper's size, meant for a GPU: 5 snapshots x 10 pairs, 10,000 rays per dot.
FULL = CampaignSpec(name="full")
# Reduced: runs on two CPU cores in a few minutes and shows the paper's qualitative result.
QUICK = CampaignSpec(name="quick", pairs_per_snapshot=2, config={"rays": {"per_dot": 100}})
# The CI regression campaign: small and fixed.
REGRESS = CampaignSpec(name="regress", snapshots=(1, 3), pairs_per_snapshot=1, noise_percent=(0.0, 3.0),
                       config={"camera": {"pixels": [256, 256]}, "rays": {"per_dot": 50}})
