"""A UNet laid out for the GPU: the RAW mosaic packed into channels at half resolution, dense 3x3 convolutions
where there are few channels and many pixels, depthwise-separable ones where there are many channels and few
pixels, and a thin full-resolution branch for thin structures."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from warpsense.models.dsunet import DSUNet, SeparableBlock, Stage, build_context, build_input_transform, norm_relu


class ConvBlock(nn.Module):
    """Dense 3x3 convolution (optionally strided) -> BN -> ReLU, residual when the shape allows.

    On a GPU a dense 3x3 convolution with 24-96 channels runs on tensor cores (bf16, NHWC) at a few times the speed
    of a depthwise 3x3 + pointwise pair with the same output, whose depthwise half is memory-bound; it costs 9x the
    pointwise parameters, so it is used only at the high resolutions, where the channels are few."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, 3, stride, 1, bias=False)
        self.norm = nn.BatchNorm2d(out_channels)
        self.residual = stride == 1 and in_channels == out_channels

    def forward(self, x):
        y = norm_relu(self.norm, self.conv(x))
        return x + y if self.residual else y


class PackUNet(DSUNet):
    """RAW mosaic [B, 1, H, W] (or RGB [B, 3, H, W]) -> logits [B, K, H, W].

    Paths, for base width w (the widths match `DSUNet`'s: 2w at 1/2, 4w at 1/4, 6w at 1/8, 8w at 1/16):
      - detail: a dense 3x3 convolution at full resolution (w channels), which sees every CFA site of each
        neighbourhood; a strided dense 3x3 takes it to 1/2;
      - packed: the input's 2 x 2 tiles as channels (pixel unshuffle: for a 2 x 2 CFA, one channel per filter site)
        joined to the detail path at 1/2 by a dense 3x3 block;
      - encoder: dense blocks at 1/2 and into 1/4, depthwise-separable blocks with squeeze-and-excitation at 1/4,
        1/8 and 1/16;
      - decoder: bilinear upsampling + skip concatenation; separable blocks at 1/8 and 1/4, a dense block at 1/2,
        and the head at full resolution: a dense 3x3 over the upsampled features and the detail path, then 1x1.

    width=22 gives 0.45M parameters for 11 classes (budget 0.5M; width=24 gives 0.54M). ``tile`` is accepted for the registry's common
    signature: the packing is 2 x 2 whatever the CFA tile (the detail path sees larger tiles whole). The padding,
    the 1/4-1/16 stages' order, the ``context`` module at 1/16 and the decoder's upsampling and skips are
    `DSUNet`'s (`encode_high` differs), and so are ``squeeze`` (False: the separable blocks without SE) and the
    ``input_transform``. ``full_width``, ``full_depth`` and ``decoder_join`` are `DSUNet`'s only (ValueError unless 0, 1 and
    "concat").
    """

    def __init__(self, in_channels: int = 1, num_classes: int = 11, width: int = 22, tile: int = 2,
                 channels_last: bool = True, context: str = "none", squeeze: bool = True,
                 input_transform: str = "linear", anscombe_offset: float = 0.0059, full_width: int = 0,
                 full_depth: int = 1, decoder_join: str = "concat"):
        nn.Module.__init__(self)  # its own layers: DSUNet's constructor would build the separable ones
        del tile
        if (full_width, full_depth) != (0, 1):
            raise ValueError("packunet has its own full-resolution path: model.full_width must be 0 and "
                             f"model.full_depth 1, got {full_width} and {full_depth}")
        if decoder_join != "concat":
            raise ValueError(f"packunet's decoder concatenates: model.decoder_join must be 'concat', got {decoder_join!r}")
        self.memory_format = torch.channels_last if channels_last else torch.contiguous_format
        self.input_transform = build_input_transform(input_transform, anscombe_offset)
        w = width
        self.detail = ConvBlock(in_channels, w)
        self.down = ConvBlock(w, 2 * w, stride=2)
        self.join = ConvBlock(2 * w + 4 * in_channels, 2 * w)
        self.enc2 = ConvBlock(2 * w, 2 * w)
        self.enc3 = nn.Sequential(ConvBlock(2 * w, 4 * w, stride=2), SeparableBlock(4 * w, 4 * w, squeeze=squeeze))
        self.enc4 = Stage(4 * w, 6 * w, 3, 2, squeeze)
        self.enc5 = Stage(6 * w, 8 * w, 3, 2, squeeze)
        self.context = build_context(context, 8 * w)
        self.join4 = self.join3 = self.join2 = self.join1 = nn.Identity()  # DSUNet.forward's "concat" joins
        self.dec4 = Stage(8 * w + 6 * w, 6 * w, 1, 1, squeeze)
        self.dec3 = Stage(6 * w + 4 * w, 4 * w, 1, 1, squeeze)
        self.dec2 = ConvBlock(4 * w + 2 * w, 2 * w)
        self.dec1 = ConvBlock(2 * w + w, w)
        self.head = nn.Conv2d(w, num_classes, 1)
        self.to(memory_format=self.memory_format)

    def encode_high(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The detail path at full resolution, joined with the 2 x 2-packed input at half resolution (the padding
        to a multiple of 16 is even, so the packing keeps the CFA phase)."""
        s1 = self.detail(raw)
        s2 = self.join(torch.cat([self.down(s1), F.pixel_unshuffle(raw, 2)], dim=1))
        return s1, self.enc2(s2)
