"""Benchmarks: the kernels against their references, error against run time, and training against the plain-torch
baseline."""

BENCH_SUITES = ("kernels", "accuracy", "train", "all")
