"""Exposure gain a(g) = 0.25 + 3.75 sigmoid(g), bounded to [0.25, 4] (paper eq. 3).

Exposure is one scalar per camera, so it has no Warp kernel of its own: `Camera` folds a(g) into the CFA
responses (phi_eff = a(g) * phi, exact because both are linear), which costs no pass over the image. The standalone
functional below is plain torch for use without a CFA.
"""

from __future__ import annotations

import torch

GAIN_MIN = 0.25
GAIN_RANGE = 3.75


def exposure_gain(gain_logit: torch.Tensor) -> torch.Tensor:
    """a(g) in [0.25, 4] for a logit g of any shape."""
    return GAIN_MIN + GAIN_RANGE * torch.sigmoid(gain_logit)


def exposure(image: torch.Tensor, gain_logit: torch.Tensor) -> torch.Tensor:
    """Scale linear irradiance [B, C, H, W] by a(g) (0-d logit g)."""
    return image * exposure_gain(gain_logit).to(image.dtype)
