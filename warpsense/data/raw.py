"""Raw captures (DNG first; any Bayer raw LibRaw reads) <-> normalised RAW mosaics, through rawpy/LibRaw, and a
capture prepared for a network (cropped to its CFA phase, binned) or previewed in grey.

`warpsense convert` writes ``<stem>.safetensors`` with tensor ``mosaic`` [1, H, W] float32: the visible area,
black-subtracted per channel and divided by (white - black), and a JSON metadata entry ``warpsense`` (CFA letters,
tile, black levels, white level, bit depth, as-shot white balance, colour matrix, make/model, source sha256).
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import logging
import math
import sys
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from torch.nn import functional as F
from tqdm import tqdm

from warpsense.choices import BAYER_LAYOUTS, IMAGE_SUFFIXES
from warpsense.errors import first_line
from warpsense.files import atomic_write

RAW_SUFFIXES = {".dng", ".cr2", ".cr3", ".nef", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw"}


class RawFileError(ValueError):
    """A raw file cannot be converted; the message names the file and the reason."""


@contextlib.contextmanager
def _quiet_tifffile():
    """tifffile logs every tag it cannot read (a truncated file: one line per tag) before raising or going on; the
    caller reports the file's problem in one line, so those logs are held back while it reads tags."""
    logger = logging.getLogger("tifffile")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)


def _camera_names(path: Path) -> tuple[str, str]:
    """Make and Model from the TIFF/DNG tags when present (LibRaw's Python binding does not expose them)."""
    try:
        import tifffile

        with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
            tags = tif.pages[0].tags
            return (str(tags["Make"].value).strip("\0 ") if "Make" in tags else "",
                    str(tags["Model"].value).strip("\0 ") if "Model" in tags else "")
    except Exception:  # not a TIFF-based raw, or unreadable tags: names are optional
        return "", ""


def _require_dng(path: Path) -> None:
    """A .dng must be a DNG: a plain TIFF renamed .dng would otherwise be read by LibRaw as a Bayer mosaic."""
    import tifffile

    try:
        with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
            is_dng = "DNGVersion" in tif.pages[0].tags
    except Exception:  # noqa: BLE001 (unparsable as TIFF: LibRaw gives the reason)
        return
    if not is_dng:
        raise RawFileError(f"{path}: named .dng but has no DNGVersion tag (a plain TIFF?): refusing")


def read_raw_file(path: str | Path) -> tuple[np.ndarray, dict]:
    """(normalised mosaic float32 [H, W], metadata) of a raw file; RawFileError for what cannot be converted."""
    import rawpy  # imported lazily: only raw-file paths need LibRaw

    path = Path(path)
    if path.is_dir():
        raise RawFileError(f"{path}: is a directory, not a raw file")
    if path.suffix.lower() == ".dng":
        _require_dng(path)
    try:
        raw = rawpy.imread(str(path))
    except (rawpy.LibRawError, OSError) as error:
        hint = ("; an sRGB image is a scene, not a capture: `warpsense simulate` makes a camera's capture of it"
                if path.suffix.lower() in IMAGE_SUFFIXES else "")
        raise RawFileError(f"{path}: LibRaw cannot read it ({type(error).__name__}: {error}){hint}") from None
    try:
        with raw:
            return _decode(raw, path, rawpy)
    except rawpy.LibRawError as error:  # LibRaw unpacks lazily: a truncated file fails at the first pixel access
        raise RawFileError(f"{path}: LibRaw cannot unpack it ({type(error).__name__}: {error})") from None


