"""Where the packaged configuration files live (`configs/`, installed as `warpsense.configs`): default.toml,
presets/, lenses/ and studies/."""

from __future__ import annotations

from importlib import resources

CONFIG_DIR = resources.files("warpsense.configs")


def shipped_studies() -> list[str]:
    """The names of the study plans shipped in configs/studies/ (what `warpsense study run NAME` takes)."""
    return sorted(p.name[:-5] for p in (CONFIG_DIR / "studies").iterdir() if p.name.endswith(".toml"))
