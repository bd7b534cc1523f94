"""The device a command or run asks for."""

from __future__ import annotations

import torch


def resolve_device(choice: str) -> torch.device:
    """The device a `warpsense.choices.DEVICES` choice names: "cuda", or "auto" where torch sees a GPU -> cuda;
    otherwise cpu."""
    return torch.device("cuda" if choice == "cuda" or (choice == "auto" and torch.cuda.is_available()) else "cpu")