def _decode(raw, path: Path, rawpy) -> tuple[np.ndarray, dict]:
    if raw.raw_type != rawpy.RawType.Flat or raw.num_colors < 3 or raw.raw_pattern is None:
        raise RawFileError(f"{path}: not a colour-filter mosaic (LinearRaw / stacked data): refusing")
    visible = raw.raw_image_visible.astype(np.float32)
    colors = raw.raw_colors_visible
    description = raw.color_desc.decode()
    tile = raw.raw_pattern.shape[0]
    letters = ["".join(description[colors[y, x]] for x in range(tile)) for y in range(tile)]
    pattern = "".join(letters)
    if pattern not in BAYER_LAYOUTS:
        raise RawFileError(f"{path}: CFA pattern {pattern!r} (tile {tile}) is not supported; supported: "
                           f"{', '.join(BAYER_LAYOUTS)}")
    black = np.asarray(raw.black_level_per_channel, dtype=np.float32)
    white = float(raw.white_level)
    if (white <= black).any():  # the normalisation would divide by zero or a negative range: NaN or flipped values
        raise RawFileError(f"{path}: its white level {white:g} is not above its black level(s) "
                           f"{', '.join(f'{value:g}' for value in black)}: refusing")
    black_map = black[colors]
    mosaic = (visible - black_map) / (white - black_map)
    make, model = _camera_names(path)
    metadata = {
        "cfa_pattern": pattern, "tile": tile, "color_desc": description,
        "black_levels": black.tolist(), "white_level": white, "bit_depth": int(math.ceil(math.log2(white + 1))),
        "as_shot_white_balance": [float(v) for v in raw.camera_whitebalance],
        "color_matrix": np.asarray(raw.color_matrix, dtype=float).tolist(),
        "rgb_xyz_matrix": np.asarray(raw.rgb_xyz_matrix, dtype=float).tolist(),
        "make": make, "model": model, "height": int(mosaic.shape[0]), "width": int(mosaic.shape[1]),
        "source": path.name, "source_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
    }
    return mosaic.astype(np.float32), metadata


def convert_file(path: str | Path, out_dir: str | Path) -> Path:
    """Convert one raw file to ``out_dir/<stem>.safetensors`` (temp file + rename: never a partial output)."""
    mosaic, metadata = read_raw_file(path)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"{Path(path).stem}.safetensors"
    with atomic_write(target) as temporary:
        save_file({"mosaic": torch.from_numpy(mosaic)[None].contiguous()}, str(temporary),
                  metadata={"warpsense": json.dumps(metadata)})
    return target


def load_raw(path: str | Path) -> tuple[torch.Tensor, dict]:
    """Read a converted file: (mosaic float32 [1, H, W], metadata dict with ``cfa_pattern`` etc.).

    Raises:
        RawFileError: the file is not one `warpsense convert` or `warpsense simulate` wrote (empty, truncated, not
            safetensors, or another safetensors file such as a checkpoint); the message names it and the reason.
    """
    from safetensors import safe_open

    path = Path(path)

    def refused(reason: str) -> RawFileError:
        return RawFileError(f"{path}: not a raw capture written by `warpsense convert` or `warpsense simulate` "
                            f"({reason})")

    try:
        with safe_open(str(path), framework="pt") as handle:
            text = (handle.metadata() or {}).get("warpsense")
            mosaic = handle.get_tensor("mosaic") if "mosaic" in handle.keys() else None
    except Exception as error:  # safetensors raises several types for zero-byte, truncated or foreign files
        raise refused(first_line(error)) from None
    if mosaic is None:
        raise refused("no 'mosaic' tensor")
    # what convert and simulate write; another tool's tensor would fail later in predict with a traceback
    if mosaic.dtype != torch.float32 or mosaic.ndim != 3 or mosaic.shape[0] != 1 or min(mosaic.shape[1:]) < 2:
        raise refused(f"its 'mosaic' is {str(mosaic.dtype).removeprefix('torch.')} {list(mosaic.shape)}, expected "
                      "float32 [1, H, W] with H, W >= 2")
    if not torch.isfinite(mosaic).all():
        raise refused("its 'mosaic' holds NaN or infinite values")
    if text is None:
        raise refused("no 'warpsense' metadata")
    try:
        metadata = json.loads(text)
    except json.JSONDecodeError as error:
        raise refused(f"its 'warpsense' metadata is not JSON: {error}") from None
    if not isinstance(metadata, dict) or not isinstance(metadata.get("cfa_pattern"), str):
        raise refused("its 'warpsense' metadata names no cfa_pattern")
    return mosaic, metadata


def read_capture(path: str | Path) -> tuple[np.ndarray, dict]:
    """Normalised mosaic float32 [H, W] and metadata (``cfa_pattern`` ...) of a raw file (DNG and what LibRaw
    reads) or of `warpsense convert`'s output (.safetensors)."""
    if Path(path).is_dir():
        raise RawFileError(f"{path}: is a folder, expected a raw file (.dng or another raw format LibRaw reads, or "
                           "a .safetensors written by `warpsense convert` or `warpsense simulate`)")
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if Path(path).suffix.lower() == ".safetensors":
        mosaic, metadata = load_raw(path)
        return mosaic[0].numpy(), metadata
    return read_raw_file(path)


