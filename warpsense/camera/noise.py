"""Sensor noise stage N (eq. 5 of the paper, docs/references.md)."""

from __future__ import annotations

import math

import torch
from torch import nn

from warpsense.camera.stage import WHAT_IF_SOURCE, SensorArguments, Stage
from warpsense.config import NoiseConfig
from warpsense.ops.noise import poisson_gaussian, poisson_gaussian_exact


def _electrons_problem(full_well_electrons: float, read_electrons: float) -> str | None:
    """Why the noise cannot be stated in electrons this way, or None."""
    if read_electrons > 0 and full_well_electrons == 0:
        return "noise.read_electrons needs noise.full_well_electrons (electrons at the white level)"
    return None


class NoisySensor(Stage):
    """What every noisy sensor stage shares: per-image seeds, the what-if overrides, the fused and unfused paths.

    Seeds are per image and live on the device (no host round trip, and a captured CUDA graph draws new noise on
    every replay): training takes the next ``batch`` values of a counter started from torch's generator at
    construction (a seeded run is reproducible; the counter is saved with the model, so a resumed run continues
    the same draws); eval uses ``eval_seed`` + the image's index in its dataset when the caller gives it
    (``image_index``), else + its place in the batch. ``exact=True`` samples true Poisson photon counts (eval only,
    not differentiable). A subclass gives `levels` and, where it converts its input, `signal_gain`.
    """

    what_if = {"noise_scale": "scale", "exact_noise": "exact"}

    @classmethod
    def check_what_if(cls, name: str, value) -> None:
        """noise_scale: a finite number >= 0 (0: no noise); exact_noise: a bool. No config key holds either, so the
        checks are here, worded as the config's (`warpsense.config.check_value`)."""
        where = f"{WHAT_IF_SOURCE}: {name}"
        if name == "noise_scale" and (isinstance(value, bool) or not isinstance(value, (int, float))
                                      or not math.isfinite(value) or value < 0):
            raise ValueError(f"{where}: must be a finite number >= 0, got {value!r}")
        if name == "exact_noise" and not isinstance(value, bool):
            raise ValueError(f"{where}: expected bool, got {type(value).__name__} {value!r}")

    def __init__(self, eval_seed: int = 1234):
        super().__init__()
        self.register_buffer("seed_counter", torch.randint(0, 2**30, (1,), dtype=torch.int64))
        self.eval_seed = eval_seed
        self.scale = 1.0
        self.exact = False

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):
        # checkpoints written before the counter existed load with the counter this module started with
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)
        if prefix + "seed_counter" in missing_keys:
            missing_keys.remove(prefix + "seed_counter")

    def levels(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(shot variance coefficient, read standard deviation) in units of the white level, scaled by
        ``noise_scale`` (shot by its square)."""
        raise NotImplementedError

    def signal_gain(self) -> torch.Tensor | None:
        """A gain on the input before the noise (None: none)."""
        return None

    def seeds(self, batch: int, image_index: torch.Tensor | None = None) -> torch.Tensor:
        """int32 [batch] per-image seeds in [0, 2^31 - 1) on the module's device (see the class docstring); int32
        is what the kernels take."""
        device = self.seed_counter.device
        if self.training:
            seeds = self.seed_counter + torch.arange(batch, device=device)
            self.seed_counter.add_(batch)
            return (seeds % (2**31 - 1)).to(torch.int32)
        if image_index is not None:
            return ((self.eval_seed + image_index.to(device)) % (2**31 - 1)).to(torch.int32)
        if 0 <= self.eval_seed and self.eval_seed + batch <= 2**31 - 1:  # the modulo changes nothing: one kernel
            return torch.arange(self.eval_seed, self.eval_seed + batch, dtype=torch.int32, device=device)
        return ((self.eval_seed + torch.arange(batch, device=device)) % (2**31 - 1)).to(torch.int32)

    def fuse(self, arguments: SensorArguments) -> bool:
        """The gain folds into the responses; the fused kernel draws the Gaussian approximation (exact Poisson counts
        take this stage's own op)."""
        gain = self.signal_gain()
        if gain is not None:
            arguments.multiply_gain(gain)
        arguments.shot, arguments.read = self.levels()
        arguments.seeds = self.seeds
        return not self.exact

    def forward(self, raw: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        gain = self.signal_gain()
        if gain is not None:
            raw = raw * gain
        shot, read = self.levels()
        seeds = self.seeds(raw.shape[0], image_index)
        if self.exact:
            return poisson_gaussian_exact(raw, shot, read, seeds)
        return poisson_gaussian(raw, shot, read, seeds)


class SensorNoise(NoisySensor):
    """Poisson-Gaussian noise with shot (variance coefficient) and read (std) levels stated directly or from the
    full well (see `__init__`). Learnable levels are bounded to [0, 2x] their initial values:
    level = 2 * init * sigmoid(p), started at p = 0, so a level starts in the middle of its bounds (a level of 0
    stays 0, with a finite gradient). Seeds and exact counts: `NoisySensor`.
    """

    config_section = "noise"

    def __init__(self, shot: float = NoiseConfig.shot, read: float = NoiseConfig.read,
                 full_well_electrons: float = NoiseConfig.full_well_electrons,
                 read_electrons: float = NoiseConfig.read_electrons, learnable: bool = NoiseConfig.learnable,
                 eval_seed: int = NoiseConfig.eval_seed):
        """Levels stated directly (``shot``, ``read``) or physically. With ``full_well_electrons`` > 0, a signal s
        (white level = 1) holds s * FWC electrons, so its shot variance is s / FWC (shot = 1 / FWC) and the read
        noise is read_electrons / FWC; ``shot`` and ``read`` are then ignored.

        Args:
            shot: shot-noise variance coefficient (variance = shot * signal), >= 0.
            read: read-noise standard deviation (units of the white level), >= 0.
            full_well_electrons: electrons at the white level (0: the levels are ``shot`` and ``read``).
            read_electrons: read noise in electrons (needs ``full_well_electrons``).
            learnable: whether both levels learn (bounded to [0, 2x] their initial values).
            eval_seed: the first noise seed in eval mode (`NoisySensor`).
        """
        super().__init__(eval_seed)
        problem = _electrons_problem(full_well_electrons, read_electrons)
        if problem:
            raise ValueError(f"SensorNoise: {problem}")
        if full_well_electrons > 0:
            shot, read = 1.0 / full_well_electrons, read_electrons / full_well_electrons
        if not (0 <= shot < math.inf and 0 <= read < math.inf):
            raise ValueError(f"noise.shot and noise.read must be finite and >= 0, got shot={shot}, read={read}")
        self.register_buffer("shot_init", torch.tensor(float(shot)))
        self.register_buffer("read_init", torch.tensor(float(read)))
        self.shot_logit = nn.Parameter(torch.tensor(0.0), requires_grad=learnable)
        self.read_logit = nn.Parameter(torch.tensor(0.0), requires_grad=learnable)

    @classmethod
    def check_section(cls, section, where: str) -> None:
        problem = _electrons_problem(section.full_well_electrons, section.read_electrons)
        if problem:
            raise ValueError(f"{where}: {problem}")

    def summary(self) -> dict:
        """The levels in use: shot variance coefficient and read standard deviation (units of the white level)."""
        shot, read = self.levels()
        return {"noise_shot": float(shot.detach()), "noise_read": float(read.detach())}

    def levels(self) -> tuple[torch.Tensor, torch.Tensor]:
        shot = 2 * self.shot_init * torch.sigmoid(self.shot_logit)
        read = 2 * self.read_init * torch.sigmoid(self.read_logit)
        if self.scale != 1:  # a what-if override (x * 1.0 is x: two kernels saved a call at the default)
            shot, read = shot * self.scale**2, read * self.scale
        return shot, read
