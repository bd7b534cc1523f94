"""PNG plots of a run: loss / mIoU curves, learned CFA, PSFs, a grid of predictions, robustness sweeps."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from warpsense.data.labels import CAMVID_COLORS, CITYSCAPES_COLORS  # noqa: E402


def colorize(label: np.ndarray, num_classes: int) -> np.ndarray:
    """[H, W] class indices -> [H, W, 3] uint8 colours (CamVid palette for 11 classes, Cityscapes for 19)."""
    palette = np.array(CAMVID_COLORS if num_classes <= len(CAMVID_COLORS) else CITYSCAPES_COLORS, dtype=np.uint8)
    out = np.zeros((*label.shape, 3), dtype=np.uint8)
    valid = label < len(palette)
    out[valid] = palette[label[valid]]
    return out


def plot_curves(records: list[dict], path: Path) -> None:
    """Training losses and validation mIoU per epoch, with the warm-up / joint boundary (the camera starts to
    learn there) drawn on both panels."""
    epochs = [r["epoch"] + 1 for r in records]
    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 3.5))
    left.plot(epochs, [r["train_loss"] for r in records], label="total")
    for key in ("train_ohem", "train_lovasz"):
        if all(key in r for r in records):
            left.plot(epochs, [r[key] for r in records], label=key[6:], alpha=0.7)
    evaluated = [r for r in records if "val_miou" in r]
    right.plot([r["epoch"] + 1 for r in evaluated], [r["val_miou"] for r in evaluated], marker="o")
    joint = [r["epoch"] + 1 for r in records if r.get("phase") == "joint"]
    if joint and any(r.get("phase") == "warmup" for r in records):
        for axis in (left, right):
            axis.axvline(min(joint) - 0.5, color="0.5", linestyle=":", label="warm-up | joint")
    left.set_xlabel("epoch"), left.set_ylabel("training loss"), left.legend(fontsize=8)
    right.set_xlabel("epoch"), right.set_ylabel("validation mIoU")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def _draw_cfa(axis, cfa) -> None:
    phi = cfa.phi().detach().cpu().numpy()
    axis.imshow(np.clip(phi / max(phi.max(), 1e-6), 0, 1), interpolation="nearest")
    for y, row in enumerate(cfa.hard_letters()):
        for x, letter in enumerate(row):
            axis.text(x, y, letter, ha="center", va="center", color="white", fontsize=14)
    axis.set_title("learned CFA (phi, export letters)")


def display_half_width(psf: np.ndarray, level: float = 1e-2) -> int:
    """Half width of the central window shown for a PSF grid [..., K, K] (each PSF scaled to peak 1): one pixel
    beyond the farthest pixel above ``level`` in any PSF, at most K // 2. Without it the tails of a large K shrink
    the cores to dots."""
    centre = psf.shape[-1] // 2
    visible = np.argwhere(psf.reshape(-1, *psf.shape[-2:]).max(axis=0) > level)
    if not len(visible):
        return centre
    return min(int(np.abs(visible - centre).max()) + 1, centre)


def _draw_psf_grid(axis, optics) -> None:
    psf = optics.psf().detach().cpu().numpy()[1]  # green channel [Gy, Gx, K, K]
    psf = psf / np.maximum(psf.max(axis=(2, 3), keepdims=True), 1e-12)
    kernel_size, centre = psf.shape[-1], psf.shape[-1] // 2
    half = display_half_width(psf)
    psf = psf[..., centre - half : centre + half + 1, centre - half : centre + half + 1]
    grid_y, grid_x, size, _ = psf.shape
    mosaic = np.zeros((grid_y * (size + 1), grid_x * (size + 1)))
    for i in range(grid_y):
        for j in range(grid_x):
            mosaic[i * (size + 1) : i * (size + 1) + size, j * (size + 1) : j * (size + 1) + size] = \
                psf[i, j]
    axis.imshow(mosaic ** 0.5, cmap="magma")
    axis.set_title(f"PSF grid (green, sqrt, per-PSF max; central {size} of K = {kernel_size})", fontsize=10)


CAMERA_PANELS = {"optics": _draw_psf_grid, "cfa": _draw_cfa}
"""Stages with a picture (`Camera.stages` names) -> a function drawing the stage on a matplotlib axis."""


def plot_camera(model, path: Path) -> bool:
    """One panel per camera stage that has a picture (`CAMERA_PANELS`), in data-path order; whether ``path`` was
    written (not for a camera without such a stage)."""
    panels = [(CAMERA_PANELS[name], stage) for name, stage in model.camera.stages() if name in CAMERA_PANELS]
    if not panels:
        return False
    figure, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 4), squeeze=False)
    for axis, (draw, stage) in zip(axes[0], panels):
        draw(axis, stage)
        axis.axis("off")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return True


def spread_indices(length: int, count: int) -> list[int]:
    """``count`` indices spread evenly over ``range(length)`` (first and last included): frames from across a
    dataset rather than neighbours of one sequence."""
    count = min(count, length)
    return sorted({round(i * (length - 1) / max(count - 1, 1)) for i in range(count)})


@torch.no_grad()
def plot_predictions(model, dataset, device, path: Path, count: int = 4) -> None:
    """Input, sensor output, prediction and label for ``count`` frames spread over the dataset, with a legend of
    the class colours."""
    from matplotlib.patches import Patch

    model.eval()
    rows = spread_indices(len(dataset), count)
    figure, axes = plt.subplots(len(rows), 4, figsize=(12, 2.6 * len(rows) + 0.6), squeeze=False)
    num_classes = model.network.head.out_channels
    for row, index in enumerate(rows):
        image, label = dataset[index]
        logits, sensed = model(image[None].to(device))
        prediction = logits.argmax(dim=1)[0].cpu().numpy()
        panels = [image.permute(1, 2, 0).numpy(), sensed[0].float().cpu().clamp(0, 1).permute(1, 2, 0).numpy().squeeze(),
                  colorize(prediction, num_classes), colorize(label.numpy(), num_classes)]
        titles = (f"input (sRGB), frame {index}", "sensor output", "prediction", "label")
        for axis, panel, title in zip(axes[row], panels, titles):
            axis.imshow(panel, cmap="gray" if panel.ndim == 2 else None)
            axis.set_title(title, fontsize=9)
            axis.axis("off")
    names = getattr(dataset, "classes", None) or [f"class {c}" for c in range(num_classes)]
    palette = colorize(np.arange(num_classes)[None], num_classes)[0] / 255.0
    figure.legend(handles=[Patch(color=palette[c], label=names[c]) for c in range(min(num_classes, len(names)))],
                  loc="lower center", ncol=min(num_classes, 10), fontsize=8, frameon=False)
    figure.tight_layout(rect=(0, 0.6 / (2.6 * len(rows) + 0.6), 1, 1))
    figure.savefig(path, dpi=90)
    plt.close(figure)


def plot_sweep(rows: list[dict], path: str | Path) -> None:
    """mIoU against each swept factor, on one shared mIoU axis so the factors compare at a glance; the
    checkpoint's operating point (rows with ``operating_point``) is starred."""
    factors = list(dict.fromkeys(r["factor"] for r in rows))
    figure, axes = plt.subplots(1, len(factors), figsize=(4 * len(factors), 3.2), squeeze=False, sharey=True)
    for axis, factor in zip(axes[0], factors):
        subset = [r for r in rows if r["factor"] == factor]
        axis.plot([r["value"] for r in subset], [r["miou"] for r in subset], marker="o")
        marked = [r for r in subset if r.get("operating_point")]
        if marked:
            axis.scatter([r["value"] for r in marked], [r["miou"] for r in marked], marker="*", s=180, color="C3",
                         zorder=3, label="operating point")
            axis.legend(fontsize=8)
        axis.set_xlabel(factor)
    axes[0][0].set_ylabel("mIoU")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def write_run_plots(run_dir: Path, model, val_set, device) -> None:
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]
    if records:
        plot_curves(records, run_dir / "curves.png")
    plot_camera(model, run_dir / "camera.png")
    plot_predictions(model, val_set, device, run_dir / "predictions.png")
