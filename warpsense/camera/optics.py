"""Optics stage O (paper eq. 2): a lens rendered to a PSF grid and applied by the PSF-convolution kernel."""

from __future__ import annotations

import numpy as np
import torch

from warpsense.camera.stage import Stage
from warpsense.ops.psf import psf_conv
from warpsense.optics.lens import Lens, LensFileError, read_lens_spec
from warpsense.optics.psf_support import collapse_grid, crop_to_energy, display_half_width


class Optics(Stage):
    """Spatially varying blur from a lens file.

    A frozen lens renders its PSF grid once, cropped to the smallest odd support holding >= 1 - energy_eps of the
    energy and collapsed to one PSF when the field variation is below ``field_tolerance``. A learnable lens
    re-renders the full grid from its (bounded) Zernike coefficients while they train. ``normalize_mean`` > 0 rescales each output image to
    that mean (paper section 4.4).
    """

    config_section = "optics"
    part = "optics"
    takes = gives = "rgb"

    def __init__(self, lens: Lens, learnable: bool = False, normalize_mean: float = 0.5, method: str = "direct",
                 energy_eps: float = 1e-3, field_tolerance: float = 1e-3):
        super().__init__()
        self.lens = lens
        self.learnable = learnable
        self.normalize_mean = normalize_mean
        self.method = method
        lens.offset.requires_grad_(learnable)
        if not learnable:
            with torch.no_grad():
                psf = collapse_grid(crop_to_energy(lens.psf_grid(), energy_eps), field_tolerance)
            self.register_buffer("frozen_psf", psf.float())

        self._cached_psf: torch.Tensor | None = None
        self._cache_valid = False
        self._register_load_state_dict_pre_hook(lambda *args, **kwargs: self.invalidate_cache())

    @classmethod
    def from_config(cls, section) -> "Optics":
        """From the [optics] section: the lens file (a name in configs/lenses or a path) and how it is applied."""
        lens = Lens.from_json(section.lens, learnable=section.learnable)
        return cls(lens, learnable=section.learnable, normalize_mean=section.normalize_mean, method=section.method,
                   energy_eps=section.energy_eps, field_tolerance=section.field_tolerance)

    @classmethod
    def check_section(cls, section, where: str) -> None:
        """The lens file must parse, even while optics is off: a saved config must run when it is turned on."""
        try:
            read_lens_spec(section.lens)
        except LensFileError as error:
            raise ValueError(f"{where}: optics.lens: {error}") from None

    def on_epoch(self, schedule, epoch: int) -> None:
        """A phase switch may have frozen or unfrozen the lens: render the cached PSF grid anew."""
        self.invalidate_cache()

    def summary(self) -> dict:
        """A learnable lens's Zernike coefficients (waves, as `Lens.coefficients`); nothing for a fixed lens."""
        if not self.learnable:
            return {}
        return {"zernike_waves": self.lens.coefficients().detach().cpu().tolist()}

    def invalidate_cache(self) -> None:
        """Mark the cached PSF grid stale (call after changing the lens coefficients or their requires_grad)."""
        self._cache_valid = False

    def psf(self) -> torch.Tensor:
        """[3, Gy, Gx, K, K] PSF grid in use. A learnable lens is re-rendered while its coefficients take gradients
        (joint phase); while they are frozen or in eval mode the rendering is cached."""
        if not self.learnable:
            return self.frozen_psf
        if self.lens.offset.requires_grad and self.training and torch.is_grad_enabled():
            self._cache_valid = False
            return self.lens.psf_grid().float()
        if not self._cache_valid:
            with torch.no_grad():
                psf = self.lens.psf_grid().float()
            # refreshed in place: a captured CUDA graph holds the cache's address, not the Python attribute
            if self._cached_psf is None or self._cached_psf.shape != psf.shape or self._cached_psf.device != psf.device:
                self._cached_psf = psf
            else:
                self._cached_psf.copy_(psf)
            self._cache_valid = True
        return self._cached_psf

    def draw(self, axis) -> None:
        """The PSF grid (green channel, each PSF scaled to its peak, square root), central window above 1%."""
        psf = self.psf().detach().cpu().numpy()[1]  # [Gy, Gx, K, K]
        psf = psf / np.maximum(psf.max(axis=(2, 3), keepdims=True), 1e-12)
        kernel_size, centre = psf.shape[-1], psf.shape[-1] // 2
        half = display_half_width(psf)
        psf = psf[..., centre - half : centre + half + 1, centre - half : centre + half + 1]
        grid_y, grid_x, size, _ = psf.shape
        mosaic = np.zeros((grid_y * (size + 1), grid_x * (size + 1)))
        for i in range(grid_y):
            for j in range(grid_x):
                mosaic[i * (size + 1) : i * (size + 1) + size, j * (size + 1) : j * (size + 1) + size] = psf[i, j]
        axis.imshow(mosaic ** 0.5, cmap="magma")
        axis.set_title(f"PSF grid (green, sqrt, per-PSF max; central {size} of K = {kernel_size})", fontsize=10)

    def forward(self, radiance: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        image = psf_conv(radiance, self.psf().to(radiance.device), method=self.method)
        if self.normalize_mean > 0:
            mean = image.mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-6)
            image = image * (self.normalize_mean / mean)
        return image
