"""warpsense: differentiable camera simulation in NVIDIA Warp, co-designed with a compact segmentation network."""

import importlib

__version__ = "0.1.0"

_SUBPACKAGES = ("bench", "camera", "commands", "data", "models", "ops", "optics", "train")


def __getattr__(name: str):
    """Import subpackages on first use, so ``import warpsense; warpsense.ops.cfa_mosaic`` works without loading
    Warp for commands that do not need it."""
    if name in _SUBPACKAGES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'warpsense' has no attribute {name!r}")
