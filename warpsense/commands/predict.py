"""`warpsense predict`: segment a real raw capture with a checkpoint trained with a fixed Bayer CFA."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from warpsense.choices import BAYER_LAYOUTS
from warpsense.data.raw import load_raw, read_raw_file
from warpsense.files import atomic_write
from warpsense.system import resolve_device


def phase_offset(file_pattern: str, model_pattern: str) -> tuple[int, int]:
    """(dy, dx) crop that turns the file's 2x2 layout into the model's (e.g. GBRG -> RGGB is (1, 0))."""
    grid = [file_pattern[:2], file_pattern[2:]]
    for dy in (0, 1):
        for dx in (0, 1):
            shifted = "".join(grid[(dy + y) % 2][(dx + x) % 2] for y in (0, 1) for x in (0, 1))
            if shifted == model_pattern:
                return dy, dx
    raise ValueError(f"layout {file_pattern} cannot be cropped into {model_pattern}")


def bin_mosaic(mosaic: torch.Tensor, factor: int) -> torch.Tensor:
    """Downscale a 2x2 Bayer mosaic [H, W] by ``factor`` keeping its layout: each of the 4 site planes is
    average-pooled, then re-interleaved."""
    if factor <= 1:
        return mosaic
    planes = F.pixel_unshuffle(mosaic[None, None], 2)
    planes = F.avg_pool2d(planes, factor)
    return F.pixel_shuffle(planes, 2)[0, 0]


# Pillow format of each output suffix; the image format follows the file name the user gives
IMAGE_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF", ".bmp": "BMP",
                 ".webp": "WEBP"}
OVERLAY_ALPHA = 0.5  # colour share of the overlay; the rest is the capture in grey


def image_format(path: str | Path) -> str:
    """Pillow format for an output path; ValueError listing the supported suffixes otherwise."""
    suffix = Path(path).suffix.lower()
    if suffix not in IMAGE_FORMATS:
        raise ValueError(f"--out {path}: unsupported image type {suffix or '(none)'}; use one of "
                         f"{', '.join(sorted(IMAGE_FORMATS))}")
    return IMAGE_FORMATS[suffix]


def read_capture(path: str | Path) -> tuple[np.ndarray, dict]:
    """Normalised mosaic float32 [H, W] and metadata (``cfa_pattern`` ...) of a raw file (DNG and what LibRaw
    reads) or of `warpsense convert`'s output (.safetensors)."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if Path(path).suffix.lower() == ".safetensors":
        mosaic, metadata = load_raw(path)
        return mosaic[0].numpy(), metadata
    return read_raw_file(path)


