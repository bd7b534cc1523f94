"""The device a command or run asks for."""

from __future__ import annotations

import torch


def resolve_device(choice: str) -> torch.device:
    """The device a `warpsense.choices.DEVICES` choice names: "cuda", or "auto" where torch sees a GPU -> cuda;
    otherwise cpu. Asking for "cuda" where torch sees none is a one-line ValueError."""
    if choice == "cuda" and not torch.cuda.is_available():
        build = "this torch build has no CUDA" if torch.version.cuda is None else "torch sees no CUDA GPU"
        raise ValueError(f"device cuda: {build} (torch {torch.__version__}); use cpu or auto (--device, or "
                         "--set run.device=... for train and study)")
    return torch.device("cuda" if choice == "cuda" or (choice == "auto" and torch.cuda.is_available()) else "cpu")
