"""Compact UNet with depthwise-separable convolutions and squeeze-and-excitation (section 3.6 of the paper,
docs/references.md)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from warpsense.models.resample import adaptive_pool, resize
from warpsense.ops import batch_norm_relu, channel_gate, upsample_concat
from warpsense.ops._warp import ELEMENT_DTYPES
from warpsense.ops.switch import OpSwitch

FUSED_DEVICES = ("cuda",)
"""Devices where a channels-last network joins its decoder's upsampling and skips with `upsample_concat`, runs its
training-mode batch norms with their ReLU as `batch_norm_relu` and its squeeze-and-excitation gates with the
blocks' residuals as `channel_gate` (Warp's CPU backend runs a kernel on one thread, where torch's ops use every
core)."""


NETWORK_OPS = OpSwitch(("joins", "norm", "gate"))
"""The network's Warp ops, by name: the decoder joins (`upsample_concat`), batch norm + ReLU (`batch_norm_relu`),
the squeeze-and-excitation gate + residual (`channel_gate`). Within `torch_ops` the networks run the named ones (all
when none is named) as torch's own ops on every device: the benchmarks' plain-torch baseline runs the same network
as a plain PyTorch script does, and an A/B (tools/device/ab.py) turns one op off."""
FUSED_OPS = NETWORK_OPS.names
torch_ops = NETWORK_OPS.torch_ops


def _fused(op: str, x: torch.Tensor) -> bool:
    """Whether x can go through the fused op ``op`` (`FUSED_OPS`): not turned off by `torch_ops`, channels-last on
    a `FUSED_DEVICES` device, bfloat16, float32 or float64, an even number of channels."""
    return (NETWORK_OPS.fused(op) and x.device.type in FUSED_DEVICES and x.dim() == 4 and x.shape[1] % 2 == 0
            and x.dtype in ELEMENT_DTYPES
            and x.is_contiguous(memory_format=torch.channels_last))


def _capturing(x: torch.Tensor) -> bool:
    """Whether x's CUDA stream is being captured into a CUDA graph (False off CUDA)."""
    return x.is_cuda and torch.cuda.is_current_stream_capturing()


def norm_relu(norm: nn.BatchNorm2d, x: torch.Tensor) -> torch.Tensor:
    """``F.relu(norm(x))``. In training mode over channels-last x (bfloat16, float32 or float64, an even number of
    channels) on a `FUSED_DEVICES` device, an nn.BatchNorm2d with affine parameters, running statistics and a fixed
    momentum runs with its ReLU as one op (`batch_norm_relu`, equal up to float rounding, deterministic; the running
    statistics and ``num_batches_tracked`` move as torch moves them): one pass each way where torch's channels-last
    batch norm and ReLU take several (docs/benchmarks.md, batch norm + ReLU)."""
    if (norm.training and type(norm) is nn.BatchNorm2d and norm.affine and norm.track_running_stats
            and norm.momentum is not None and _fused("norm", x)):
        norm.num_batches_tracked.add_(1)
        return batch_norm_relu(x, norm.weight, norm.bias, norm.running_mean, norm.running_var, norm.momentum,
                               norm.eps)
    return F.relu(norm(x))


