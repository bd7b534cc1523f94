"""A raw capture as the calibration reads it: its CFA site planes in white-level units, each with the ADC's clip
bounds and code step, and what its metadata says about the sensor (white and black levels, camera, ISO).

Captures are read by `warpsense.data.raw.read_capture`: DNG and the other raws rawpy/LibRaw reads, and the
``.safetensors`` mosaics `warpsense convert` and `warpsense simulate` write. The mosaic is already black-subtracted
per channel and divided by (white - black), the units of the project's noise.shot and noise.read.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

SATURATED = 0.5
"""A capture with more than this fraction of its pixels at the white level is refused as saturated."""
DARK_LEVEL = 0.01
"""A capture whose 99.9th percentile is below this fraction of the white level is refused as all dark."""


class CalibrateError(ValueError):
    """A capture (or a set of them) cannot be calibrated; the message names the file and what is missing."""


@dataclass
class Site:
    """One site of the CFA tile: its filter letter, its plane (float64 [h, w], white-level units) and the ADC's
    clip bounds and code step there (white-level units: the zero code is -black / (white - black))."""

    letter: str
    row: int
    col: int
    plane: np.ndarray
    lower: float
    upper: float
    step: float


@dataclass
class Capture:
    """A capture's site planes and sensor description."""

    path: Path
    sites: list[Site]
    pattern: str
    white_level: float
    black_levels: dict[str, float]
    bit_depth: int
    camera: str
    iso: float | None = None
    exposure_s: float | None = None
    height: int = 0
    width: int = 0
    notes: list[str] = field(default_factory=list)

    @property
    def letters(self) -> list[str]:
        """The CFA's filter letters, each once, in the tile's order."""
        return list(dict.fromkeys(site.letter for site in self.sites))

    def describe(self) -> dict:
        """What the JSON says about the file."""
        return {"path": str(self.path), "camera": self.camera, "cfa_pattern": self.pattern,
                "white_level": self.white_level, "black_levels": self.black_levels, "bit_depth": self.bit_depth,
                "iso": self.iso, "exposure_s": self.exposure_s, "height": self.height, "width": self.width}


def _exif(path: Path) -> tuple[float | None, float | None]:
    """(ISO, exposure time in seconds) from a TIFF-based raw's EXIF where it states them (> 0); LibRaw's Python
    binding exposes neither."""
    try:
        import tifffile

        from warpsense.data.raw import _quiet_tifffile

        with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
            tags = tif.pages[0].tags
            exif = tags["ExifTag"].value if "ExifTag" in tags else {}
            iso = exif.get("ISOSpeedRatings", exif.get("PhotographicSensitivity"))
            exposure = exif.get("ExposureTime")
    except Exception:  # noqa: BLE001 (not a TIFF-based raw, or unreadable tags: both are optional)
        return None, None
    if isinstance(iso, (tuple, list)):
        iso = iso[0] if iso else None
    if isinstance(exposure, (tuple, list)) and len(exposure) == 2:
        exposure = exposure[0] / exposure[1] if exposure[1] else None
    iso = float(iso) if isinstance(iso, (int, float)) and iso > 0 else None
    exposure = float(exposure) if isinstance(exposure, (int, float)) and exposure > 0 else None
    return iso, exposure


def _letter_black(metadata: dict, letter: str) -> float:
    """The black level (raw codes) of a filter letter: LibRaw's per-channel levels are indexed by its colour
    description ("RGBG": the two greens are 1 and 3); their mean where a letter has two."""
    blacks = [float(value) for value in metadata.get("black_levels") or [0.0]]
    description = str(metadata.get("color_desc") or "")
    chosen = [blacks[i] for i, char in enumerate(description[: len(blacks)]) if char == letter]
    return float(np.mean(chosen)) if chosen else float(np.mean(blacks))


def read_calibration_capture(path: str | Path, check_levels: bool = True) -> Capture:
    """Read one capture and check it can be calibrated; ``check_levels`` False reads a series' frame, whose dark
    frames and brightest flat fields are meant to be so, without the saturated and all-dark checks.

    Raises:
        CalibrateError: not a raw capture (the reader's reason), a CFA this reader cannot split, a saturated or all
            dark capture; the message names the file.
    """
    from warpsense.data.raw import RawFileError, read_capture

    path = Path(path)
    try:
        mosaic, metadata = read_capture(path)
    except (RawFileError, FileNotFoundError) as error:
        raise CalibrateError(str(error)) from None
    pattern = str(metadata.get("cfa_pattern", ""))
    tile = int(metadata.get("tile", 0) or 0)
    if pattern == "mono":
        pattern, tile = "M", 1
    if tile < 1 or len(pattern) != tile * tile:
        raise CalibrateError(f"{path}: its CFA pattern {pattern!r} (tile {tile}) does not name one filter per site")
    white = float(metadata.get("white_level", 0) or 0)
    if not white > 0:
        raise CalibrateError(f"{path}: its metadata states no white level: the noise cannot be put in its units")
    mosaic = np.asarray(mosaic, dtype=np.float64)
    height, width = mosaic.shape
    sites = []
    blacks = {}
    for index, letter in enumerate(pattern):
        row, col = divmod(index, tile)
        black = _letter_black(metadata, letter) if pattern != "M" else float((metadata.get("black_levels") or [0])[0])
        blacks[letter] = black
        span = white - black
        sites.append(Site(letter, row, col, mosaic[row::tile, col::tile], -black / span, 1.0, 1.0 / span))
    saturated = float(np.mean(mosaic >= 1.0 - 0.5 / (white - min(blacks.values()))))
    if check_levels and saturated > SATURATED:
        raise CalibrateError(f"{path}: saturated: {saturated:.0%} of its pixels are at the white level, too few "
                             "below it to read the noise")
    brightest = float(np.percentile(mosaic, 99.9))
    if check_levels and brightest < DARK_LEVEL:
        raise CalibrateError(f"{path}: all dark: 99.9% of its pixels are below {DARK_LEVEL:.0%} of the white level, "
                             "no signal levels to read the shot noise from (a dark frame belongs in a --series, "
                             "with --dark)")
    make, model = str(metadata.get("make", "")).strip(), str(metadata.get("model", "")).strip()
    camera = model if make and model.startswith(make) else f"{make} {model}".strip()
    iso, exposure = _exif(path) if path.suffix.lower() != ".safetensors" else (None, None)
    return Capture(path, sites, pattern if pattern != "M" else "mono", white, blacks,
                   int(metadata.get("bit_depth") or int(np.ceil(np.log2(white + 1)))), camera or "unknown camera",
                   iso, exposure, height, width)
