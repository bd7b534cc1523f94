"""Photon budget stage: the sensor stated physically, from a scene light level to ADC units.

A pixel behind filter phi (transmittance per band, `warpsense.camera.cfa.FILTERS`) that sees linear radiance L (the
scene's, times the optics' relative throughput: (2 / N)^2 t / 10 ms, `warpsense.camera.optics`) collects

    electrons = E_mid * (phi . L) / (3 * 0.18) * (pitch / 3 um)^2 * QE / 0.6

where E_mid is the light level: the electrons a mid-grey patch (18% linear, all three bands) gives a clear pixel of
the reference pixel (3 um pitch, quantum efficiency 0.6) at f/2 in 10 ms (named levels in
`warpsense.choices.LIGHT_LEVELS`). A clear pixel thus collects 3x a green one in a flat white field. The pixel's
count has Poisson shot noise (variance = electrons, the Gaussian approximation in training; ``exact_noise`` draws true
Poisson counts), read noise of ``read_electrons`` (std), and an analog gain G >= 1 maps the charge to the ADC: the
signal in ADC units (1 = the top code) is electrons * G / FWC, so unity gain puts the full well at the top code and a
higher gain amplifies a dim signal above the ADC's steps at the price of clipping at FWC / G electrons. With G >= 1
the ADC clips at or below the full well, so the quantizer's clip is the full-well clip.

The network does not see a frame rescaled to a fixed mean (that would hide the photon count): the camera's output is
the ADC value times a fixed digital gain (``digital_gain``; 0 = the gain that maps the mid-grey patch through a clear
filter to 0.5 at the starting design), recorded in the checkpoint.
"""

from __future__ import annotations

import torch

from warpsense.camera.bounds import check_log_bounds, log_bounded, log_bounded_parameter
from warpsense.camera.noise import NoisySensor
from warpsense.camera.stage import SensorArguments
from warpsense.choices import LIGHT_LEVELS
from warpsense.config import PhotonsConfig

MID_GREY = 0.18
"""Linear reflectance of the mid-grey patch that states a light level."""
REFERENCE_PITCH_UM, REFERENCE_QE = 3.0, 0.6
"""The reference pixel of the light levels."""


def light_electrons(light: str, mid_grey_electrons: float = 0.0) -> float:
    """The light level E_mid in electrons: ``mid_grey_electrons`` when > 0, else the named level."""
    if mid_grey_electrons > 0:
        return float(mid_grey_electrons)
    if light not in LIGHT_LEVELS:
        raise KeyError(f"unknown light level {light!r}; valid levels: {', '.join(LIGHT_LEVELS)}")
    return LIGHT_LEVELS[light]


def gain_problem(analog_gain: float, gain_max: float) -> str | None:
    """Why an analog gain cannot start at ``analog_gain`` (a message naming the key), or None. A learned gain may
    start on a bound (unity gain, the default, included): `warpsense.camera.bounds` starts it just inside."""
    return check_log_bounds("photons.analog_gain", analog_gain, 1.0, gain_max, ("1", "photons.gain_max"))


