"""Differentiable camera ops, the training loss's terms (softmax with per-pixel cross-entropy, Lovasz-softmax,
edge-aware smoothness), the decoder's upsampling, the network's batch norm + ReLU and squeeze-and-excitation gate:
Warp kernels registered into torch autograd (functional API, docs/references.md)."""

from warpsense.ops.batchnorm import batch_norm_relu
from warpsense.ops.cfa import cfa_mosaic
from warpsense.ops.cross_entropy import softmax_cross_entropy
from warpsense.ops.exposure import exposure, exposure_gain
from warpsense.ops.gate import channel_gate
from warpsense.ops.lovasz import lovasz_softmax
from warpsense.ops.noise import poisson_gaussian, poisson_gaussian_exact
from warpsense.ops.psf import PSF_METHODS, psf_conv
from warpsense.ops.quantize import QUANTIZE_MODES, quantize_ste
from warpsense.ops.smoothness import edge_aware_smoothness
from warpsense.ops.upsample import upsample_concat

__all__ = [
    "batch_norm_relu", "cfa_mosaic", "channel_gate", "edge_aware_smoothness", "exposure", "exposure_gain",
    "lovasz_softmax", "poisson_gaussian", "poisson_gaussian_exact", "psf_conv", "quantize_ste", "softmax_cross_entropy",
    "upsample_concat", "PSF_METHODS", "QUANTIZE_MODES",
]
