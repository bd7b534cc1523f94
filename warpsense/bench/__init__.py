"""Benchmarks: the kernels against their references, error against run time, and training against the plain-torch
baseline."""

BENCH_SUITES = ("kernels", "accuracy", "train", "time-to-accuracy", "all")
"""Suites of `warpsense bench`; "all" runs kernels, accuracy and train (time-to-accuracy trains for minutes)."""