def legend_strip(class_names: list[str], present: set[int], num_classes: int, width: int) -> np.ndarray:
    """[h, width, 3] uint8 strip naming the colour of each class present in the prediction; its text scales with the
    image (about 1/60 of its width, at least 11 px) so that it reads on a full-resolution capture."""
    from PIL import Image, ImageDraw, ImageFont

    from warpsense.data.labels import colorize

    palette = colorize(np.arange(num_classes)[None], num_classes)[0]
    font_size = max(11, width // 60)
    try:
        font = ImageFont.load_default(size=font_size)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        font = ImageFont.load_default()
    row_height, swatch, gap = font_size + 8, font_size, font_size
    entries = [(index, class_names[index] if index < len(class_names) else f"class {index}") for index in sorted(present)]
    strip = Image.new("RGB", (width, row_height), "white")
    draw = ImageDraw.Draw(strip)
    rows, x = [strip], 4
    for index, name in entries:
        needed = swatch + 4 + int(draw.textlength(name, font=font)) + gap
        if x + needed > width and x > 4:  # wrap onto a new row
            strip = Image.new("RGB", (width, row_height), "white")
            draw, x = ImageDraw.Draw(strip), 4
            rows.append(strip)
        draw.rectangle([x, 4, x + swatch, 4 + swatch], fill=tuple(int(v) for v in palette[index]), outline="black")
        draw.text((x + swatch + 4, 3), name, fill="black", font=font)
        x += needed
    return np.concatenate([np.asarray(row) for row in rows], axis=0)


def preview_grey(mosaic: np.ndarray) -> np.ndarray:
    """[H, W] grey preview of a CFA mosaic without its checkerboard: each 2 x 2 tile's mean (every filter of the
    tile once), on the tile's four pixels."""
    height, width = mosaic.shape
    even = np.pad(mosaic, ((0, height % 2), (0, width % 2)), mode="edge")
    tiles = (even[0::2, 0::2] + even[0::2, 1::2] + even[1::2, 0::2] + even[1::2, 1::2]) / 4
    return np.repeat(np.repeat(tiles, 2, axis=0), 2, axis=1)[:height, :width]


@torch.no_grad()
def predict_raw(checkpoint: str, raw_path: str, out_image: str, device: str = "auto", target_width: int = 480,
                overlay: bool = False, legend: bool = True) -> Path:
    """Run the network of ``checkpoint`` on the mosaic of ``raw_path`` and write a colour-coded label image.

    The capture is black/white normalised, phase-matched to the model's Bayer layout by a one-pixel crop, binned
    to about ``target_width`` pixels wide (the scale the network was trained at) and scaled to the exposure the
    model saw in training (its exposure gain times the mean radiance 0.5 of the lens normalisation, when present).
    The label map is resized (nearest) back to the capture's size, so the output is as large as the input.

    Args:
        raw_path: a DNG (or other LibRaw raw file) or a `warpsense convert` .safetensors.
        out_image: the file type follows its suffix (`IMAGE_FORMATS`).
        overlay: blend the colours over the capture (grey) instead of writing colours alone.
        legend: append a strip naming the colour of each class present.
    """
    from PIL import Image

    from warpsense.data.labels import colorize
    from warpsense.system import load_system

    file_format = image_format(out_image)
    torch_device = resolve_device(device)
    model, config, state = load_system(checkpoint, torch_device)
    learned = model.camera.learned()
    model_pattern = learned.cfa_layout or ""
    if model_pattern not in BAYER_LAYOUTS:  # a 2 x 2 R/G/B layout: the only kind a DNG holds
        raise ValueError(f"{checkpoint}: the checkpoint's CFA ({model_pattern or 'none'}) is not a Bayer layout; "
                         f"predict needs one of {', '.join(BAYER_LAYOUTS)}")
    mosaic_np, metadata = read_capture(raw_path)
    capture_height, capture_width = mosaic_np.shape
    dy, dx = phase_offset(metadata["cfa_pattern"], model_pattern)
    mosaic = torch.from_numpy(np.ascontiguousarray(mosaic_np[dy:, dx:])).clamp(0, 1)
    mosaic = mosaic[: mosaic.shape[0] // 2 * 2, : mosaic.shape[1] // 2 * 2]
    factor = max(1, round(mosaic.shape[1] / target_width))
    mosaic = bin_mosaic(mosaic, factor)
    if learned.exposure_gain is not None:
        mosaic = mosaic * (model.camera.raw_mean() * 0.5 / max(float(mosaic.mean()), 1e-6))
    mosaic = mosaic.clamp(0, 1)
    if learned.digital_gain is not None:  # a photon budget: the capture is in ADC units, as the camera's ADC gives
        mosaic = mosaic * learned.digital_gain
    sensed = mosaic[None, None].to(torch_device)
    if model.isp is not None:
        sensed = model.isp(sensed)
    logits = model.network(sensed)
    num_classes = logits.shape[1]
    prediction = logits.argmax(dim=1)[0].cpu().numpy().astype(np.uint8)
    labels = np.asarray(Image.fromarray(prediction).resize((capture_width, capture_height), Image.NEAREST))
    picture = colorize(labels, num_classes)
    if overlay:
        preview = preview_grey(mosaic_np)
        grey = np.clip(preview / max(float(np.percentile(preview, 99)), 1e-6), 0, 1) ** (1 / 2.2) * 255
        picture = (OVERLAY_ALPHA * picture + (1 - OVERLAY_ALPHA) * grey[..., None]).astype(np.uint8)
    if legend:
        names = list(state.get("class_names") or [])
        picture = np.concatenate([picture, legend_strip(names, set(np.unique(labels).tolist()), num_classes,
                                                        capture_width)], axis=0)
    out = Path(out_image)
    with atomic_write(out) as temporary:
        Image.fromarray(picture).save(temporary, format=file_format)
    # sizes height x width, as --latency-size and every other size warpsense reads or prints
    print(f"wrote {out} ({capture_height}x{capture_width} HxW; the network ran at {prediction.shape[0]}x"
          f"{prediction.shape[1]}, 1/{factor} of the capture after the {metadata['cfa_pattern']} -> {model_pattern} "
          f"crop ({dy}, {dx}){'; legend strip below' if legend else ''})")
    return out
