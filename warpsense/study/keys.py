"""Config keys as a study names and learns them: a value in a camera's name (`value_label`) and the keys a camera can
learn by gradient (`LEARNED_KEYS`), shared by sweeps, maps and searches (a module of its own: each of them imports
it, none of them another)."""

from __future__ import annotations

LEARNED_KEYS = {"optics.f_number": ("optics.f_number_learnable", "f_number"),
                "optics.exposure_ms": ("optics.exposure_learnable", "exposure_ms"),
                "photons.analog_gain": ("photons.gain_learnable", "analog_gain")}
"""Swept or searched config key -> (the config flag that makes it learnable, the key of its learned value in each
epoch's metrics record and in the evaluation's "camera" record)."""


def value_label(value) -> str:
    """A grid value as it appears in a camera name: "1.4" -> "1p4", -2 -> "m2", True -> "true"."""
    if isinstance(value, bool):
        return str(value).lower()
    text = f"{value:g}" if isinstance(value, float) else str(value)
    return text.replace("+", "").replace("-", "m").replace(".", "p")
