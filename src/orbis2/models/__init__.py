"""Networks, one file per model with all of its blocks."""


def preset_config(presets: dict[str, dict], kind: str, preset: str, overrides: dict) -> dict:
    """A preset's settings with ``overrides`` applied; an unknown preset or setting raises ``KeyError``."""
    if preset not in presets:
        raise KeyError(f"unknown {kind} preset {preset!r}; choose from {sorted(presets)}")
    cfg = dict(presets[preset])
    unknown = set(overrides) - set(cfg)
    if unknown:
        raise KeyError(f"unknown {kind} setting(s) {sorted(unknown)}; known: {sorted(cfg)}")
    cfg.update(overrides)
    return cfg
