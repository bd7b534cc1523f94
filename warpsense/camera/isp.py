"""Fixed ISP of the baseline: bilinear demosaic of a known CFA layout and a display gamma (not learnable)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from warpsense.camera.cfa import FILTERS
from warpsense.config import ISPConfig


class FixedISP(nn.Module):
    """RAW [B, 1, H, W] with a fixed RGB layout (letters R, G, B per site) -> display RGB [B, 3, H, W].

    Each channel is interpolated from its own sites by normalised convolution with the bilinear kernel
    [[1, 2, 1], [2, 4, 2], [1, 2, 1]] (exact bilinear demosaicking for Bayer layouts), then x^(1/gamma).
    """

    def __init__(self, letters: list[list[str]], gamma: float = ISPConfig.gamma):
        super().__init__()
        if any(letter not in "RGB" for row in letters for letter in row):
            raise ValueError(f"the fixed ISP needs an R/G/B layout, got {letters}")
        tile = len(letters)
        masks = torch.tensor([[FILTERS[letter] for letter in row] for row in letters]).permute(2, 0, 1)  # [3, T, T]
        self.register_buffer("site_masks", masks)
        bilinear = torch.tensor([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]])
        self.register_buffer("kernel", bilinear.expand(3, 1, 3, 3).clone())
        self.tile = tile
        self.gamma = gamma

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        height, width = raw.shape[-2:]
        reps = (-(-height // self.tile), -(-width // self.tile))
        masks = self.site_masks.repeat(1, *reps)[:, :height, :width].unsqueeze(0).to(raw.dtype)
        sparse = raw * masks
        # a side of one pixel has nothing to reflect (torch refuses it): that side's border repeats its pixel
        mode = "reflect" if min(height, width) > 1 else "replicate"
        numerator = F.conv2d(F.pad(sparse, (1, 1, 1, 1), mode=mode), self.kernel.to(raw.dtype), groups=3)
        denominator = F.conv2d(F.pad(masks, (1, 1, 1, 1), mode=mode), self.kernel.to(raw.dtype), groups=3)
        rgb = numerator / denominator.clamp_min(1e-6)
        return rgb.clamp(1e-6, 1).pow(1.0 / self.gamma)  # clamp away from 0: pow has an infinite slope there
