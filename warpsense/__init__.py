"""warpsense: differentiable camera simulation in NVIDIA Warp, co-designed with a compact segmentation network."""

__version__ = "0.1.0"
