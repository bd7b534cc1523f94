"""Sensor noise stage N (paper eq. 5)."""

from __future__ import annotations

import torch
from torch import nn

from warpsense.ops.noise import poisson_gaussian, poisson_gaussian_exact


class SensorNoise(nn.Module):
    """Poisson-Gaussian noise with shot (variance coefficient) and read (std) levels.

    Training draws a new seed from torch's generator every call (so a seeded run is reproducible); eval uses
    ``eval_seed``. Learnable levels are bounded to [0, 2x] their initial values: level = 2 * init * sigmoid(p).
    ``exact=True`` samples true Poisson photon counts (eval only, not differentiable).
    """

    def __init__(self, shot: float = 0.015, read: float = 0.002, learnable: bool = False, eval_seed: int = 1234):
        super().__init__()
        if shot < 0 or read < 0:
            raise ValueError(f"noise levels must be >= 0, got shot={shot}, read={read}")
        self.register_buffer("shot_init", torch.tensor(float(shot)))
        self.register_buffer("read_init", torch.tensor(float(read)))
        self.shot_logit = nn.Parameter(torch.tensor(0.0), requires_grad=learnable)
        self.read_logit = nn.Parameter(torch.tensor(0.0), requires_grad=learnable)
        self.eval_seed = eval_seed
        self.scale = 1.0
        self.exact = False

    def levels(self) -> tuple[torch.Tensor, torch.Tensor]:
        shot = 2 * self.shot_init * torch.sigmoid(self.shot_logit) * self.scale**2
        read = 2 * self.read_init * torch.sigmoid(self.read_logit) * self.scale
        return shot, read

    def next_seed(self) -> int:
        if self.training:
            return int(torch.randint(0, 2**31 - 1, (1,)).item())
        return self.eval_seed

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        shot, read = self.levels()
        if self.exact:
            return poisson_gaussian_exact(raw, shot, read, self.next_seed())
        return poisson_gaussian(raw, shot, read, self.next_seed())
