"""Small render configurations for the renderer tests (imported by the test modules)."""

SMALL = {"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 200}, "target": {"dots_per_32px": 8}}


def small_config(**tables):
    """SMALL with the given tables' keys merged in: small_config(volume={...}, rays={...})."""
    cfg = {k: dict(v) for k, v in SMALL.items()}
    for table, values in tables.items():
        cfg.setdefault(table, {}).update(values)
    return cfg
