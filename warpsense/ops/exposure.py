"""Exposure gain a(g) = 0.25 + 3.75 sigmoid(g), bounded to [0.25, 4] (eq. 3 of the paper, docs/references.md).

Exposure is one scalar per camera, so it has no Warp kernel of its own: `Camera` folds a(g) into the CFA
responses (phi_eff = a(g) * phi, exact because both are linear), which costs no pass over the image. The standalone
functional below is plain torch for use without a CFA.
"""

from __future__ import annotations

import math

import torch

from warpsense.ops.arguments import check_same_device, check_tensor

GAIN_MIN = 0.25
GAIN_RANGE = 3.75


def exposure_gain(gain_logit: torch.Tensor) -> torch.Tensor:
    """a(g) in [0.25, 4] for a logit g of any shape."""
    check_tensor("exposure_gain", "gain_logit", gain_logit)
    return GAIN_MIN + GAIN_RANGE * torch.sigmoid(gain_logit)


def exposure_logit(gain: float) -> float:
    """The logit g whose gain a(g) is ``gain`` (the inverse of `exposure_gain`, for configs: ``exposure.gain_logit``);
    ``gain`` must lie strictly inside (0.25, 4)."""
    share = (gain - GAIN_MIN) / GAIN_RANGE
    if not 0 < share < 1:
        raise ValueError(f"exposure gain {gain} is outside the exposure stage's range ({GAIN_MIN}, "
                         f"{GAIN_MIN + GAIN_RANGE})")
    return math.log(share / (1 - share))


def exposure(image: torch.Tensor, gain_logit: torch.Tensor) -> torch.Tensor:
    """Scale linear irradiance [B, C, H, W] by a(g) (0-d or 1-element logit g)."""
    check_tensor("exposure", "image", image, 4, "[B, C, H, W]")
    check_tensor("exposure", "gain_logit", gain_logit)
    check_same_device("exposure", image=image, gain_logit=gain_logit)
    if gain_logit.numel() != 1:
        raise ValueError(f"exposure: gain_logit must be 0-d or 1-element (one gain per camera), got "
                         f"{tuple(gain_logit.shape)}")
    return image * exposure_gain(gain_logit).to(image.dtype)
