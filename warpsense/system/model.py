"""The model users load: camera -> (fixed ISP) -> segmentation network, as one nn.Module (`SensingModel`)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from warpsense.camera import Camera
from warpsense.camera.isp import FixedISP
from warpsense.data.color import linear_to_srgb, srgb_to_linear, unprocess


class SensingModel(nn.Module):
    """uint8 sRGB or linear radiance [B, 3, H, W] -> (logits [B, K, H, W], sensor output fed to the network).

    ``srgb_input``: the network reads the clean sRGB frame in [0, 1] instead of a capture (no camera: the RGB
    teacher of distillation, model.input = "srgb"; linear radiance is encoded back to sRGB)."""

    def __init__(self, camera: Camera, network: nn.Module, isp: FixedISP | None = None, unprocess_input: bool = False,
                 srgb_input: bool = False):
        super().__init__()
        self.camera = camera
        self.isp = isp
        self.network = network
        self.unprocess_input = unprocess_input
        self.srgb_input = srgb_input

    def radiance(self, image: torch.Tensor) -> torch.Tensor:
        """uint8 sRGB -> linear radiance (float tensors are taken as radiance already)."""
        if image.dtype == torch.uint8:
            image = srgb_to_linear(image)
            if self.unprocess_input:
                image = unprocess(image)
        return image

    def sense(self, image: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        if self.srgb_input:
            return image.float() * (1 / 255) if image.dtype == torch.uint8 else linear_to_srgb(image)
        sensed = self.camera(self.radiance(image), image_index)
        return self.isp(sensed) if self.isp is not None else sensed

    def forward(self, image: torch.Tensor, amp: bool = False, image_index: torch.Tensor | None = None):
        """``image_index`` [B]: the images' indices in their dataset, which key the eval-mode sensor noise."""
        sensed = self.sense(image, image_index)
        with torch.autocast(device_type=sensed.device.type, dtype=torch.bfloat16, enabled=amp):
            logits = self.network(sensed)
        return logits, sensed

    @torch.no_grad()
    def probabilities(self, image: torch.Tensor, amp: bool = False, image_index: torch.Tensor | None = None,
                      flip: bool = False, scales: tuple[float, ...] = (1.0,)) -> torch.Tensor:
        """Class probabilities [B, K, H, W] of one capture. Test-time augmentation, all of it on that capture (no
        second exposure): ``scales``: averaged over the capture resized by each scale (`cfa_resize`, the CFA phase
        kept; each view's logits resized back bilinearly before the softmax); ``flip``: at every scale also the
        horizontally mirrored capture (`cfa_flip`)."""
        logits, sensed = self(image, amp, image_index)
        if not flip and tuple(scales) == (1.0,):
            return torch.softmax(logits.float(), dim=1)
        views = [view for scale_views in self.scaled_views(sensed, logits, scales, flip, amp) for view in scale_views]
        return sum(views) / len(views)

    @torch.no_grad()
    def scaled_views(self, sensed: torch.Tensor, logits: torch.Tensor, scales, flip: bool = False,
                     amp: bool = False) -> list[list[torch.Tensor]]:
        """Per scale of ``scales``, the class probabilities [B, K, H, W] of the capture ``sensed`` resized by it
        (`cfa_resize`; ``logits`` are the network's on ``sensed`` itself, reused at scale 1), each view's logits
        resized back to H x W before the softmax; with ``flip`` each scale's list also holds the mirrored view
        (`cfa_flip`). `probabilities` averages them; tools that score several scale sets average their own."""
        tile = self.camera.tile if self.isp is None else 1
        height, width = sensed.shape[-2:]
        per_scale = []
        for scale in scales:
            if scale == 1.0:
                scaled, scaled_logits = sensed, logits
            else:
                scaled = cfa_resize(sensed, scale, tile)
                scaled_logits = self._network(scaled, amp)
            view_logits = [scaled_logits.float()]
            if flip:
                flipped, shift = cfa_flip(scaled, tile)
                view_logits.append(cfa_unflip(self._network(flipped, amp).float(), shift))
            views = []
            for view in view_logits:
                if view.shape[-2:] != (height, width):  # logits are resized, then turned into probabilities
                    view = F.interpolate(view, size=(height, width), mode="bilinear", align_corners=False)
                views.append(torch.softmax(view, dim=1))
            per_scale.append(views)
        return per_scale

    def _network(self, sensed: torch.Tensor, amp: bool) -> torch.Tensor:
        with torch.autocast(device_type=sensed.device.type, dtype=torch.bfloat16, enabled=amp):
            return self.network(sensed)


def cfa_resize(sensed: torch.Tensor, scale: float, tile: int) -> torch.Tensor:
    """A capture [B, C, H, W] resized by ``scale`` (bilinear) so that every pixel keeps its CFA site: with 2 x 2
    tiles the mosaic's four sites are resized as planes at half resolution (the output is 2 round(H s / 2) x
    2 round(W s / 2)); with 1 x 1 (RGB after an ISP) the capture is resized directly. Scale 1 returns it as is."""
    if scale == 1.0:
        return sensed
    if scale <= 0:
        raise ValueError(f"scale test-time augmentation needs scales > 0, got {scale}")
    if tile not in (1, 2):
        raise ValueError(f"scale test-time augmentation keeps the CFA phase only for 1x1 and 2x2 tiles, got {tile}x{tile}")
    planes = F.pixel_unshuffle(sensed, tile) if tile == 2 else sensed
    size = tuple(max(1, round(side * scale)) for side in planes.shape[-2:])
    planes = F.interpolate(planes, size=size, mode="bilinear", align_corners=False)
    return F.pixel_shuffle(planes, tile) if tile == 2 else planes


def cfa_flip(sensed: torch.Tensor, tile: int) -> tuple[torch.Tensor, int]:
    """Mirror a capture [B, C, H, W] left-right so that every pixel keeps its CFA site.

    A plain flip moves column x to W - 1 - x, whose site differs when W is even (2x2 tiles); shifting the mirrored
    frame by ``shift`` = (W - 1) mod 2 columns (edge column repeated) restores the phase. Tiles wider than 2 have no
    such shift. Returns (mirrored capture, shift) for `cfa_unflip`."""
    if tile > 2:
        raise ValueError(f"flip test-time augmentation keeps the CFA phase only for 1x1 and 2x2 tiles, got {tile}x{tile}")
    width = sensed.shape[-1]
    shift = (width - 1) % 2 if tile == 2 else 0
    mirrored = sensed.flip(-1)
    if shift:
        mirrored = F.pad(mirrored, (shift, 0, 0, 0), mode="replicate")[..., :width]
    return mirrored, shift


def cfa_unflip(prediction: torch.Tensor, shift: int) -> torch.Tensor:
    """Map a prediction on `cfa_flip`'s capture back to the original columns (the ``shift`` edge columns it cannot
    see repeat their neighbour)."""
    restored = prediction[..., shift:].flip(-1)
    return F.pad(restored, (shift, 0, 0, 0), mode="replicate") if shift else restored
