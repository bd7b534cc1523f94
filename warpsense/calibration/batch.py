"""`warpsense calibrate`'s work: captures in, the noise estimate out (printed, and as JSON, a preset and a plot).

Which method: without ``series`` every capture is a scene and is estimated alone (`single.estimate_capture`), then
all of them together (one sensor at one setting: captures of different cameras, bit depths, white levels or ISOs
are refused together). With ``series`` the captures are flat fields paired by level and ``darks`` dark frames
(`series.estimate_series`).

A batch goes on past a bad capture: each is read and estimated on its own, a failure is kept with its one-line
reason, and the estimate is made from the others; the failures are printed (``skipped ...``) and listed in the
JSON, and the command exits 2. When no capture can be used, nothing is estimated or written: one error line (the
file's own reason for a single capture). Outputs are written only once everything is estimated, each whole or not
at all (a temporary file renamed), and the preset is loaded back as a config before it is published.
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from warpsense.calibration.captures import CalibrateError, Capture, read_calibration_capture
from warpsense.calibration.fit import NoiseFit
from warpsense.calibration.report import UNITS, electrons, slug, study_light

DEFAULT_BASE = "camvid_raw_fixed"
"""The preset a calibrated preset inherits unless --base names another."""
SINGLE = "single capture: local variances of smooth regions, clipping-aware fit (Foi et al. 2008)"
SERIES = "photon transfer: flat-field pairs and dark frames (EMVA 1288)"


@dataclass
class Calibration:
    """A finished estimate: the curve over all channels and per channel, the captures behind it, per-file
    records, the plot's points per channel, the failures and notes."""

    method: str
    fit: NoiseFit
    channels: dict[str, NoiseFit | None]
    captures: list[Capture]
    files: list[dict]
    points: dict[str, list[dict]]
    failures: list[tuple[str, str]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    series: dict | None = None

    @property
    def camera(self) -> str:
        return self.captures[0].camera

    @property
    def bits(self) -> int:
        return self.captures[0].bit_depth

    def electrons(self) -> dict:
        first = self.captures[0]
        black = float(np.mean(list(first.black_levels.values())))
        isos = {c.iso for c in self.captures}
        return electrons(self.fit, first.white_level, black, isos.pop() if len(isos) == 1 else None)

    def light(self) -> dict:
        return study_light(self.fit, slug(self.camera), self.bits)


def _setting(capture: Capture) -> tuple:
    return (capture.camera, capture.white_level, tuple(sorted(capture.black_levels.items())), capture.bit_depth,
            capture.iso)


def _check_one_sensor(captures: list[Capture]) -> None:
    """Captures estimated together must be of one sensor at one setting."""
    first = captures[0]
    for capture in captures[1:]:
        if _setting(capture) != _setting(first):
            raise CalibrateError(
                f"{capture.path}: not the sensor and setting of {first.path} (camera {capture.camera!r} vs "
                f"{first.camera!r}, white level {capture.white_level:g} vs {first.white_level:g}, black "
                f"{capture.black_levels} vs {first.black_levels}, {capture.bit_depth} vs {first.bit_depth} bits, ISO "
                f"{capture.iso} vs {first.iso}): calibrate them separately")


def _expand(inputs: list[str]) -> tuple[list[Path], list[tuple[str, str]]]:
    from warpsense.data.raw import expand_inputs

    paths, problems = expand_inputs(inputs)
    return paths, [(str(path), reason) for path, reason in problems]


def _nothing(failures: list[tuple[str, str]]) -> CalibrateError:
    if len(failures) == 1:
        return CalibrateError(failures[0][1])
    return CalibrateError(f"no capture could be calibrated: {'; '.join(reason for _, reason in failures)}")


def calibrate_captures(inputs: list[str], series: bool = False, darks: list[str] = (),
                       progress: bool = False) -> Calibration:
    """Estimate the noise of ``inputs`` (files, folders of raws, glob patterns; see the module docstring).

    Raises:
        CalibrateError: no capture could be used (one line: the file's reason, or every file's), or the usable
            ones are of different sensors or settings, or a series gives too few points.
    """
    from tqdm import tqdm

    from warpsense.calibration.series import estimate_series
    from warpsense.calibration.single import estimate_capture, fit_together

    paths, failures = _expand(inputs)
    dark_paths, dark_failures = _expand(list(darks)) if darks else ([], [])
    failures += dark_failures
    if darks and not series:
        raise CalibrateError("--dark frames belong to a photon-transfer series: add --series")
    captures, estimates, dark_captures = [], [], []
    for path in tqdm(paths + dark_paths, desc="calibrate", unit="file", disable=not progress):
        try:
            capture = read_calibration_capture(path, check_levels=not series)
            if path in dark_paths:
                dark_captures.append(capture)
            elif series:
                captures.append(capture)
            else:
                estimates.append(estimate_capture(capture))
                captures.append(capture)
        except CalibrateError as error:
            failures.append((str(path), str(error)))
    if not captures:
        raise _nothing(failures or [("", f"no captures in {' '.join(inputs)}")])
    _check_one_sensor(captures + dark_captures)
    if series:
        result, unpaired = estimate_series(captures, dark_captures)
        failures += [(str(path), reason) for path, reason in unpaired]
        paired = {file for pair in result.pairs for file in pair}
        used = [c for c in captures if str(c.path) in paired] + dark_captures
        points = {}
        for point in result.points:
            site = next(s for s in captures[0].sites if s.letter == point.letter)
            if point.used and point.mean > 0:
                points.setdefault(point.letter, []).append(
                    {"mean": point.mean, "variance": point.variance, "error": float(np.sqrt(point.variance_variance)),
                     "lower": site.lower, "upper": site.upper, "step": site.step})
        files = [{**c.describe(), "role": "dark" if c in dark_captures else "flat"} for c in used]
        series_record = {"pairs": [list(pair) for pair in result.pairs], "darks": result.darks,
                         "points": [{"channel": p.letter, "kind": p.kind, "mean": p.mean, "variance": p.variance,
                                     "files": list(p.files), "used": p.used} for p in result.points]}
        return Calibration(SERIES, result.fit, result.channels, used, files, points, failures, result.notes,
                           series_record)
    if len(estimates) == 1:
        fit, channels = estimates[0].fit, estimates[0].channels
    else:
        fit, channels = fit_together(estimates)
    files, points, notes = [], {}, []
    for estimate in estimates:
        files.append({**estimate.capture.describe(), "noise": estimate.fit.to_dict(),
                      "per_channel": {k: v.to_dict() if v else None for k, v in estimate.channels.items()},
                      "regions": estimate.regions()})
        notes += estimate.notes
        for site_sets in estimate.sites:
            sets, site = site_sets.group.sets, site_sets.site
            for i in range(len(sets)):
                points.setdefault(site.letter, []).append(
                    {"mean": float(sets.mean[i]), "variance": float(sets.variance[i]),
                     "error": float(np.sqrt(sets.variance_variance[i])), "lower": site.lower, "upper": site.upper,
                     "step": site.step})
    return Calibration(SINGLE, fit, channels, captures, files, points, failures, notes)


def calibration_json(calibration: Calibration, preset: str | None = None) -> dict:
    """The JSON record (docs/guide/calibrate.md lists its fields)."""
    fit = calibration.fit
    record = {
        "method": calibration.method,
        "camera": calibration.camera,
        "units": UNITS,
        "noise": {**fit.to_dict(),
                  "per_channel": {k: v.to_dict() if v else None for k, v in calibration.channels.items()}},
        "electrons": calibration.electrons(),
        "study_light": calibration.light(),
        "files": calibration.files,
        "failed": [{"path": path, "reason": reason} for path, reason in calibration.failures],
        "notes": calibration.notes,
        "preset": preset,
    }
    if calibration.series is not None:
        record["series"] = calibration.series
    return record


def summary(calibration: Calibration) -> str:
    """What the command prints: the estimate over all channels, per channel, and in electrons."""
    fit = calibration.fit
    count = len(calibration.captures)
    lines = [f"calibrated {count} capture(s) of {calibration.camera} ({calibration.method.split(':')[0]}), units of "
             f"the white level:",
             f"  all    noise.shot = {fit.shot:.4g} [{fit.shot_interval[0]:.4g}, {fit.shot_interval[1]:.4g}]  "
             f"noise.read = {fit.read:.4g} [{fit.read_interval[0]:.4g}, {fit.read_interval[1]:.4g}]"]
    for letter, channel in calibration.channels.items():
        if channel is None:
            lines.append(f"  {letter:6s} too few level sets for a fit of its own")
            continue
        lines.append(f"  {letter:6s} noise.shot = {channel.shot:.4g} [{channel.shot_interval[0]:.4g}, "
                     f"{channel.shot_interval[1]:.4g}]  noise.read = {channel.read:.4g} [{channel.read_interval[0]:.4g}"
                     f", {channel.read_interval[1]:.4g}]")
    e = calibration.electrons()
    iso = f" (ISO {e['iso']:g})" if e["iso"] else ""
    lines.append(f"  electrons at the captures' gain{iso}: {e['conversion_gain_dn_per_electron']:.4g} DN/e-, read "
                 f"noise {e['read_noise_electrons']:.3g} e-, full well {e['full_well_electrons']:.4g} e-")
    lines += [f"  note: {note}" for note in calibration.notes]
    return "\n".join(lines)


def base_has_photons(base: str) -> bool:
    """Whether the base preset (a name or TOML path) states the sensor by the photon budget (photons.enabled)."""
    from warpsense.config import load_config

    return load_config(base).photons.enabled


def check_base(base: str) -> None:
    """Refuse a --base that does not resolve (one line naming it), before any capture is read."""
    from warpsense.config import ConfigError, load_config

    try:
        load_config(base)
    except ConfigError as error:
        raise ValueError(f"--base {base}: {error}") from None


def write_outputs(calibration: Calibration, json_path: str | None, preset_path: str | None,
                  plot_path: str | None, base: str = DEFAULT_BASE) -> None:
    """Write the requested outputs; the preset is checked (`report.check_preset`) before anything is written."""
    from warpsense.calibration.report import check_preset, draw, preset_text
    from warpsense.files import atomic_write, write_json

    text = None
    if preset_path:
        base_value = str(Path(base).resolve()) if Path(base).suffix.lower() == ".toml" else base
        fit, e = calibration.fit, calibration.electrons()
        header = [f"{calibration.camera}: sensor noise calibrated by `warpsense calibrate` from "
                  f"{len(calibration.captures)} capture(s) ({calibration.method.split(':')[0]}).",
                  f"noise.shot 95% [{fit.shot_interval[0]:.4g}, {fit.shot_interval[1]:.4g}], noise.read 95% "
                  f"[{fit.read_interval[0]:.4g}, {fit.read_interval[1]:.4g}] (units of the white level).",
                  f"At the captures' gain: {e['conversion_gain_dn_per_electron']:.4g} DN/e-, read noise "
                  f"{e['read_noise_electrons']:.3g} e-, full well {e['full_well_electrons']:.4g} e- (1 / shot).",
                  "A study's [[light]] at this sensor: full_well_electrons = "
                  f"{1 / fit.shot:.6g}, read_electrons = {fit.read / fit.shot:.6g}, bits = {calibration.bits}."]
        text = preset_text(fit, base_value, slug(Path(preset_path).stem), calibration.bits,
                           base_has_photons(base), header)
        with tempfile.TemporaryDirectory() as folder:
            trial = Path(folder) / Path(preset_path).name
            trial.write_text(text)
            check_preset(trial, str(preset_path))
    if plot_path:
        draw(plot_path, calibration.points, calibration.channels, calibration.fit,
             f"{calibration.camera}: {len(calibration.captures)} capture(s), {calibration.method.split(':')[0]}")
    if text is not None:
        with atomic_write(preset_path) as temporary:
            temporary.write_text(text)
    if json_path:
        write_json(json_path, calibration_json(calibration, str(preset_path) if preset_path else None))


def calibrate_files(inputs: list[str], json_path: str | None = None, preset_path: str | None = None,
                    plot_path: str | None = None, base: str = DEFAULT_BASE, series: bool = False,
                    darks: list[str] = (), progress: bool = False) -> list[tuple[str, str]]:
    """Calibrate, print the summary and the skipped captures, write the outputs; returns the failures (the
    command exits 2 when there are any)."""
    calibration = calibrate_captures(inputs, series, darks, progress)
    write_outputs(calibration, json_path, preset_path, plot_path, base)
    for _, reason in calibration.failures:
        print(f"warpsense calibrate: skipped {reason}", file=sys.stderr)
    print(summary(calibration))
    written = [str(path) for path in (json_path, preset_path, plot_path) if path]
    if written:
        print(f"wrote {', '.join(written)}")
    return calibration.failures
