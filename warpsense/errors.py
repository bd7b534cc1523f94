"""Library exceptions turned into the one-line messages warpsense's own errors quote."""

from __future__ import annotations


def first_line(error: BaseException) -> str:
    """The first line of ``error``'s message, or its type's name when the message is empty (torch, CUDA and
    safetensors messages run to many lines)."""
    message = str(error).strip()
    return message.splitlines()[0] if message else type(error).__name__
