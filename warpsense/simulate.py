"""Your own images through a camera: sRGB (or linear) images -> the configured or checkpointed camera -> RAW.

Per image ``<stem>`` the output folder receives:

- ``<stem>.safetensors``: the RAW mosaic in `warpsense.data.raw`'s format (tensor ``mosaic`` [1, H, W] float32 in
  units of the white level, metadata ``warpsense`` with ``cfa_pattern`` etc.), which `warpsense predict` reads;
- ``<stem>.dng``: the mosaic as integer codes (0 .. 2^bits - 1, black level 0) in a minimal CFA DNG that
  rawpy/LibRaw read, where the camera's CFA is a 2 x 2 Bayer layout of R, G and B (a DNG CFA pattern holds no
  other filters: a learned RCCB layout, a 4 x 4 tile or a monochrome sensor get no DNG, with a note);
- ``<stem>.preview.png``: an 8-bit sRGB preview of the mosaic (each 2 x 2 Bayer tile's R, mean G, B; otherwise each
  tile's mean in grey).

The camera runs in eval mode: its noise is drawn from the fixed eval seed plus ``seed`` plus a key of the file name,
so the same image and seed give the same RAW, and two images do not share one noise pattern. A file that cannot be
read or simulated is reported in one line and the batch goes on; each image's files are written under temporary
names and renamed together, so a failure leaves none of them.
"""

from __future__ import annotations

import itertools
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from warpsense.choices import BAYER_LAYOUTS, IMAGE_SUFFIXES
from warpsense.errors import first_line

LINEAR_SUFFIXES = {".tif", ".tiff", ".png"}
DNG_BITS_WITHOUT_QUANTIZER = 16
"""Bit depth of the DNG codes when the camera has no ADC stage (its RAW is continuous)."""
LIBRAW_MIN_SIDE = 22
"""LibRaw refuses a raw image narrower or shorter than this ("Unsupported file format"): no DNG below it."""


class SimulateError(ValueError):
    """One input cannot be simulated; the message names the file and the reason."""


@dataclass
class SimulatedCamera:
    """A camera ready to simulate: the module in eval mode and what the outputs need to describe it."""

    camera: torch.nn.Module
    source: str

    @property
    def device(self) -> torch.device:
        """Where the camera runs (its parameters' and buffers' device; the CPU for a camera without any)."""
        tensor = next(itertools.chain(self.camera.parameters(), self.camera.buffers()), None)
        return tensor.device if tensor is not None else torch.device("cpu")

    @property
    def letters(self) -> str | None:
        """The exported CFA letters row by row ("RGGB"), None for a monochrome sensor."""
        layout = self.camera.layout_letters()
        return "".join("".join(row) for row in layout) if layout is not None else None

    @property
    def bits(self) -> int:
        """The ADC's bit depth (`DNG_BITS_WITHOUT_QUANTIZER` without one), from the fused kernel's arguments."""
        bits = self.camera.sensor_arguments()[0].bits
        return int(bits) if bits else DNG_BITS_WITHOUT_QUANTIZER

    @property
    def white_level(self) -> float:
        white = self.camera.sensor_arguments()[0].white_level
        return float(white) if white else 1.0

    def dng_note(self) -> str | None:
        """Why this camera's RAW cannot be a DNG (None when it can)."""
        letters = self.letters
        if letters is None:
            return "a monochrome sensor (no CFA) is not a CFA DNG"
        if letters not in BAYER_LAYOUTS:
            return (f"the CFA {letters} (tile {self.camera.tile}) is not a 2 x 2 R/G/B Bayer layout, the only kind a "
                    f"DNG CFA pattern holds here ({', '.join(BAYER_LAYOUTS)})")
        return None