class SqueezeExcitation(nn.Module):
    """Channel attention (Hu et al. 2018): global pool -> bottleneck MLP -> sigmoid gate; with ``residual``, the
    gated features plus it (the block's residual connection). In training, channels-last x (bfloat16, float32 or
    float64, an even number of channels, a residual of the same dtype and layout) on a `FUSED_DEVICES` device takes
    the gate and the residual in one pass forward and one backward (`channel_gate`, equal up to float rounding,
    deterministic), a shorter training step. Evaluation keeps torch's two kernels, which a batch-1 CUDA graph replays
    faster (docs/benchmarks.md, the squeeze-and-excitation gate)."""

    def __init__(self, channels: int, reduction: int = 4):
        super().__init__()
        hidden = max(4, channels // reduction)
        self.reduce = nn.Conv2d(channels, hidden, 1)
        self.expand = nn.Conv2d(hidden, channels, 1)

    def forward(self, x, residual=None):
        gate = torch.sigmoid(self.expand(F.relu(self.reduce(x.mean(dim=(2, 3), keepdim=True)))))
        residual_fits = residual is None or (residual.dtype == x.dtype and _fused("gate", residual))
        if self.training and _fused("gate", x) and residual_fits:
            return channel_gate(x, gate, residual)
        return x * gate if residual is None else residual + x * gate


class SeparableBlock(nn.Module):
    """Depthwise 3x3 (optionally strided) -> pointwise 1x1, BN + ReLU after each, optional SE, residual when the
    shape allows."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1, squeeze: bool = True):
        super().__init__()
        self.depthwise = nn.Conv2d(in_channels, in_channels, 3, stride, 1, groups=in_channels, bias=False)
        self.norm1 = nn.BatchNorm2d(in_channels)
        self.pointwise = nn.Conv2d(in_channels, out_channels, 1, bias=False)
        self.norm2 = nn.BatchNorm2d(out_channels)
        self.squeeze = SqueezeExcitation(out_channels) if squeeze else nn.Identity()
        self.residual = stride == 1 and in_channels == out_channels

    def forward(self, x):
        y = norm_relu(self.norm1, self.depthwise(x))
        y = norm_relu(self.norm2, self.pointwise(y))
        residual = x if self.residual else None
        if isinstance(self.squeeze, SqueezeExcitation):
            return self.squeeze(y, residual)  # the gate and the residual in one op where fused
        return y if residual is None else x + y


class PyramidPooling(nn.Module):
    """Scene context at the bottleneck: the features average-pooled over 1 x 1, 2 x 2 and 4 x 4 regions of the whole
    image, each reduced by a 1x1 convolution, upsampled back and added through a 1x1 convolution + BN (pyramid
    pooling, Zhao et al. 2017, PSPNet, which motivates it by the same kind of error: an object's class decided by
    the scene around it, e.g. a car against a facade).

    The block is residual and its last BN scale starts at 0, so a network with it starts as the one without. The
    pooled branches carry no BN: a 1 x 1 pooled map with a batch of one has no batch statistics. ``channels`` C:
    [B, C, h, w] -> [B, C, h, w]; three C -> C/4 branches and a 3C/4 -> C fusion, about 1.5 C^2 parameters (56k at
    C = 192).
    """

    BINS = (1, 2, 4)

    def __init__(self, channels: int):
        super().__init__()
        reduced = max(4, channels // 4)
        self.branches = nn.ModuleList(nn.Conv2d(channels, reduced, 1) for _ in self.BINS)
        self.fuse = nn.Conv2d(reduced * len(self.BINS), channels, 1, bias=False)
        self.norm = nn.BatchNorm2d(channels)
        nn.init.zeros_(self.norm.weight)

    def forward(self, x):
        pooled = [DSUNet._up(F.relu(branch(adaptive_pool(x, bins))), x)
                  for bins, branch in zip(self.BINS, self.branches)]
        return x + self.norm(self.fuse(torch.cat(pooled, dim=1)))


CONTEXTS = {"none": lambda channels: nn.Identity(), "pyramid": PyramidPooling}
"""Bottleneck context modules (`warpsense.choices.MODEL_CONTEXTS`): name -> constructor taking the channels."""


def build_context(name: str, channels: int) -> nn.Module:
    """The context module ``name`` for a [B, channels, h, w] bottleneck; unknown names raise a KeyError listing
    the valid ones."""
    if name not in CONTEXTS:
        raise KeyError(f"unknown context {name!r}; valid contexts: {', '.join(sorted(CONTEXTS))}")
    return CONTEXTS[name](channels)


class SeparableStack(nn.Sequential):
    """``depth`` separable blocks at one resolution of the UNet (the first with ``stride``, changing the channels
    ``in_channels`` -> ``out_channels``); a Sequential, so its blocks' checkpoint keys are ``<name>.0``, ``<name>.1``,
    ..."""

    def __init__(self, in_channels: int, out_channels: int, depth: int, stride: int, squeeze: bool = True):
        blocks = [SeparableBlock(in_channels, out_channels, stride, squeeze)]
        blocks += [SeparableBlock(out_channels, out_channels, squeeze=squeeze) for _ in range(depth - 1)]
        super().__init__(*blocks)


class DSUNet(nn.Module):
    """RAW mosaic [B, 1, H, W] (or RGB [B, 3, H, W] from a fixed ISP) -> logits [B, K, H, W].

    The mosaic enters at full resolution through a dense 3x3 stem (which sees every CFA site of each
    neighbourhood, so thin structures keep full-resolution detail) and, in parallel, as a T x T pixel-unshuffle
    (the CFA tile's sites as channels) concatenated at half resolution. Encoder: 1, 1/2, 1/4, 1/8, 1/16 with widths
    w, 2w, 4w, 6w, 8w; decoder: bilinear upsampling + skip concatenation + separable blocks; head at full
    resolution. width=16 gives 0.18M parameters, width=24 0.40M (0.455M with the camvid presets' context).
    ``context`` adds a module at 1/16 (`CONTEXTS`; "pyramid": +56k parameters at width 24); "none" adds nothing.
    ``squeeze`` = False leaves out every block's squeeze-and-excitation (-117k parameters at width 24): a speed
    candidate, since each SE adds a global pooling and a multiply over its block's output. Each decoder stage
    upsamples the deeper features as they are and concatenates its encoder skip (dec1 runs on 2w + f channels at
    full resolution).

    The full-resolution path (stem, ``enc1``, ``dec1`` and the head's input) carries ``full_width`` channels (0: w)
    through ``full_depth`` separable blocks in the encoder and in the decoder (1: one each). It is where a pole or a
    sign a few pixels wide is seen whole. It costs little in parameters (width 40 adds 5.6k, depth 2 adds 2.4k at
    w = 24) and much in activations, which are full-resolution there (longer runs: docs/records/history.md, the
    full-resolution path).

    ``channels_last`` keeps weights and activations in NHWC: on CUDA in bf16 batch norm and depthwise convolutions
    have fast NHWC kernels, where their NCHW bf16 backward is slow (docs/benchmarks.md, measurements behind code
    choices). The output is the same up to float rounding. While torch's deterministic algorithms are on
    (``run.deterministic``), the upsampling and pooling take the forms in `warpsense.models.resample`, whose CUDA
    backward is deterministic.
    """

    def __init__(self, in_channels: int = 1, num_classes: int = 11, width: int = 16, tile: int = 2,
                 channels_last: bool = False, context: str = "none", squeeze: bool = True, full_width: int = 0,
                 full_depth: int = 1):
        super().__init__()
        if full_width < 0 or full_depth < 1:
            raise ValueError(f"full_width must be >= 0 and full_depth >= 1, got {full_width} and {full_depth}")
        self.memory_format = torch.channels_last if channels_last else torch.contiguous_format
        w = width
        f = full_width or w
        self.tile = tile if in_channels == 1 and tile > 1 else 0
        # conv and BN; the ReLU is applied with the BN (`norm_relu`); a Sequential for its checkpoint keys
        self.stem = nn.Sequential(nn.Conv2d(in_channels, f, 3, 1, 1, bias=False), nn.BatchNorm2d(f))
        self.enc1 = SeparableStack(f, f, full_depth, 1, squeeze)
        shuffle_channels = in_channels * self.tile * self.tile if self.tile else 0
        self.down2 = SeparableBlock(f, 2 * w, stride=2, squeeze=squeeze)
        self.mix2 = nn.Conv2d(2 * w + shuffle_channels, 2 * w, 1) if shuffle_channels else nn.Identity()
        self.enc2 = SeparableStack(2 * w, 2 * w, 1, 1, squeeze)
        self.enc3 = SeparableStack(2 * w, 4 * w, 2, 2, squeeze)
        self.enc4 = SeparableStack(4 * w, 6 * w, 3, 2, squeeze)
        self.enc5 = SeparableStack(6 * w, 8 * w, 3, 2, squeeze)
        self.context = build_context(context, 8 * w)
        # each decoder stage runs on the upsampled deeper features joined to its skip
        self.dec4 = SeparableStack(8 * w + 6 * w, 6 * w, 1, 1, squeeze)
        self.dec3 = SeparableStack(6 * w + 4 * w, 4 * w, 1, 1, squeeze)
        self.dec2 = SeparableStack(4 * w + 2 * w, 2 * w, 1, 1, squeeze)
        self.dec1 = SeparableStack(2 * w + f, f, full_depth, 1, squeeze)
        self.head = nn.Conv2d(f, num_classes, 1)
        self.to(memory_format=self.memory_format)

    @staticmethod
    def _up(x, like):
        # autocast runs bilinear upsampling in float32, and the float32 result then promotes the skip concatenation
        # and the next block's input: upsample in the activations' own dtype instead
        with torch.autocast(x.device.type, enabled=False):
            return resize(x, like.shape[-2:])

    def _up_cat(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        """``torch.cat([upsampled x, skip], dim=1)``: the decoder's bilinear x2 and skip connection. A channels-last
        network on a `FUSED_DEVICES` device takes them in one pass forward and one backward (`upsample_concat`,
        equal up to float rounding and deterministic; torch's NHWC resize backward and the concatenations are a
        large share of the step's time), except a single image in eval mode run eagerly: there the host's cost per
        op decides, and torch's resize and cat cost less of it than the custom op (docs/benchmarks.md, batch-1
        latency); inside a CUDA graph capture the op's shorter GPU time wins again."""
        if (self.memory_format == torch.channels_last and x.device.type in FUSED_DEVICES
                and NETWORK_OPS.fused("joins") and (self.training or x.shape[0] > 1 or _capturing(x))):
            return upsample_concat(x, skip)
        return torch.cat([self._up(x, skip), skip], dim=1)

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        height, width = raw.shape[-2:]
        pad_h, pad_w = (-height) % 16, (-width) % 16
        if pad_h or pad_w:
            raw = F.pad(raw, (0, pad_w, 0, pad_h), mode="replicate")
        raw = raw.contiguous(memory_format=self.memory_format)
        convolution, norm = self.stem
        s1 = self.enc1(norm_relu(norm, convolution(raw)))
        s2 = self.down2(s1)
        if self.tile == 2:
            # the tile's sites in the features' dtype and layout: under autocast a float32 mosaic would promote the
            # join to float32 in NCHW, copied twice more for the convolution (bf16, channels-last); the convolution
            # casts its input to bf16 anyway, so the values are the same
            sites = F.pixel_unshuffle(raw, 2).to(s2.dtype).contiguous(memory_format=self.memory_format)
            s2 = self.mix2(torch.cat([s2, sites], dim=1))
        s2 = self.enc2(s2)
        s3 = self.enc3(s2)
        s4 = self.enc4(s3)
        s5 = self.context(self.enc5(s4))
        d4 = self.dec4(self._up_cat(s5, s4))
        d3 = self.dec3(self._up_cat(d4, s3))
        d2 = self.dec2(self._up_cat(d3, s2))
        d1 = self.dec1(self._up_cat(d2, s1))
        return self.head(d1)[..., :height, :width]
