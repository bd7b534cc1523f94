"""`warpsense predict`: segment a real raw capture with a checkpoint trained with a fixed Bayer CFA."""

from __future__ import annotations

from pathlib import Path

import torch
from torch.nn import functional as F

from warpsense.data.raw import BAYER_PATTERNS, read_raw_file
from warpsense.files import publish


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


@torch.no_grad()
def predict_raw(checkpoint: str, raw_path: str, out_png: str, device: str = "auto", target_width: int = 480) -> Path:
    """Run the network of ``checkpoint`` on the mosaic of ``raw_path`` and write a colour-coded PNG.

    The capture is black/white normalised, phase-matched to the model's Bayer layout by a one-pixel crop, binned
    to about ``target_width`` pixels wide (the scale the network was trained at) and scaled to the exposure the
    model saw in training (its exposure gain times the mean radiance 0.5 of the lens normalisation, when present).
    """
    from PIL import Image

    from warpsense.train.checkpoint import load_system
    from warpsense.train.plots import colorize

    torch_device = torch.device("cuda" if device == "cuda" or (device == "auto" and torch.cuda.is_available()) else "cpu")
    model, config, state = load_system(checkpoint, torch_device)
    cfa = model.camera.cfa
    model_pattern = "".join("".join(row) for row in cfa.hard_letters()) if cfa is not None else ""
    if cfa is None or cfa.tile != 2 or model_pattern not in BAYER_PATTERNS:
        raise ValueError(f"{checkpoint}: the checkpoint's CFA ({model_pattern or 'none'}) is not a Bayer layout; "
                         f"predict needs one of {', '.join(BAYER_PATTERNS)}")
    mosaic_np, metadata = read_raw_file(raw_path)
    dy, dx = phase_offset(metadata["cfa_pattern"], model_pattern)
    mosaic = torch.from_numpy(mosaic_np[dy:, dx:]).clamp(0, 1)
    mosaic = mosaic[: mosaic.shape[0] // 2 * 2, : mosaic.shape[1] // 2 * 2]
    mosaic = bin_mosaic(mosaic, max(1, round(mosaic.shape[1] / target_width)))
    if model.camera.exposure is not None:
        level = float(model.camera.exposure.gain()) * (config.optics.normalize_mean if config.optics.enabled else 0.25)
        mosaic = mosaic * (level * 0.5 / max(float(mosaic.mean()), 1e-6))
    sensed = mosaic.clamp(0, 1)[None, None].to(torch_device)
    if model.isp is not None:
        sensed = model.isp(sensed)
    logits = model.network(sensed)
    prediction = logits.argmax(dim=1)[0].cpu().numpy()
    out = Path(out_png)
    tmp = out.with_name(out.stem + ".tmp.png")
    Image.fromarray(colorize(prediction, logits.shape[1])).save(tmp, format="PNG")
    publish(tmp, out)
    print(f"wrote {out} ({prediction.shape[1]}x{prediction.shape[0]}, {metadata['cfa_pattern']} -> {model_pattern} "
          f"crop ({dy}, {dx}))")
    return out