def load_camera(config: str | None = None, overrides: list[str] | tuple[str, ...] = (),
                checkpoint: str | None = None, device: str | None = None) -> SimulatedCamera:
    """The camera of a config (file or preset, with ``section.key=value`` overrides) or of a checkpoint, in eval
    mode on ``device``; exactly one of ``config`` and ``checkpoint``.

    Args:
        device: "auto", "cpu" or "cuda" (`warpsense.system.resolve_device`: cuda where torch has none is a one-line
            ValueError, as in train, eval and predict); None: the config's run.device, "auto" for a checkpoint (as
            eval and predict)."""
    from warpsense.camera import Camera
    from warpsense.config import load_config
    from warpsense.system import load_system, resolve_device
    from warpsense.system.build import check_config

    if (config is None) == (checkpoint is None):
        raise ValueError("give either --config (with --set) or --checkpoint")
    if checkpoint is not None:
        if overrides:
            raise ValueError("--set changes a config: with --checkpoint the camera is the checkpoint's")
        model, _, _ = load_system(checkpoint, resolve_device(device or "auto"))
        return SimulatedCamera(model.camera.eval(), str(checkpoint))
    resolved = load_config(config, overrides)
    check_config(resolved, f"config {config}")
    # the config's run.device, resolved: "cuda" without CUDA is refused rather than run on the CPU
    torch_device = resolve_device(device or resolved.run.device)
    return SimulatedCamera(Camera.from_config(resolved).eval().to(torch_device), str(config))


def read_image(path: str | Path, linear: bool = False) -> torch.Tensor:
    """Linear radiance [1, 3, H, W] float32 of an image file.

    sRGB (default): an 8-bit PNG/JPEG/BMP/WebP, decoded with the sRGB curve. ``linear``: a TIFF (or PNG) of linear
    values: 16-bit integers divided by 65535, 8-bit by 255, floats taken as they are (>= 0, finite). Grey images are
    repeated into three channels; an alpha channel is dropped."""
    from PIL import Image

    from warpsense.data.color import srgb_to_linear

    path = Path(path)
    if path.is_dir():
        raise SimulateError(f"{path}: is a directory, not an image")
    suffix = path.suffix.lower()
    allowed = LINEAR_SUFFIXES if linear else IMAGE_SUFFIXES
    if suffix not in allowed:
        hint = " (a linear TIFF needs --linear)" if suffix in {".tif", ".tiff"} else \
            " (a raw capture goes to `warpsense convert` / `predict`)" if suffix in {".dng", ".nef", ".cr2", ".arw"} \
            else ""
        raise SimulateError(f"{path}: not a supported {'linear ' if linear else 'sRGB '}image type "
                            f"({', '.join(sorted(allowed))}){hint}")
    if not path.is_file():
        raise SimulateError(f"{path}: no such file")
    try:
        if suffix in {".tif", ".tiff"}:
            import tifffile

            array = np.asarray(tifffile.imread(path))
        else:
            with Image.open(path) as image:
                image.load()
                if image.mode not in ("L", "RGB", "RGBA", "I;16", "I"):
                    image = image.convert("RGB")
                array = np.array(image)
    except Exception as error:  # noqa: BLE001 (the decoders raise many types: zlib.error for a cut deflate TIFF)
        raise SimulateError(f"{path}: cannot read it as an image ({type(error).__name__}: {first_line(error)})") \
            from None
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=2)
    if array.ndim != 3 or array.shape[2] < 3:
        raise SimulateError(f"{path}: expected an H x W x 3 (or grey) image, got shape {array.shape}")
    array = array[..., :3]
    if array.shape[0] < 2 or array.shape[1] < 2:
        raise SimulateError(f"{path}: image of {array.shape[0]}x{array.shape[1]} pixels is too small")
    if not linear:
        if array.dtype != np.uint8:
            raise SimulateError(f"{path}: an sRGB image must be 8-bit, got {array.dtype} (a linear one: --linear)")
        return srgb_to_linear(torch.from_numpy(np.ascontiguousarray(array)).permute(2, 0, 1)[None])
    if array.dtype == np.uint16:
        values = array.astype(np.float32) / 65535
    elif array.dtype == np.uint8:
        values = array.astype(np.float32) / 255
    elif np.issubdtype(array.dtype, np.floating):
        values = array.astype(np.float32)
        if not np.isfinite(values).all() or (values < 0).any():
            raise SimulateError(f"{path}: a linear float image must be finite and >= 0")
    else:
        raise SimulateError(f"{path}: unsupported linear sample type {array.dtype} (uint8, uint16 or float)")
    return torch.from_numpy(np.ascontiguousarray(values)).permute(2, 0, 1)[None]


