"""Benchmarks: the kernels against their references, error against run time, and training against the plain-torch
baseline."""

BENCH_SUITES = ("kernels", "accuracy", "train", "time-to-accuracy", "study", "all")
"""Suites of `warpsense bench`; "all" runs kernels, accuracy and train (time-to-accuracy trains for minutes, study
trains a plan's cells twice)."""


def parse_size(text: str, option: str, example: str) -> tuple[int, int]:
    """``HxW`` (e.g. "192x640") as (height, width), both positive integers; otherwise a ValueError naming
    ``option`` and giving ``example``."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(part.isdigit() and int(part) > 0 for part in parts):
        raise ValueError(f"{option} must be HxW, e.g. {example}, got {text!r}")
    return int(parts[0]), int(parts[1])
