"""Library exceptions turned into the one-line messages warpsense's own errors quote."""

from __future__ import annotations

import re


def first_line(error: BaseException) -> str:
    """The first line of ``error``'s message, or its type's name when the message is empty (torch, CUDA and
    safetensors messages run to many lines)."""
    message = str(error).strip()
    return message.splitlines()[0] if message else type(error).__name__


_WORKER_ERROR = re.compile(r"Caught (\w+) in DataLoader worker process \d+\.\nOriginal Traceback")


def worker_message(message: str) -> str:
    """An error's message without the traceback a torch DataLoader worker wraps it in: torch raises a worker's error
    again in the main process with the worker's whole traceback as its message ("Caught DatasetError in DataLoader
    worker process 0.", "Original Traceback ...", ..., "warpsense.data.datasets.DatasetError: <message>"), which
    would print as many lines; this returns <message>, and any other message as it is."""
    match = _WORKER_ERROR.match(message)
    if match is None:
        return message
    last = message.rstrip().splitlines()[-1]
    _, _, text = last.partition(f"{match.group(1)}: ")
    return text or last
