"""Packaged configs: default.toml, presets/ (overrides only) and lenses/ (JSON lens files)."""
