"""Argument checks shared by the ops, run before any kernel launch: a wrong type, shape or value is a one-line
TypeError / ValueError that names the op and the argument.

Value policy (documented per op):
- tensors are checked for type, floating dtype, shape and device, never for their values: reading values would
  synchronise the device on every call (and break CUDA-graph capture). Non-finite values propagate to the outputs
  they reach; `Camera` rejects non-finite radiance at its input.
- noise levels and white levels given as Python numbers are checked for range (finite, >= 0 / > 0); given as
  tensors (learnable levels) their shape is checked and their values are clamped inside the kernels.
- integers that count (bits) must be int, not bool.
"""

from __future__ import annotations

import math
import numbers

import torch


def check_tensor(op: str, name: str, value, ndim: int | None = None, layout: str = "") -> None:
    """``value`` must be a floating-point torch.Tensor (of ``ndim`` dimensions, described by ``layout``, with no
    empty dimension)."""
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{op}: {name} must be a torch.Tensor, got {type(value).__name__} (torch.as_tensor "
                        "converts numpy arrays and lists)")
    if not value.is_floating_point():
        raise TypeError(f"{op}: {name} must be floating point, got {value.dtype}")
    if ndim is not None and (value.dim() != ndim or 0 in value.shape):
        raise ValueError(f"{op}: {name} must be a non-empty {layout or f'{ndim}-d tensor'}, got "
                         f"{tuple(value.shape)}")


def check_channel_pairs(op: str, x) -> tuple[int, int, int, int]:
    """``x`` must be a floating [B, C, H, W] tensor with an even number of channels (kernels that read channels in
    pairs); its shape."""
    check_tensor(op, "x", x, 4, "[B, C, H, W] tensor")
    if x.shape[1] % 2:
        raise ValueError(f"{op}: x must have an even number of channels (the kernels read them in pairs), got "
                         f"{x.shape[1]}")
    return tuple(x.shape)


def check_class_maps(op: str, name: str, maps, labels) -> tuple[int, int, int, int]:
    """``maps`` (argument ``name``) must be a floating [B, K, H, W] tensor and ``labels`` an integer [B, H, W] one on
    its device (per-pixel class indices); the maps' shape."""
    check_tensor(op, name, maps, 4, "[B, K, H, W] tensor")
    if not isinstance(labels, torch.Tensor) or labels.is_floating_point() or labels.is_complex() \
            or labels.dtype == torch.bool:
        raise TypeError(f"{op}: labels must be an integer tensor, got "
                        f"{labels.dtype if isinstance(labels, torch.Tensor) else type(labels).__name__}")
    check_same_device(op, **{name: maps, "labels": labels})
    batch, classes, height, width = maps.shape
    if tuple(labels.shape) != (batch, height, width):
        raise ValueError(f"{op}: labels must be [B, H, W] = {(batch, height, width)} to match {name} "
                         f"{tuple(maps.shape)}, got {tuple(labels.shape)}")
    return batch, classes, height, width


def check_indices(op: str, name: str, value, batch: int) -> None:
    """``value`` must be an integer tensor [``batch``]: one index per image of a batch (any device)."""
    if not isinstance(value, torch.Tensor) or value.is_floating_point() or value.is_complex() \
            or value.dtype == torch.bool:
        raise TypeError(f"{op}: {name} must be an integer tensor [B], got "
                        f"{value.dtype if isinstance(value, torch.Tensor) else type(value).__name__}")
    if tuple(value.shape) != (batch,):
        raise ValueError(f"{op}: {name} must be [B] = ({batch},), one index per image, got {tuple(value.shape)}")


def check_ignore_index(op: str, value) -> int:
    """A label value that marks unlabelled pixels: an integer (a Python or numpy int, not a bool) in int32's
    range, which the kernels compare labels with; returned as an int."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{op}: ignore_index must be an int, got {type(value).__name__} {value!r}")
    if not -2**31 <= value < 2**31:
        raise ValueError(f"{op}: ignore_index must fit in int32 (the labels' kernel type), got {value!r}")
    return int(value)


def check_same_device(op: str, **tensors: torch.Tensor) -> None:
    devices = {name: tensor.device for name, tensor in tensors.items()}
    if len(set(devices.values())) > 1:
        raise ValueError(f"{op}: inputs must be on one device, got " +
                         ", ".join(f"{name} on {device}" for name, device in devices.items()))


def check_level(op: str, name: str, level) -> None:
    """A noise level: a finite Python number >= 0, or a floating 0-d / 1-element tensor."""
    if isinstance(level, torch.Tensor):
        if not level.is_floating_point() or level.numel() != 1:
            raise ValueError(f"{op}: {name} must be a float or a floating 0-d tensor, got a {level.dtype} tensor "
                             f"of shape {tuple(level.shape)}")
        return
    if isinstance(level, bool) or not isinstance(level, (int, float)):
        raise TypeError(f"{op}: {name} must be a float or a tensor, got {type(level).__name__}")
    if not math.isfinite(level) or level < 0:
        raise ValueError(f"{op}: {name} must be finite and >= 0, got {level!r}")
