"""What a calibration hands back: the noise in electrons, the JSON record, the preset TOML and the mean-variance
plot.

Electrons. In white-level units a signal s holds s / shot electrons when shot is the variance coefficient of
Poisson counts (variance of the count N is N, and s = N * shot), so at the captures' gain:

- conversion gain K = shot * (white - black) raw codes (DN) per electron;
- full well = 1 / shot electrons at the white level (the electrons that fill the ADC's range);
- read noise = read / shot electrons.

These hold at the gain (ISO) the captures were taken at. Taking that gain as unity, the analog gain of 1 that the
project's photon budget starts from (`photons.analog_gain`), the full well is the sensor's own; a capture at a
higher ISO (gain G) reads a full well G times smaller than the pixel's, and the preset then describes the sensor
at that ISO. The captures' ISO is recorded where their EXIF states it.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from warpsense.calibration.fit import NoiseFit

UNITS = ("white level after black-level subtraction: signal = (raw - black) / (white - black); shot is a variance "
         "coefficient (noise variance = shot * signal + read^2), read a standard deviation")
ASSUMPTION = ("electrons at the captures' gain, taken as unity (the base ISO): the full well is the electrons at "
              "the white level (1 / shot); at a higher ISO G it is the pixel's full well / G")


def electrons(fit: NoiseFit, white_level: float, black_level: float, iso: float | None) -> dict:
    """The noise in electrons at the captures' gain (see the module docstring), with intervals."""
    span = white_level - black_level
    low, high = fit.shot_interval
    read_low, read_high = fit.read_interval
    return {
        "conversion_gain_dn_per_electron": fit.shot * span,
        "conversion_gain_interval": [low * span, high * span],
        "electrons_per_dn": 1.0 / (fit.shot * span),
        "full_well_electrons": 1.0 / fit.shot,
        "full_well_interval": [1.0 / high, 1.0 / low],
        "read_noise_electrons": fit.read / fit.shot,
        "read_noise_interval": [read_low / high, read_high / low],
        "read_noise_dn": fit.read * span,
        "white_level": white_level, "black_level": black_level, "iso": iso, "assumption": ASSUMPTION,
    }


def study_light(fit: NoiseFit, name: str, bits: int) -> dict:
    """A study plan's [[light]] at this sensor (the noise stage stated in electrons: shot = 1 / full well,
    read = read electrons / full well)."""
    return {"name": name, "full_well_electrons": 1.0 / fit.shot, "read_electrons": fit.read / fit.shot,
            "bits": int(bits)}


def slug(text: str) -> str:
    """A run or light name from free text: letters, digits and underscores."""
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_").lower() or "sensor"


def _number(value: float) -> str:
    """A TOML float that reads back as the same double."""
    return repr(float(value)) if math.isfinite(value) else "0.0"


def preset_text(fit: NoiseFit, base: str, name: str, bits: int, photons: bool, header: list[str]) -> str:
    """The preset TOML: ``base`` (a preset name or a TOML path), the run's ``name``, and the sensor: [noise] shot and
    read, or, for a base with the photon budget on (``photons``), [photons] full_well_electrons and read_electrons
    (the noise the budget draws at analog gain 1 is then the calibrated one); [quantize] bits either way."""
    lines = [f"# {line}" for line in header]
    lines += [f"base = {base!r}".replace("'", '"'), "[run]", f'name = "{name}"']
    if photons:
        lines += ["[photons]", f"full_well_electrons = {_number(1.0 / fit.shot)}",
                  f"read_electrons = {_number(fit.read / fit.shot)}"]
    else:
        lines += ["[noise]", "enabled = true", f"shot = {_number(fit.shot)}", f"read = {_number(fit.read)}"]
    lines += ["[quantize]", "enabled = true", f"bits = {int(bits)}"]
    return "\n".join(lines) + "\n"


def check_preset(path: Path, source: str) -> None:
    """The written preset loads as a config (`load_config`) and passes the stages' checks (`check_config`)."""
    from warpsense.config import load_config
    from warpsense.system.build import check_config

    check_config(load_config(str(path)), source)


def draw(path: str | Path, channels: dict[str, list[dict]], fits: dict[str, NoiseFit | None], pooled: NoiseFit,
         title: str) -> None:
    """The mean-variance plot: per channel, its points (mean, variance, standard error) and its fitted curve
    (clipping and quantization included, against the clipped mean), with the fit over all channels dashed; log
    axes, so that the read-noise floor and the shot-noise slope both show. Written atomically."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warpsense.calibration.model import clipped_moments, noise_variance
    from warpsense.files import atomic_write, plot_format

    colours = {"R": "tab:red", "G": "tab:green", "B": "tab:blue"}
    letters = list(channels)
    figure, axes = plt.subplots(1, len(letters), figsize=(4.2 * len(letters), 3.8), squeeze=False)
    for axis, letter in zip(axes[0], letters):
        points = [p for p in channels[letter] if p["mean"] > 0 and p["variance"] > 0]
        colour = colours.get(letter, "tab:gray")
        if points:
            mean = np.array([p["mean"] for p in points])
            variance = np.array([p["variance"] for p in points])
            error = np.array([p["error"] for p in points])
            axis.errorbar(mean, variance, yerr=np.minimum(error, variance * 0.999), fmt="o", ms=3, color=colour,
                          alpha=0.7, lw=0.8, label=f"{letter} points")
            lower, upper, step = points[0]["lower"], points[0]["upper"], points[0]["step"]
            grid = np.geomspace(mean.min() * 0.8, min(mean.max() * 1.2, upper), 200)
            for curve, style, label in ((fits.get(letter), "-", f"{letter} fit"), (pooled, "--", "all channels")):
                if curve is None:
                    continue
                model_mean, model_variance = clipped_moments(
                    grid, noise_variance(grid, curve.shot, curve.read**2), lower, upper, step)
                axis.plot(model_mean, model_variance, style, color="black" if style == "--" else colour, lw=1.2,
                          label=f"{label}: shot {curve.shot:.3g}, read {curve.read:.3g}")
        axis.set_xscale("log")
        axis.set_yscale("log")
        for which in (axis.xaxis, axis.yaxis):  # decades only: labelled minor ticks overlap on a short axis
            which.set_minor_formatter(matplotlib.ticker.NullFormatter())
        axis.set_xlabel("mean signal (white level = 1)")
        axis.set_ylabel("noise variance")
        axis.set_title(f"channel {letter}")
        axis.grid(True, which="both", alpha=0.25)
        axis.legend(fontsize=7, loc="upper left")
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    with atomic_write(path) as temporary:
        figure.savefig(temporary, dpi=120, format=plot_format(path))
    plt.close(figure)
