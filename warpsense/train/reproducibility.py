"""`run.deterministic`: bitwise-repeatable training, the way torch offers it (docs: "Reproducibility")."""

from __future__ import annotations

import contextlib
import os

import torch


@contextlib.contextmanager
def deterministic_algorithms(enabled: bool):
    """While active (``enabled``): torch's deterministic algorithms (operations without a deterministic CUDA
    implementation warn once instead of failing), cuDNN's deterministic convolutions without benchmarking, and the
    cuBLAS workspace setting deterministic matrix products need (``CUBLAS_WORKSPACE_CONFIG``, unless already set:
    it must be set before cuBLAS starts, so set it in the environment when CUDA is already in use). The networks
    switch their bilinear upsampling and adaptive pooling to `warpsense.models.resample` meanwhile; the Warp
    kernels are deterministic by design. The previous settings come back on exit (the environment variable stays)."""
    if not enabled:
        yield
        return
    previous = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled(),
                torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark)
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(previous[0], warn_only=previous[1])
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = previous[2], previous[3]
