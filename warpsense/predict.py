"""Segment a real raw capture with a checkpoint trained with a fixed Bayer CFA (`warpsense predict`): the capture read,
put into the model's CFA phase and scale, fed to the network as the model takes a real capture
(`warpsense.system.SensingModel.sense_capture`), and the label map written as a colour-coded image as large as the
capture (over the capture in grey with ``overlay``, with a legend strip)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from warpsense.choices import BAYER_LAYOUTS
from warpsense.files import atomic_write

if TYPE_CHECKING:  # numpy is imported where the work starts: building the parser loads none of it
    import numpy as np


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


def legend_strip(class_names: list[str], present: set[int], num_classes: int, width: int) -> np.ndarray:
    """[h, width, 3] uint8 strip naming the colour of each class present in the prediction; its text scales with the
    image (about 1/60 of its width, at least 11 px) so that it reads on a full-resolution capture."""
    import numpy as np
    from PIL import Image, ImageDraw, ImageFont

    from warpsense.data.labels import colorize

    palette = colorize(np.arange(num_classes)[None], num_classes)[0]
    font_size = max(11, width // 60)
    try:
        font = ImageFont.load_default(size=font_size)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        font = ImageFont.load_default()
    row_height, swatch, gap = font_size + 8, font_size, font_size
    entries = [(index, class_names[index] if index < len(class_names) else f"class {index}")
               for index in sorted(present)]
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


def predict_raw(checkpoint: str, raw_path: str, out_image: str, device: str = "auto", target_width: int = 480,
                overlay: bool = False, legend: bool = True) -> Path:
    """Run the network of ``checkpoint`` on the mosaic of ``raw_path`` and write a colour-coded label image.

    The capture is black/white normalised, phase-matched to the model's Bayer layout by a one-pixel crop, binned
    to about ``target_width`` pixels wide (the scale the network was trained at) and fed to the network as the
    model takes a real capture (`warpsense.system.SensingModel.sense_capture`: its exposure scaled to a share of the
    camera's training level, `warpsense.system.model.CAPTURE_MEAN_SHARE`). The label map is resized (nearest) back
    to the capture's size, so the output is as large as the input.

    Args:
        raw_path: a DNG (or other LibRaw raw file) or a `warpsense convert` .safetensors.
        out_image: the file type follows its suffix (`IMAGE_FORMATS`).
        overlay: blend the colours over the capture (grey) instead of writing colours alone.
        legend: append a strip naming the colour of each class present.
    """
    import numpy as np
    import torch
    from PIL import Image

    from warpsense.data.labels import colorize
    from warpsense.data.raw import prepare_capture, preview_grey, read_capture
    from warpsense.system import load_system, resolve_device

    file_format = image_format(out_image)
    torch_device = resolve_device(device)
    with torch.no_grad():  # inference: no autograd graph through the camera or the network
        model, config, state = load_system(checkpoint, torch_device)
        learned = model.camera.learned()
        model_pattern = learned.cfa_layout or ""
        if model_pattern not in BAYER_LAYOUTS:  # a 2 x 2 R/G/B layout: the only kind a DNG holds
            raise ValueError(f"{checkpoint}: the checkpoint's CFA ({model_pattern or 'none'}) is not a Bayer layout; "
                             f"predict needs one of {', '.join(BAYER_LAYOUTS)}")
        mosaic_np, metadata = read_capture(raw_path)
        if metadata["cfa_pattern"] not in BAYER_LAYOUTS:  # a simulated RCCB or monochrome capture, say
            raise ValueError(f"{raw_path}: the capture's CFA {metadata['cfa_pattern']!r} is not a Bayer layout; "
                             f"predict needs one of {', '.join(BAYER_LAYOUTS)}")
        capture_height, capture_width = mosaic_np.shape
        mosaic, factor, (dy, dx) = prepare_capture(mosaic_np, metadata["cfa_pattern"], model_pattern, target_width)
        if min(mosaic.shape) < 2:  # the phase crop left no whole 2 x 2 tile: the network would get an empty image
            raise ValueError(f"{raw_path}: its {capture_height}x{capture_width} mosaic holds no whole "
                             f"{model_pattern} tile after the {metadata['cfa_pattern']} -> {model_pattern} crop "
                             f"({dy}, {dx})")
        logits = model.network(model.sense_capture(mosaic))
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
