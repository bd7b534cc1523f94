"""Every set of named choices a user picks from, defined once.

The config (`warpsense.config`) validates against these tuples and the CLI offers them; the modules that implement
a choice import its names from here. This module imports neither torch nor Warp, so the config and ``--help`` stay
fast. Registries that map a name to an implementation (datasets, models) are checked against these names by tests.
"""

from __future__ import annotations

DEVICES = ("auto", "cpu", "cuda")
"""Where a command runs: ``auto`` takes CUDA when torch sees a GPU."""

DATASETS = ("scenes", "camvid", "cityscapes", "kitti360", "folder")
"""Dataset kinds (`warpsense.data.DATASETS`); ``scenes`` is the procedural street-scene generator; ``folder`` is a
CamVid-layout folder with the user's class table (``data.classes_file``, `warpsense.data.folder`)."""

SCENE_SPLITS = ("train", "val")
"""The generated scenes' splits, each its own stream of the generator."""

ON_DEVICE_MODES = ("auto", "always", "never")
"""Whether the decoded training set is kept on the GPU (`warpsense.data.on_device`)."""

SCALE_FILLS = ("cover", "reflect")
"""How a training crop is filled where the rescaled frame is smaller than it (`warpsense.data.transforms`):
``cover`` raises the scale until the frame covers the crop; ``reflect`` keeps the drawn scale and mirrors the frame
into the rest of the crop, labelled ignore there (real zoom-out, and no black pixels for the camera to see)."""

PSF_METHODS = ("auto", "direct", "conv2d", "fft", "patch")
"""PSF-convolution methods (`warpsense.ops.psf.psf_conv`)."""

RENDER_PRECISIONS = ("float32", "float64")
"""Precisions of the lens's pupil FFTs (`warpsense.optics.lens.Lens.psf_at`): torch dtype names."""

CFA_LAYOUTS = {
    "RGGB": ("RG", "GB"), "BGGR": ("BG", "GR"), "GRBG": ("GR", "BG"), "GBRG": ("GB", "RG"),
    "RCCC": ("RC", "CC"), "RCCB": ("RC", "CB"), "RYYB": ("RY", "YB"),
}
"""2 x 2 colour filter layouts, row by row (R, G, B filters, C = clear as on RCCC automotive sensors, Y = yellow as on
RYYB phone sensors)."""

CFA_FILTERS = "RGBCY"
"""The filter letters (`warpsense.camera.cfa.FILTERS` gives each one's transmittance per band)."""

BAYER_LAYOUTS = tuple(name for name, rows in CFA_LAYOUTS.items() if set("".join(rows)) <= set("RGB"))
"""The layouts with red, green and blue filters only: those a DNG's CFA pattern can be."""

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp")
"""sRGB image files (scenes `warpsense simulate` captures; not raw captures)."""

CFA_MODES = ("softmax", "gumbel", "free", "fixed")
"""How the CFA responses are parametrised (`warpsense.camera.cfa.CFA`)."""

QUANTIZE_MODES = ("full_well", "max")
"""ADC ranges: the fixed white level, or each image's maximum (`warpsense.ops.quantize`)."""

COMPILE_MODES = ("off", "default", "reduce-overhead", "max-autotune")
"""``torch.compile`` modes for the training step (``off``: eager)."""

SELF_CAPTURING_COMPILE_MODES = ("reduce-overhead", "max-autotune")
"""Compile modes that capture CUDA graphs themselves (not combinable with ``train.cuda_graph``)."""

MODEL_INPUTS = ("sensor", "srgb")
"""What the network reads: the camera's output (RAW, or RGB through the fixed ISP) or the clean sRGB frame itself
(an RGB teacher for distillation, `warpsense.system.model.SensingModel`)."""

MODEL_NAMES = ("dsunet",)
"""Segmentation networks (`warpsense.models.MODELS`)."""

DISTILL_MODES = ("pixel",)
"""How a student's logits match its teacher's (`warpsense.train.losses.DISTILLATION`): per pixel over the classes
(Hinton et al. 2015). The channel-wise mode was retired (`warpsense.config.RETIRED_VALUES`)."""

MODEL_CONTEXTS = ("none", "pyramid")
"""Context modules at the networks' 1/16 bottleneck (`warpsense.models.dsunet.CONTEXTS`)."""

LIGHT_LEVELS = {"night": 70.0, "dusk": 700.0, "day": 7000.0}
"""Named scene light levels of the photon budget (`warpsense.camera.photons`): the electrons a mid-grey patch (18%
linear reflectance) gives a clear pixel of the reference pixel (3 um pitch, quantum efficiency 0.6) at f/2 in 10 ms.
"night" is calibrated so that a CamVid frame (mean linear radiance 0.26) gives its green pixels the electrons of the
normalised default camera (33 e- at the mean: 0.5 of a 66.7 e- well); dusk and day are 10x and 100x brighter."""

MPS_MODES = ("auto", "on", "off")
"""``study run --mps``: auto (with more than one cell per GPU, where the control program is on the PATH), on
(required), off (`warpsense.study.mps`)."""
