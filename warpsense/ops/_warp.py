"""The one place where torch tensors meet Warp kernels (the checklist of SPEC section 5).

- Inputs are wrapped with ``wp.from_torch(t.detach(), requires_grad=False)`` so Warp neither allocates gradients nor
  syncs the device; outputs and input gradients are allocated by torch; grad_output is made contiguous (a copy when
  it is not), never written.
- Kernels launch on torch's current CUDA stream, so they order correctly with the surrounding torch work and can be
  captured in a CUDA graph.
- Kernels run in float32 or float64: float16/bfloat16 inputs (e.g. under autocast) are computed in float32.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence

import torch
import warp as wp

wp.config.log_level = 30  # warnings only: no banner or per-module compile lines
wp.init()
_KERNEL_DTYPES = (torch.float32, torch.float64)


def kernel_dtype(*tensors: torch.Tensor) -> torch.dtype:
    """The float type the kernels compute in: float64 if any input is float64, else float32."""
    for tensor in tensors:
        if not tensor.is_floating_point():
            raise TypeError(f"expected a floating-point tensor, got {tensor.dtype}")
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


def prepare(*tensors: torch.Tensor) -> list[torch.Tensor]:
    """Cast inputs to their common kernel dtype and make them contiguous (autograd-tracked casts, no copies when
    nothing changes). All tensors must share one device."""
    dtype = kernel_dtype(*tensors)
    device = tensors[0].device
    for tensor in tensors[1:]:
        if tensor.device != device:
            raise ValueError(f"all inputs must be on one device, got {device} and {tensor.device}")
    return [t.to(dtype).contiguous() for t in tensors]


def to_warp(tensor: torch.Tensor) -> wp.array:
    """A Warp view of a contiguous torch tensor, without gradient storage."""
    return wp.from_torch(tensor.detach(), requires_grad=False)


def scalar_tensor(value: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """A 1-element tensor of ``like``'s dtype and device holding ``value`` (kept on the device: no host sync)."""
    if isinstance(value, torch.Tensor):
        if value.numel() != 1:
            raise ValueError(f"expected a scalar (0-d or 1-element) tensor, got shape {tuple(value.shape)}")
        return value.reshape(1).to(device=like.device, dtype=like.dtype)
    return torch.tensor([float(value)], device=like.device, dtype=like.dtype)


@contextlib.contextmanager
def _torch_stream(device: torch.device):
    if device.type == "cuda":
        with wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(device)), sync_enter=False):
            yield
    else:
        yield


def launch(kernel, dim: int | Sequence[int], inputs: Sequence, device: torch.device) -> None:
    """Launch a Warp kernel on ``device`` (torch's current stream on CUDA); tensors in ``inputs`` are wrapped."""
    if isinstance(dim, int):
        dim = (dim,)
    if any(d == 0 for d in dim):
        return
    arguments = [to_warp(x) if isinstance(x, torch.Tensor) else x for x in inputs]
    with _torch_stream(device):
        wp.launch(kernel, dim=tuple(dim), inputs=arguments, device=wp.device_from_torch(device))


def reduction_lanes(total: int, device: torch.device) -> int:
    """Number of lanes for strided reductions: enough to fill a GPU, few on the (serial) CPU backend."""
    return max(1, min(total, 65536 if device.type == "cuda" else 64))


def seed_int32(seed: int) -> int:
    """Map any Python int to the int32 Warp's generator takes."""
    seed = int(seed) & 0xFFFFFFFF
    return seed - (1 << 32) if seed >= (1 << 31) else seed