def noise_key(path: str | Path, seed: int) -> int:
    """The image index the camera's eval noise is keyed by: ``seed`` plus a hash of the file name (stable across
    runs and batches, different between images)."""
    return (int(seed) + zlib.crc32(Path(path).name.encode()) % (1 << 20)) % (2**31 - 1)


@torch.no_grad()
def simulate_image(sim: SimulatedCamera, radiance: torch.Tensor, key: int = 0) -> np.ndarray:
    """The normalised RAW mosaic [H', W'] float32 (units of the white level; ADC units before a photon budget's
    digital gain, as a real capture's file holds them) of radiance [1, 3, H, W]; the image is cropped to a multiple
    of the CFA tile (top-left kept) so that the mosaic's layout is the camera's."""
    from warpsense.ops.arguments import check_tensor

    # checked here: the camera saw a batch of 2 as an image_index of the wrong length (the one key is this
    # function's), and an image under one tile as the empty crop it had become, (1, 3, 0, 0)
    check_tensor("simulate_image", "radiance", radiance, 4, "[1, 3, H, W] tensor")
    tile = sim.camera.tile
    if radiance.shape[:2] != (1, 3) or min(radiance.shape[-2:]) < tile:
        raise ValueError(f"simulate_image: radiance must be one image [1, 3, H, W] of at least the CFA tile "
                         f"({tile} x {tile} pixels), got {tuple(radiance.shape)}")
    height, width = radiance.shape[-2] // tile * tile, radiance.shape[-1] // tile * tile
    radiance = radiance[..., :height, :width]
    device = sim.device
    raw = sim.camera(radiance.float().to(device), torch.tensor([key], device=device))
    digital_gain = sim.camera.learned().digital_gain
    if digital_gain is not None:
        raw = raw / digital_gain
    return (raw[0, 0] / sim.white_level).float().cpu().numpy()


def preview(mosaic: np.ndarray, letters: str | None) -> np.ndarray:
    """[H, W, 3] uint8 sRGB preview: a Bayer mosaic's 2 x 2 tiles as (R, mean G, B) on their four pixels, any other
    mosaic as each tile's mean in grey (`warpsense.data.raw.preview_grey`)."""
    from warpsense.data.color import linear_to_srgb
    from warpsense.data.raw import preview_grey

    height, width = mosaic.shape
    if letters in BAYER_LAYOUTS:
        sites = {(y, x): mosaic[y::2, x::2] for y in (0, 1) for x in (0, 1)}
        planes = {letter: [sites[divmod(i, 2)] for i, c in enumerate(letters) if c == letter] for letter in "RGB"}
        rgb = np.stack([sum(planes[c]) / len(planes[c]) for c in "RGB"], axis=-1)
        rgb = np.repeat(np.repeat(rgb, 2, axis=0), 2, axis=1)[:height, :width]
    else:
        rgb = np.repeat(preview_grey(mosaic)[..., None], 3, axis=2)
    srgb = linear_to_srgb(torch.from_numpy(np.clip(rgb, 0, 1).astype(np.float32))).numpy()
    return np.round(srgb * 255).astype(np.uint8)


def mosaic_metadata(sim: SimulatedCamera, mosaic: np.ndarray, path: Path) -> dict:
    """The ``warpsense`` metadata entry `warpsense.data.raw.load_raw` returns, for a simulated capture."""
    import hashlib

    letters = sim.letters or "mono"
    white = float((1 << sim.bits) - 1)
    learned = sim.camera.learned()
    return {
        "cfa_pattern": letters, "tile": sim.camera.tile, "color_desc": "RGBG", "black_levels": [0.0] * 4,
        "white_level": white, "bit_depth": sim.bits, "as_shot_white_balance": [1.0, 1.0, 1.0, 1.0],
        "make": "warpsense", "model": "simulated", "height": int(mosaic.shape[0]), "width": int(mosaic.shape[1]),
        "source": path.name, "source_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "simulated": {"camera": sim.source, "cfa_responses": learned.cfa_responses,
                      "exposure_gain": learned.exposure_gain, "noise_shot": learned.noise_shot,
                      "noise_read": learned.noise_read, "digital_gain": learned.digital_gain},
    }


