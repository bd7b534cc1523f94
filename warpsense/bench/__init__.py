"""Benchmarks: the kernels against their references, error against run time, and training against the plain-torch
baseline."""

BENCH_SUITES = ("kernels", "accuracy", "train", "time-to-accuracy", "study", "all")
"""Suites of `warpsense bench`; "all" runs kernels, accuracy and train (time-to-accuracy trains for minutes, study
trains a plan's cells twice)."""


def parse_size(text: str, option: str, example: str, minimum: int = 1) -> tuple[int, int]:
    """``HxW`` (e.g. "192x640") as (height, width), both integers >= ``minimum``; otherwise a ValueError naming
    ``option`` and giving ``example``."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(part.isdigit() and int(part) >= max(minimum, 1) for part in parts):
        least = f" with both sides >= {minimum}" if minimum > 1 else ""
        raise ValueError(f"{option} must be HxW{least}, e.g. {example}, got {text!r}")
    return int(parts[0]), int(parts[1])
