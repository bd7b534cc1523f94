"""Optics stage O (eq. 2 of the paper, docs/references.md): a lens and the exposure's motion rendered to a PSF grid,
applied by the PSF-convolution kernel."""

from __future__ import annotations

import numpy as np
import torch

from warpsense.camera.bounds import check_log_bounds, log_bounded, log_bounded_parameter
from warpsense.camera.stage import Stage
from warpsense.config import OpticsConfig
from warpsense.ops.psf import psf_conv
from warpsense.optics.lens import Lens, LensFileError, read_lens_spec
from warpsense.optics.motion import compose, streak_psfs, streak_size
from warpsense.optics.psf_support import collapse_grid, crop_to_energy, display_half_width

REFERENCE_F_NUMBER, REFERENCE_EXPOSURE_MS = 2.0, 10.0
"""The throughput 1 of the photon budget (`warpsense.camera.photons`): f/2 for 10 ms."""
BOUND_KEYS = {key: (f"optics.{key}_min", f"optics.{key}_max") for key in ("f_number", "exposure_ms")}
"""The config keys of the bounds of a learned f-number and exposure time."""


class Optics(Stage):
    """What reaches the sensor during the exposure: the lens's spatially varying blur at its f-number, the motion
    blur of the vehicle's forward motion over the exposure time, and the light both let through.

    A lens renders its PSF grid from the lens file (`warpsense.optics.lens`), optionally stopped to another
    f-number; with ``corner_speed_px_per_ms`` > 0 each node's PSF is convolved with its radial motion streak
    (`warpsense.optics.motion`), so `psf_conv` renders both in one pass. A frozen design renders once, cropped to the
    smallest odd support holding >= 1 - energy_eps of the energy and collapsed to one PSF when the field variation
    is below ``field_tolerance``; a learnable lens (Zernike terms), f-number or (with motion) exposure time re-renders
    the grid while it trains.

    Light: ``normalize_mean`` > 0 rescales each output image to that mean (section 4.4 of the paper; the photon count is
    then hidden). With ``normalize_mean`` = 0 the output is the radiance times the relative throughput
    (2 / F#)^2 * t / 10 ms: one stop (F# x sqrt 2) halves it, doubling t doubles it.
    Learnable f-number and exposure time are bounded log-uniformly (`warpsense.camera.bounds`); a start on a bound
    (f/1.4 with f_number_min = 1.4) is learned from just inside it.
    """

    config_section = "optics"
    part = "optics"
    takes = gives = "rgb"

    def __init__(self, lens: Lens | str = OpticsConfig.lens, learnable: bool = OpticsConfig.learnable,
                 normalize_mean: float = OpticsConfig.normalize_mean, method: str = OpticsConfig.method,
                 render_precision: str = OpticsConfig.render_precision, energy_eps: float = OpticsConfig.energy_eps,
                 field_tolerance: float = OpticsConfig.field_tolerance, f_number: float = OpticsConfig.f_number,
                 f_number_learnable: bool = OpticsConfig.f_number_learnable,
                 f_number_min: float = OpticsConfig.f_number_min, f_number_max: float = OpticsConfig.f_number_max,
                 exposure_ms: float = OpticsConfig.exposure_ms,
                 exposure_learnable: bool = OpticsConfig.exposure_learnable,
                 exposure_ms_min: float = OpticsConfig.exposure_ms_min,
                 exposure_ms_max: float = OpticsConfig.exposure_ms_max,
                 corner_speed_px_per_ms: float = OpticsConfig.corner_speed_px_per_ms):
        """Args (the [optics] keys, docs/guide/camera.md):
            lens: a `Lens`, or a lens file (a name in configs/lenses or a path) read with its Zernike terms
                learnable as ``learnable`` says.
            learnable: learn the lens's Zernike coefficients (bounded).
            normalize_mean: > 0: rescale each output image to this mean; 0: times the throughput.
            method: how the PSFs are applied (a `warpsense.choices.PSF_METHODS` name).
            render_precision: "float32" or "float64", the dtype of a re-rendered grid's pupil FFTs.
            energy_eps, field_tolerance: a frozen grid's crop (energy left out) and collapse to one PSF (L1).
            f_number, f_number_learnable, f_number_min, f_number_max: the f-number (0: the lens file's), learned
                within its bounds or fixed.
            exposure_ms, exposure_learnable, exposure_ms_min, exposure_ms_max: the exposure time (ms), likewise.
            corner_speed_px_per_ms: image speed of the frame corner (pixels per ms; 0: no motion blur).
        """
        super().__init__()
        if not isinstance(lens, Lens):
            lens = Lens.from_json(lens, learnable=learnable)
        self.lens = lens
        self.learnable = learnable
        self.normalize_mean = normalize_mean
        self.method = method
        self.corner_speed = float(corner_speed_px_per_ms)
        self.render_dtype = getattr(torch, render_precision)
        lens.offset.requires_grad_(learnable)
        self.f_number_bounds = (float(f_number_min), float(f_number_max))
        self.exposure_bounds = (float(exposure_ms_min), float(exposure_ms_max))
        self.stopped = f_number_learnable or f_number > 0  # rendered at another f-number than the file's
        start_f = f_number if f_number > 0 else lens.spec.f_number
        if f_number_learnable:
            self.f_number_logit = log_bounded_parameter(start_f, *self.f_number_bounds, key="optics.f_number",
                                                        bound_keys=BOUND_KEYS["f_number"])
        else:
            # from the config, not learned: not in the state dict (checkpoints from before it existed still load)
            self.register_buffer("fixed_f_number", torch.tensor(float(start_f)), persistent=False)
        self.grid_f_number = self.f_number_bounds[0] if f_number_learnable else float(start_f)
        if exposure_learnable:
            self.exposure_logit = log_bounded_parameter(exposure_ms, *self.exposure_bounds, key="optics.exposure_ms",
                                                        bound_keys=BOUND_KEYS["exposure_ms"])
        else:
            self.register_buffer("fixed_exposure_ms", torch.tensor(float(exposure_ms)), persistent=False)
        longest = self.exposure_bounds[1] if exposure_learnable else exposure_ms
        self.streak_size = streak_size(self.corner_speed * longest) if self.corner_speed > 0 else 0
        self.dynamic = learnable or f_number_learnable or (exposure_learnable and self.corner_speed > 0)
        if not self.dynamic:
            with torch.no_grad():
                # rendered once: float64 costs nothing here
                psf = collapse_grid(crop_to_energy(self.render(torch.float64), energy_eps), field_tolerance)
            self.register_buffer("frozen_psf", psf.float())

        self._cached_psf: torch.Tensor | None = None
        self._cache_valid = False
        # a bound method, not a closure over self: a lambda cannot be pickled (torch.save of the module), and
        # copy.deepcopy keeps it as it is, so a copy's load_state_dict invalidated the original's cache, not its own
        self._register_load_state_dict_pre_hook(self._invalidate_on_load)

    def _invalidate_on_load(self, *args, **kwargs) -> None:
        """load_state_dict pre-hook: the loaded design renders its PSF grid anew."""
        self.invalidate_cache()

    @classmethod
    def check_section(cls, section, where: str) -> None:
        """The lens file must parse, even while optics is off: a saved config must run when it is turned on. A
        learned f-number or exposure time starts within its bounds (a bound included: `warpsense.camera.bounds`)
        and trades light, so it needs the photon count (normalize_mean = 0)."""
        try:
            spec = read_lens_spec(section.lens)
        except LensFileError as error:
            raise ValueError(f"{where}: optics.lens: {error}") from None
        starts = {"f_number": section.f_number or spec.f_number, "exposure_ms": section.exposure_ms}
        for key, learnable_key in (("f_number", "f_number_learnable"), ("exposure_ms", "exposure_learnable")):
            if not getattr(section, learnable_key):
                continue
            name = f"optics.{key}" if key != "f_number" or section.f_number else "optics.f_number (0: the lens file's)"
            problem = check_log_bounds(name, starts[key], getattr(section, f"{key}_min"),
                                       getattr(section, f"{key}_max"), BOUND_KEYS[key])
            if problem:
                raise ValueError(f"{where}: {problem} (optics.{learnable_key} = true)")
            if section.normalize_mean > 0:
                raise ValueError(f"{where}: optics.{learnable_key} needs optics.normalize_mean = 0: rescaling each "
                                 "frame hides the light it trades")

    def f_number(self) -> torch.Tensor:
        """The f-number in use (dimensionless)."""
        if hasattr(self, "f_number_logit"):
            return log_bounded(self.f_number_logit, *self.f_number_bounds)
        return self.fixed_f_number

    def exposure_ms(self) -> torch.Tensor:
        """The exposure time in use (ms)."""
        if hasattr(self, "exposure_logit"):
            return log_bounded(self.exposure_logit, *self.exposure_bounds)
        return self.fixed_exposure_ms

    def throughput(self) -> torch.Tensor:
        """Light relative to f/2 for 10 ms: (2 / F#)^2 * t / 10 ms."""
        return (REFERENCE_F_NUMBER / self.f_number()) ** 2 * self.exposure_ms() / REFERENCE_EXPOSURE_MS

    def on_epoch(self, schedule, epoch: int) -> None:
        """A phase switch may have frozen or unfrozen the design: render the cached PSF grid anew."""
        self.invalidate_cache()

    def summary(self) -> dict:
        """The learned design: a learnable lens's Zernike coefficients (waves, as `Lens.coefficients`), a learnable
        f-number and exposure time (ms); nothing for a fixed design."""
        summary = {}
        if self.learnable:
            summary["zernike_waves"] = self.lens.coefficients().detach().cpu().tolist()
        if hasattr(self, "f_number_logit"):
            summary["f_number"] = float(self.f_number().detach())
        if hasattr(self, "exposure_logit"):
            summary["exposure_ms"] = float(self.exposure_ms().detach())
        return summary

    def invalidate_cache(self) -> None:
        """Mark the cached PSF grid stale (call after changing the design or its requires_grad)."""
        self._cache_valid = False

    def render(self, dtype: torch.dtype | None = None) -> torch.Tensor:
        """[3, Gy, Gx, K, K] PSF grid of the design now (lens at its f-number, composed with the motion streaks),
        its pupil FFTs in ``dtype`` (default: the configured render precision)."""
        options = {"f_number": self.f_number(), "grid_f_number": self.grid_f_number} if self.stopped else {}
        psf = self.lens.psf_grid(dtype=dtype or self.render_dtype, **options)
        if self.corner_speed > 0:
            grid_y, grid_x = self.lens.spec.psf_grid
            height, azimuth = self.lens.field_points()
            lengths = height * self.corner_speed * self.exposure_ms().to(height.dtype)
            streaks = streak_psfs(lengths, azimuth, self.streak_size).reshape(grid_y, grid_x, self.streak_size,
                                                                              self.streak_size)
            psf = compose(psf, streaks)
        return psf

    def _training_design(self) -> bool:
        parameters = [self.lens.offset] + [getattr(self, name) for name in ("f_number_logit", "exposure_logit")
                                           if hasattr(self, name)]
        return any(p.requires_grad for p in parameters)

    def psf(self) -> torch.Tensor:
        """[3, Gy, Gx, K, K] PSF grid in use. A learnable design is re-rendered while it takes gradients (joint
        phase); while it is frozen or in eval mode the rendering is cached."""
        if not self.dynamic:
            return self.frozen_psf
        if self.training and torch.is_grad_enabled() and self._training_design():
            self._cache_valid = False
            return self.render().float()
        if not self._cache_valid:
            with torch.no_grad():
                psf = self.render().float()
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
        """Radiance [B, 3, H, W] -> irradiance [B, 3, H, W]: blurred, then rescaled to ``normalize_mean`` or times
        the throughput."""
        image = psf_conv(radiance, self.psf().to(radiance.device), method=self.method)
        if self.normalize_mean > 0:
            mean = image.mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-6)
            return image * (self.normalize_mean / mean)
        return image * self.throughput().to(image.dtype)
