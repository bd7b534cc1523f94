"""Bilinear resizing and adaptive average pooling whose backward passes are deterministic on CUDA.

`torch.nn.functional.interpolate` (bilinear) and `adaptive_avg_pool2d` differentiate on CUDA with atomic adds, so
two runs with the same seed drift apart (torch's deterministic mode refuses or only warns about them). These give
the same values from slices and small matrix products, whose gradients are sums in a fixed order. The networks call
`resize` and `adaptive_pool`, which take these forms while `torch.are_deterministic_algorithms_enabled()`
(`run.deterministic`) and torch's own ops otherwise.

Conventions are torch's: bilinear with ``align_corners=False`` (source coordinate (o + 0.5) in / out - 0.5, clamped
at 0, neighbours clamped at the edge) and adaptive pooling windows [floor(i in / n), ceil((i + 1) in / n)).
"""

from __future__ import annotations

import functools

import torch
from torch.nn import functional as F


def _double(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Bilinear x2 along ``dim`` (``align_corners=False``): output 2i takes 3/4 of input i and 1/4 of input i - 1,
    output 2i + 1 takes 3/4 of i and 1/4 of i + 1 (edges repeated)."""
    dim %= x.ndim
    size = x.shape[dim]
    before = torch.cat([x.narrow(dim, 0, 1), x.narrow(dim, 0, size - 1)], dim=dim)
    after = torch.cat([x.narrow(dim, 1, size - 1), x.narrow(dim, size - 1, 1)], dim=dim)
    # [..., n, 2, ...] -> [..., 2n, ...]: the even and odd outputs interleaved
    return torch.stack([0.75 * x + 0.25 * before, 0.75 * x + 0.25 * after], dim=dim + 1).flatten(dim, dim + 1)


def upsample2x(x: torch.Tensor) -> torch.Tensor:
    """[..., h, w] -> [..., 2h, 2w], bilinear (``align_corners=False``), one axis after the other."""
    return _double(_double(x, -2), -1)


@functools.lru_cache(maxsize=64)
def _bilinear_matrix(size_out: int, size_in: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """[size_out, size_in]: row o holds the weights of output o on the inputs."""
    source = ((torch.arange(size_out, dtype=torch.float64) + 0.5) * (size_in / size_out) - 0.5).clamp_min(0)
    low = source.floor().long().clamp_max(size_in - 1)
    high = (low + 1).clamp_max(size_in - 1)
    fraction = source - low
    matrix = torch.zeros(size_out, size_in, dtype=torch.float64)
    rows = torch.arange(size_out)
    matrix.index_put_((rows, low), 1 - fraction, accumulate=True)
    matrix.index_put_((rows, high), fraction, accumulate=True)
    return matrix.to(dtype=dtype, device=device)


@functools.lru_cache(maxsize=64)
def _pooling_matrix(bins: int, size_in: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """[bins, size_in]: row i averages torch's adaptive window i."""
    matrix = torch.zeros(bins, size_in, dtype=torch.float64)
    for i in range(bins):
        start, end = (i * size_in) // bins, -(-((i + 1) * size_in) // bins)
        matrix[i, start:end] = 1.0 / (end - start)
    return matrix.to(dtype=dtype, device=device)


def _separable(x: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """rows [H', h] @ x [..., h, w] @ cols^T [w, W'] (the result is contiguous)."""
    return torch.matmul(torch.matmul(rows, x), cols.transpose(0, 1))


def resize_bilinear(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``F.interpolate(x, size, mode="bilinear", align_corners=False)`` for [B, C, h, w] ``x``: `upsample2x` when
    ``size`` is twice the input, else a product with per-axis interpolation matrices (meant for small maps)."""
    height, width = x.shape[-2:]
    if tuple(size) == (2 * height, 2 * width):
        return upsample2x(x)
    rows = _bilinear_matrix(int(size[0]), height, x.dtype, x.device)
    cols = _bilinear_matrix(int(size[1]), width, x.dtype, x.device)
    return _separable(x, rows, cols)


def adaptive_avg_pool(x: torch.Tensor, bins: int) -> torch.Tensor:
    """``F.adaptive_avg_pool2d(x, bins)`` for [B, C, h, w] ``x``, as products with per-axis averaging matrices."""
    height, width = x.shape[-2:]
    return _separable(x, _pooling_matrix(bins, height, x.dtype, x.device),
                      _pooling_matrix(bins, width, x.dtype, x.device))


def resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear resize of [B, C, h, w] ``x`` to ``size``: `resize_bilinear` under torch's deterministic algorithms,
    else torch's own (faster) op."""
    if torch.are_deterministic_algorithms_enabled():
        return resize_bilinear(x, size)
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False)


def adaptive_pool(x: torch.Tensor, bins: int) -> torch.Tensor:
    """Adaptive average pooling of [B, C, h, w] ``x`` to bins x bins: `adaptive_avg_pool` under torch's
    deterministic algorithms, else torch's own op."""
    if torch.are_deterministic_algorithms_enabled():
        return adaptive_avg_pool(x, bins)
    return F.adaptive_avg_pool2d(x, bins)
