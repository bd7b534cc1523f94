"""Leave out what a scene does not need: crop PSF support and collapse field-invariant grids."""

from __future__ import annotations

import numpy as np
import torch


def crop_to_energy(psf: torch.Tensor, eps: float) -> torch.Tensor:
    """Crop [C, Gy, Gx, K, K] to the smallest odd K' (centred) whose window holds >= 1 - eps of every PSF's energy,
    then renormalise each PSF to sum 1. eps = 0 keeps K."""
    size = psf.shape[-1]
    total = psf.sum(dim=(-2, -1))
    for new_size in range(1, size + 1, 2):
        start = (size - new_size) // 2
        window = psf[..., start : start + new_size, start : start + new_size]
        if bool((window.sum(dim=(-2, -1)) >= (1 - eps) * total).all()):
            return window / window.sum(dim=(-2, -1), keepdim=True)
    return psf


def collapse_grid(psf: torch.Tensor, tolerance: float) -> torch.Tensor:
    """Return a [C, 1, 1, K, K] mean PSF if no node differs from it by more than ``tolerance`` (L1 distance, a
    fraction of the PSF's unit energy), else ``psf`` unchanged."""
    mean = psf.mean(dim=(1, 2), keepdim=True)
    if float((psf - mean).abs().sum(dim=(-2, -1)).max()) <= tolerance:
        return mean
    return psf


def display_half_width(psf: np.ndarray, level: float = 1e-2) -> int:
    """Half width of the central window shown for a PSF grid [..., K, K] (each PSF scaled to peak 1): one pixel
    beyond the farthest pixel above ``level`` in any PSF, at most K // 2. Without it the tails of a large K shrink
    the cores to dots."""
    centre = psf.shape[-1] // 2
    visible = np.argwhere(psf.reshape(-1, *psf.shape[-2:]).max(axis=0) > level)
    if not len(visible):
        return centre
    return min(int(np.abs(visible - centre).max()) + 1, centre)