def bin_mosaic(mosaic: torch.Tensor, factor: int) -> torch.Tensor:
    """Downscale a 2x2 Bayer mosaic [H, W] by ``factor`` keeping its layout: each of the 4 site planes is
    average-pooled, then re-interleaved."""
    if factor <= 1:
        return mosaic
    planes = F.pixel_unshuffle(mosaic[None, None], 2)
    planes = F.avg_pool2d(planes, factor)
    return F.pixel_shuffle(planes, 2)[0, 0]


def prepare_capture(mosaic: np.ndarray, file_pattern: str, model_pattern: str,
                    target_width: int) -> tuple[torch.Tensor, int, tuple[int, int]]:
    """A capture's mosaic as a network trained on ``model_pattern`` reads it: cropped by one pixel into that CFA
    phase, clipped to [0, 1], cut to whole 2x2 tiles and binned to about ``target_width`` pixels wide (the scale the
    network was trained at).

    Args:
        mosaic: [H, W] normalised mosaic (`read_capture`).
        file_pattern: the capture's 2x2 layout (its metadata's ``cfa_pattern``).
        model_pattern: the 2x2 Bayer layout the network was trained with.
        target_width: the width to bin towards.

    Returns:
        (the prepared mosaic [h, w], the binning factor, the (dy, dx) phase crop).
    """
    # imported here: the camera package loads Warp, which `warpsense convert` (a user of this module) never needs
    from warpsense.camera.geometry import phase_offset

    dy, dx = phase_offset(file_pattern, model_pattern)
    prepared = torch.from_numpy(np.ascontiguousarray(mosaic[dy:, dx:])).clamp(0, 1)
    prepared = prepared[: prepared.shape[0] // 2 * 2, : prepared.shape[1] // 2 * 2]
    factor = max(1, round(prepared.shape[1] / target_width))
    return bin_mosaic(prepared, factor), factor, (dy, dx)


def preview_grey(mosaic: np.ndarray) -> np.ndarray:
    """[H, W] grey preview of a CFA mosaic without its checkerboard: each 2 x 2 tile's mean (every filter of the
    tile once), on the tile's four pixels."""
    height, width = mosaic.shape
    even = np.pad(mosaic, ((0, height % 2), (0, width % 2)), mode="edge")
    tiles = (even[0::2, 0::2] + even[0::2, 1::2] + even[1::2, 0::2] + even[1::2, 1::2]) / 4
    return np.repeat(np.repeat(tiles, 2, axis=0), 2, axis=1)[:height, :width]


def expand_inputs(inputs: list[str]) -> tuple[list[Path], list[tuple[Path, str]]]:
    """Files, folders (raw files inside, recursively) and glob patterns -> (sorted unique paths, problems).

    Problems are reported, not dropped: a named folder without raw files, a folder named like a raw file, a pattern
    that matches nothing."""
    found, problems = [], []
    for item in inputs:
        path = Path(item)
        if path.is_dir():
            inside = [p for p in sorted(path.rglob("*")) if p.suffix.lower() in RAW_SUFFIXES]
            problems += [(p, f"{p}: is a directory, not a raw file") for p in inside if p.is_dir()]
            files = [p for p in inside if p.is_file()]
            if not files and path.suffix.lower() not in RAW_SUFFIXES:
                problems.append((path, f"{path}: no raw files ({', '.join(sorted(RAW_SUFFIXES))}) in this folder"))
            found += files if path.suffix.lower() not in RAW_SUFFIXES else [path]
        elif any(ch in item for ch in "*?["):
            matches = [Path(p) for p in sorted(glob.glob(item, recursive=True))]
            if not matches:
                problems.append((path, f"{item}: the pattern matches nothing"))
            found += [p for p in matches if p.is_file()]
        else:
            found.append(path)
    unique = []
    for path in found:
        if path not in unique:
            unique.append(path)
    return unique, problems


def up_to_date(path: Path, target: Path) -> bool:
    """Whether ``target`` is a conversion of ``path`` as it is now: a readable output whose metadata names the same
    source bytes (``source_sha256``). What lets an interrupted batch go on where it stopped."""
    from safetensors import safe_open

    if not target.is_file():
        return False
    try:
        with safe_open(str(target), framework="pt") as handle:
            recorded = json.loads((handle.metadata() or {}).get("warpsense", "{}")).get("source_sha256")
    except Exception:  # noqa: BLE001 - a foreign, truncated or unreadable output is converted again
        return False
    try:
        return recorded == hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as error:  # reported as the source's, not as "cannot write its output"
        raise RawFileError(f"{path}: cannot read it ({error})") from None


def convert_files(inputs: list[str], out_dir: str | Path, progress: bool = True,
                  force: bool = False) -> list[tuple[Path, str]]:
    """Convert every input; a failing file is reported on stderr with a one-line reason and skipped, and the batch
    goes on. Two inputs with one stem would write one output: the second is refused, naming the first. An output
    that already converts the same source bytes is kept (`up_to_date`; ``force`` converts it again), so a batch run
    again after an interruption goes on where it stopped.

    Returns the failures [(path, reason)]; the CLI exits 2 when there are any.

    Raises:
        RawFileError: no input names a file to convert (empty folders, patterns that match nothing), with every
            input's reason in one line; nothing is written.
    """
    paths, failures = expand_inputs(inputs)
    if not paths:  # an error, not an empty batch: "converted 0 of 0 file(s)" said nothing useful
        reasons = "; ".join(reason for _, reason in failures) or f"no raw files in {' '.join(inputs)}"
        raise RawFileError(f"nothing to convert: {reasons}")
    for _, reason in failures:
        print(f"warpsense convert: skipped {reason}", file=sys.stderr)
    outputs: dict[str, Path] = {}
    kept = 0
    for path in tqdm(paths, desc="convert", unit="file", disable=not progress):
        try:
            name = f"{path.stem}.safetensors"
            if name in outputs:
                raise RawFileError(f"{path}: its output {name} would overwrite the one from {outputs[name]}; "
                                   "convert it into another folder")
            if not path.exists():
                raise RawFileError(f"{path}: no such file")
            if not force and up_to_date(path, Path(out_dir) / name):
                kept += 1
            else:
                convert_file(path, out_dir)
            outputs[name] = path
        except (RawFileError, OSError) as error:
            reason = str(error) if isinstance(error, RawFileError) else f"{path}: cannot write its output ({error})"
            failures.append((path, reason))
            tqdm.write(f"warpsense convert: skipped {reason}", file=sys.stderr)
    failed = f"; {len(failures)} failed" if failures else ""
    where = f" into {out_dir}" if outputs else ""  # nothing written: no folder to name
    earlier = f" ({kept} up to date from an earlier run, kept)" if kept else ""
    print(f"converted {len(outputs)} of {len(paths)} file(s){where}{earlier}{failed}")
    return failures


_CFA_CODES = {"R": 0, "G": 1, "B": 2}


def write_dng(path: str | Path, mosaic: np.ndarray, pattern: str, black_level: int = 0, white_level: int = 1023,
              make: str = "warpsense", model: str = "simulated") -> None:
    """Write a single-channel Bayer mosaic as a minimal DNG (1.4) that LibRaw reads.

    Args:
        mosaic: [H, W] values in [0, 1] (normalised, as produced by the sensor simulation) or integer codes.
        pattern: one of RGGB, BGGR, GRBG, GBRG (CFARepeatPatternDim 2x2, CFAPattern).
        black_level, white_level: stored as BlackLevel / WhiteLevel; float input is mapped to
            black + value * (white - black) and rounded.
    """
    import tifffile

    if pattern not in BAYER_LAYOUTS:
        raise ValueError(f"write_dng: pattern must be one of {BAYER_LAYOUTS}, got {pattern!r}")
    mosaic = np.asarray(mosaic)
    if mosaic.ndim != 2:
        raise ValueError(f"write_dng: mosaic must be [H, W], got {mosaic.shape}")
    if np.issubdtype(mosaic.dtype, np.floating):
        mosaic = np.round(black_level + np.clip(mosaic, 0, 1) * (white_level - black_level))
    data = mosaic.astype(np.uint16)
    extratags = [
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, tuple(_CFA_CODES[c] for c in pattern), True),  # CFAPattern
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, f"{make} {model}", True),  # UniqueCameraModel
        (50710, "B", 3, (0, 1, 2), True),  # CFAPlaneColor
        (50711, "H", 1, 1, True),  # CFALayout: rectangular
        (50714, "I", 1, int(black_level), True),  # BlackLevel
        (50717, "I", 1, int(white_level), True),  # WhiteLevel
        (50721, "2i", 9, (10000, 1, 0, 1, 0, 1, 0, 1, 10000, 1, 0, 1, 0, 1, 0, 1, 10000, 1), True),  # ColorMatrix1
        (50728, "2I", 3, (1, 1, 1, 1, 1, 1), True),  # AsShotNeutral
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1: D65
        (271, "s", 0, make, True),  # Make
        (272, "s", 0, model, True),  # Model
    ]
    with atomic_write(path) as temporary:
        tifffile.imwrite(temporary, data, photometric=32803, subfiletype=0, extratags=extratags, metadata=None)
