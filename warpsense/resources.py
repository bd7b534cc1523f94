"""Where the packaged configuration files live (`configs/`, installed as `warpsense.configs`): default.toml,
presets/, lenses/ and studies/."""

from __future__ import annotations

from importlib import resources

CONFIG_DIR = resources.files("warpsense.configs")