def write_outputs(sim: SimulatedCamera, mosaic: np.ndarray, source: Path, out_dir: Path) -> list[Path]:
    """Write ``<stem>.safetensors``, ``<stem>.dng`` (when `SimulatedCamera.dng_note` is None) and
    ``<stem>.preview.png`` into ``out_dir``: every file under a temporary name first, then all renamed; on any error
    the temporaries are removed and no output of this image is left."""
    import json

    from PIL import Image
    from safetensors.torch import save_file

    from warpsense.data.raw import write_dng
    from warpsense.files import publish

    stem = source.stem
    targets = {"raw": out_dir / f"{stem}.safetensors", "preview": out_dir / f"{stem}.preview.png"}
    if sim.dng_note() is None and min(mosaic.shape) >= LIBRAW_MIN_SIDE:
        targets["dng"] = out_dir / f"{stem}.dng"
    temporaries = {kind: target.with_name(f"{target.name}.tmp") for kind, target in targets.items()}
    if "dng" in targets:  # write_dng publishes through a temporary of its own onto this one
        temporaries["dng"] = out_dir / f"{stem}.dng.tmp.dng"
    try:
        save_file({"mosaic": torch.from_numpy(np.ascontiguousarray(mosaic))[None].contiguous()},
                  str(temporaries["raw"]), metadata={"warpsense": json.dumps(mosaic_metadata(sim, mosaic, source))})
        Image.fromarray(preview(mosaic, sim.letters)).save(temporaries["preview"], format="PNG")
        if "dng" in targets:
            write_dng(temporaries["dng"], np.clip(mosaic, 0, 1), sim.letters, black_level=0,
                      white_level=(1 << sim.bits) - 1)
        for kind in ("preview", "dng", "raw"):  # the RAW last: it is what marks the image done
            if kind in targets:
                publish(temporaries[kind], targets[kind])
    finally:
        for temporary in temporaries.values():
            temporary.unlink(missing_ok=True)
    return list(targets.values())


def simulate_files(inputs: list[str], out_dir: str | Path, sim: SimulatedCamera, linear: bool = False,
                   seed: int = 0) -> list[tuple[str, str]]:
    """Simulate every input into ``out_dir``; a failing file is reported on stderr in one line and the batch goes
    on. Returns the failures [(input, reason)]."""
    out_dir = Path(out_dir)
    created = not out_dir.exists()  # made at the first output, and removed again if nothing was written into it
    note = sim.dng_note()
    if note:
        print(f"warpsense simulate: no DNG: {note}; writing the .safetensors RAW and the preview only",
              file=sys.stderr)
    failures, written, stems = [], 0, {}
    for item in inputs:
        path = Path(item)
        try:
            if path.stem in stems:
                raise SimulateError(f"{path}: its outputs {path.stem}.* would overwrite those of {stems[path.stem]}")
            radiance = read_image(path, linear)
            mosaic = simulate_image(sim, radiance, noise_key(path, seed))
            out_dir.mkdir(parents=True, exist_ok=True)
            written_files = write_outputs(sim, mosaic, path, out_dir)
            if mosaic.shape != tuple(radiance.shape[-2:]):  # said, as predict says its crop: the outputs are smaller
                print(f"warpsense simulate: {path}: cropped {radiance.shape[-2]}x{radiance.shape[-1]} to "
                      f"{mosaic.shape[0]}x{mosaic.shape[1]} (HxW, top-left kept): whole {sim.camera.tile} x "
                      f"{sim.camera.tile} CFA tiles", file=sys.stderr)
            if not note and not any(file.suffix == ".dng" for file in written_files):
                print(f"warpsense simulate: {path}: no DNG: its {mosaic.shape[0]}x{mosaic.shape[1]} mosaic is under "
                      f"the {LIBRAW_MIN_SIDE} pixels a side LibRaw reads", file=sys.stderr)
            stems[path.stem] = path
            written += 1
        except (SimulateError, ValueError, OSError) as error:
            reason = str(error) if isinstance(error, SimulateError) else f"{path}: {error}"
            failures.append((item, reason))
            print(f"warpsense simulate: skipped {reason}", file=sys.stderr)
    if created and not written and out_dir.is_dir() and not any(out_dir.iterdir()):
        out_dir.rmdir()
    failed = f"; {len(failures)} failed" if failures else ""
    print(f"simulated {written} of {len(inputs)} image(s) into {out_dir}{failed}")
    return failures