class PhotonBudget(NoisySensor):
    """Relative exposure [B, 1, H, W] (phi . L, after the CFA) -> noisy signal in ADC units; owns the analog gain.

    Learnable gain: G = G_max ** sigmoid(p) in [1, G_max] (log-uniform), started at ``analog_gain`` (a start on a
    bound, unity gain included, just inside it: `warpsense.camera.bounds`). A fixed gain on a bound is exact.
    """

    config_section = "photons"

    def __init__(self, light: str = PhotonsConfig.light, mid_grey_electrons: float = PhotonsConfig.mid_grey_electrons,
                 pixel_pitch_um: float = PhotonsConfig.pixel_pitch_um,
                 quantum_efficiency: float = PhotonsConfig.quantum_efficiency,
                 full_well_electrons: float = PhotonsConfig.full_well_electrons,
                 read_electrons: float = PhotonsConfig.read_electrons, analog_gain: float = PhotonsConfig.analog_gain,
                 gain_learnable: bool = PhotonsConfig.gain_learnable, gain_max: float = PhotonsConfig.gain_max,
                 digital_gain: float = PhotonsConfig.digital_gain, eval_seed: int = PhotonsConfig.eval_seed):
        """Args:
            light: the scene light level by name (`LIGHT_LEVELS`), unless ``mid_grey_electrons`` > 0.
            mid_grey_electrons: > 0: the light level E_mid in electrons instead of by name.
            pixel_pitch_um, quantum_efficiency: the pixel (um; in (0, 1]).
            full_well_electrons, read_electrons: full-well capacity and read noise (std), in electrons.
            analog_gain, gain_learnable, gain_max: the analog gain G in [1, gain_max], learned or fixed.
            digital_gain: the gain from ADC units to the network's input (0: mid-grey through a clear filter at the
                starting design -> 0.5).
            eval_seed: the first noise seed in eval mode (`NoisySensor`).
        """
        mid_grey_electrons = light_electrons(light, mid_grey_electrons)
        if not (pixel_pitch_um > 0 and quantum_efficiency > 0 and full_well_electrons > 0 and read_electrons >= 0):
            raise ValueError("photons: pitch, quantum efficiency and full well must be > 0, read noise >= 0")
        super().__init__(eval_seed)
        # electrons per unit of relative exposure phi . L (a clear pixel on the mid-grey patch collects E_mid)
        self.electrons_per_unit = (mid_grey_electrons / (3 * MID_GREY) * (pixel_pitch_um / REFERENCE_PITCH_UM) ** 2
                                   * quantum_efficiency / REFERENCE_QE)
        self.full_well = float(full_well_electrons)
        self.read_electrons = float(read_electrons)
        self.gain_max = float(gain_max)
        self.gain_logit = log_bounded_parameter(analog_gain, 1.0, gain_max, learnable=gain_learnable,
                                                key="photons.analog_gain", bound_keys=("1", "photons.gain_max"))
        if digital_gain <= 0:  # the mid-grey patch through a clear filter at the starting design -> 0.5
            digital_gain = 0.5 * self.full_well / (mid_grey_electrons * analog_gain)
        self.register_buffer("digital_gain", torch.tensor(float(digital_gain)))

    @classmethod
    def check_section(cls, section, where: str) -> None:
        problem = gain_problem(section.analog_gain, section.gain_max)
        if problem:
            raise ValueError(f"{where}: {problem}")

    @classmethod
    def check_design(cls, config, where: str) -> None:
        """The photon budget states the noise and the exposure itself, and a frame rescaled to a mean would hide its
        photon count: the stages that do so otherwise must be off, the ADC range fixed."""
        section = getattr(config, cls.config_section, None)
        if section is None or not section.enabled:
            return
        if config.noise.enabled:
            raise ValueError(f"{where}: photons.enabled states the noise from electrons: set noise.enabled = false")
        if config.exposure.enabled:
            raise ValueError(f"{where}: photons.enabled sets the exposure through optics.exposure_ms, the "
                             "f-number and photons.analog_gain: set exposure.enabled = false")
        if config.optics.enabled and config.optics.normalize_mean > 0:
            raise ValueError(f"{where}: photons.enabled needs optics.normalize_mean = 0 (rescaling each frame "
                             "to a mean would hide the photon count)")
        if config.quantize.enabled and (config.quantize.mode != "full_well" or config.quantize.white_level != 1):
            raise ValueError(f"{where}: photons.enabled needs quantize.mode = \"full_well\" and "
                             "quantize.white_level = 1 (the analog gain maps the charge to the ADC's range)")

    def analog_gain(self) -> torch.Tensor:
        """G in [1, G_max] (dimensionless)."""
        return log_bounded(self.gain_logit, 1.0, self.gain_max)

    def adc_per_electron(self) -> torch.Tensor:
        """ADC units (1 = the top code) per electron: G / FWC."""
        return self.analog_gain() / self.full_well

    def levels(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Noise in ADC units: shot variance coefficient G / FWC (variance = electrons * (G / FWC)^2) and read std
        read_electrons * G / FWC; ``noise_scale`` scales both standard deviations."""
        per_electron = self.adc_per_electron()
        return per_electron * self.scale**2, per_electron * self.read_electrons * self.scale

    def signal_gain(self) -> torch.Tensor:
        """ADC units per unit of relative exposure phi . L: electrons_per_unit * G / FWC."""
        return self.electrons_per_unit * self.adc_per_electron()

    def summary(self) -> dict:
        """The analog gain, the electrons a mid-grey patch gives a clear pixel at the reference throughput, the
        noise levels in ADC units and the digital gain."""
        shot, read = self.levels()
        return {"analog_gain": float(self.analog_gain().detach()),
                "mid_grey_electrons": self.electrons_per_unit * 3 * MID_GREY,
                "noise_shot": float(shot.detach()), "noise_read": float(read.detach()),
                "digital_gain": float(self.digital_gain)}

    def fuse(self, arguments: SensorArguments) -> bool:
        """As `NoisySensor.fuse`, and the camera applies the digital gain after the ADC."""
        arguments.digital_gain = self.digital_gain
        return super().fuse(arguments)
