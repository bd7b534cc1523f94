"""Where the CFA's sites fall on a capture: mirroring a capture without moving a pixel off its filter, and the crop
that puts a file's 2x2 Bayer layout in the phase a model was trained with."""

from __future__ import annotations

import torch
from torch.nn import functional as F


def cfa_flip(sensed: torch.Tensor, tile: int) -> tuple[torch.Tensor, int]:
    """Mirror a capture [B, C, H, W] left-right so that every pixel keeps its CFA site.

    A plain flip moves column x to W - 1 - x, whose site differs when W is even (2x2 tiles); shifting the mirrored
    frame by ``shift`` = (W - 1) mod 2 columns (edge column repeated) restores the phase. Tiles wider than 2 have no
    such shift.

    Args:
        sensed: the capture, its columns in CFA order.
        tile: the CFA tile's side (1: no CFA phase, or an ISP's full-colour output).

    Returns:
        (mirrored capture, shift) for `cfa_unflip`.

    Raises:
        ValueError: a tile wider than 2.
    """
    if tile > 2:
        raise ValueError(f"flip test-time augmentation keeps the CFA phase only for 1x1 and 2x2 tiles, "
                         f"got {tile}x{tile}")
    width = sensed.shape[-1]
    shift = (width - 1) % 2 if tile == 2 else 0
    mirrored = sensed.flip(-1)
    if shift:
        mirrored = F.pad(mirrored, (shift, 0, 0, 0), mode="replicate")[..., :width]
    return mirrored, shift


def cfa_unflip(prediction: torch.Tensor, shift: int) -> torch.Tensor:
    """Map a prediction on `cfa_flip`'s capture back to the original columns (the ``shift`` edge columns it cannot
    see repeat their neighbour)."""
    restored = prediction[..., shift:].flip(-1)
    return F.pad(restored, (shift, 0, 0, 0), mode="replicate") if shift else restored


def phase_offset(file_pattern: str, model_pattern: str) -> tuple[int, int]:
    """The (dy, dx) crop that turns a file's 2x2 layout into a model's, e.g. GBRG -> RGGB is (1, 0).

    Args:
        file_pattern: the capture's four CFA letters, row by row (a raw file's ``cfa_pattern``).
        model_pattern: the layout the model was trained with.

    Raises:
        ValueError: no one-pixel crop gives ``model_pattern`` (the two hold other filters).
    """
    grid = [file_pattern[:2], file_pattern[2:]]
    for dy in (0, 1):
        for dx in (0, 1):
            shifted = "".join(grid[(dy + y) % 2][(dx + x) % 2] for y in (0, 1) for x in (0, 1))
            if shifted == model_pattern:
                return dy, dx
    raise ValueError(f"layout {file_pattern} cannot be cropped into {model_pattern}")
