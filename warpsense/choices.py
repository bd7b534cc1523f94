"""Every set of named choices a user picks from, defined once.

The config (`warpsense.config`) validates against these tuples and the CLI offers them; the modules that implement
a choice import its names from here. This module imports neither torch nor Warp, so the config and ``--help`` stay
fast. Registries that map a name to an implementation (datasets, models) are checked against these names by tests.
"""

from __future__ import annotations

DEVICES = ("auto", "cpu", "cuda")
"""Where a command runs: ``auto`` takes CUDA when torch sees a GPU."""

DATASETS = ("scenes", "camvid", "cityscapes", "kitti360")
"""Dataset kinds (`warpsense.data.DATASETS`); ``scenes`` is the procedural street-scene generator."""

ON_DEVICE_MODES = ("auto", "always", "never")
"""Whether the decoded training set is kept on the GPU (`warpsense.data.on_device`)."""

PSF_METHODS = ("auto", "direct", "conv2d", "fft", "patch")
"""PSF-convolution methods (`warpsense.ops.psf.psf_conv`)."""

CFA_LAYOUTS = {
    "RGGB": ("RG", "GB"), "BGGR": ("BG", "GR"), "GRBG": ("GR", "BG"), "GBRG": ("GB", "RG"),
    "RCCC": ("RC", "CC"), "RCCB": ("RC", "CB"),
}
"""2 x 2 colour filter layouts, row by row (R, G, B filters and C = clear, as on RCCC automotive sensors)."""

BAYER_LAYOUTS = tuple(name for name, rows in CFA_LAYOUTS.items() if set("".join(rows)) <= set("RGB"))
"""The layouts with red, green and blue filters only: those a DNG's CFA pattern can be."""

CFA_MODES = ("softmax", "free", "fixed")
"""How the CFA responses are parametrised (`warpsense.camera.cfa.CFA`)."""

QUANTIZE_MODES = ("full_well", "max")
"""ADC ranges: the fixed white level, or each image's maximum (`warpsense.ops.quantize`)."""

COMPILE_MODES = ("off", "default", "reduce-overhead", "max-autotune")
"""``torch.compile`` modes for the training step (``off``: eager)."""

SELF_CAPTURING_COMPILE_MODES = ("reduce-overhead", "max-autotune")
"""Compile modes that capture CUDA graphs themselves (not combinable with ``train.cuda_graph``)."""

MODEL_NAMES = ("dsunet",)
"""Segmentation networks (`warpsense.models.MODELS`)."""
