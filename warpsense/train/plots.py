"""PNG plots of a run: loss / mIoU curves, learned CFA, PSFs, a grid of predictions, robustness sweeps."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from warpsense.data.labels import colorize  # noqa: E402
from warpsense.train.run_dir import RunDir  # noqa: E402


def epoch_axis(axis, epochs: list[int]) -> None:
    """Whole-epoch ticks on ``axis``'s x axis, and half an epoch of room either side when the run is short (one
    epoch alone would otherwise span 0.96 to 1.04, a few epochs show ticks at 1.5)."""
    axis.xaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))
    if epochs and max(epochs) - min(epochs) < 4:
        axis.set_xlim(min(epochs) - 0.5, max(epochs) + 0.5)


def plot_curves(records: list[dict], path: Path) -> None:
    """Training losses and validation mIoU per epoch, with the warm-up / joint boundary (the camera starts to
    learn there) drawn on both panels. Every value is marked, so that a one-epoch run shows its point."""
    epochs = [r["epoch"] + 1 for r in records]
    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 3.5))
    left.plot(epochs, [r["train_loss"] for r in records], label="total", marker="o", markersize=3)
    for key in ("train_ohem", "train_lovasz", "train_distill"):
        if all(key in r for r in records) and any(r[key] > 0 for r in records):
            left.plot(epochs, [r[key] for r in records], label=key[6:], alpha=0.7, marker="o", markersize=3)
    evaluated = [r for r in records if "val_miou" in r]
    right.plot([r["epoch"] + 1 for r in evaluated], [r["val_miou"] for r in evaluated], marker="o")
    joint = [r["epoch"] + 1 for r in records if r.get("phase") == "joint"]
    if joint and any(r.get("phase") == "warmup" for r in records):
        for axis in (left, right):
            axis.axvline(min(joint) - 0.5, color="0.5", linestyle=":", label="warm-up | joint")
    for axis in (left, right):
        epoch_axis(axis, epochs)
    left.set_xlabel("epoch"), left.set_ylabel("training loss"), left.legend(fontsize=8)
    right.set_xlabel("epoch"), right.set_ylabel("validation mIoU")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def plot_camera(model, path: Path) -> bool:
    """One panel per camera stage that has a picture (`Camera.draw`), in data-path order; whether ``path`` was
    written (not for a camera without such a stage)."""
    count = model.camera.pictures()
    if not count:
        return False
    figure, axes = plt.subplots(1, count, figsize=(4 * count, 4), squeeze=False)
    model.camera.draw(list(axes[0]))
    for axis in axes[0]:
        axis.axis("off")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return True


DESIGN_KEYS = {"f_number": "f-number", "exposure_ms": "exposure time (ms)", "analog_gain": "analog gain",
               "exposure_gain": "exposure gain a(g)"}
"""The scalar camera design values a run records per epoch (`Camera.summary`) that `plot_design` draws."""


def plot_design(records: list[dict], path: Path) -> bool:
    """The learned design over training: one panel per scalar design value that changes (`DESIGN_KEYS`) and the
    CFA layout chosen per epoch (a strip of filter colours, one column per epoch; grey and "?" where a site's
    candidates still tie, as at a uniform start); whether ``path`` was written (not when nothing was learned)."""
    from warpsense.camera.cfa import FILTERS, UNDECIDED_COLOUR

    epochs = [r["epoch"] + 1 for r in records]
    scalars = [key for key in DESIGN_KEYS if all(key in r for r in records)
               and len({round(r[key], 9) for r in records}) > 1]
    # the choice with ties marked; records written before it was recorded have the export (the argmax) only
    layouts = [r.get("cfa_choice", r.get("cfa_layout")) for r in records]
    show_cfa = all(layouts) and len(set(layouts)) > 1
    panels = len(scalars) + show_cfa
    if not panels:
        return False
    figure, axes = plt.subplots(1, panels, figsize=(4 * panels, 3.2), squeeze=False)
    for axis, key in zip(axes[0], scalars):
        axis.plot(epochs, [r[key] for r in records], marker=".")
        axis.ticklabel_format(axis="y", useOffset=False)
        axis.set_xlabel("epoch"), axis.set_ylabel(DESIGN_KEYS[key])
        epoch_axis(axis, epochs)
    if show_cfa:
        axis = axes[0][-1]
        colours = np.array([[FILTERS.get(letter, UNDECIDED_COLOUR) for letter in layout]
                            for layout in layouts])  # [E, sites, 3]
        axis.imshow(colours.transpose(1, 0, 2), aspect="auto", interpolation="nearest",
                    extent=(epochs[0] - 0.5, epochs[-1] + 0.5, colours.shape[1] - 0.5, -0.5))
        axis.set_yticks(range(colours.shape[1]), [f"site {i}" for i in range(colours.shape[1])])
        axis.xaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))
        axis.set_xlabel("epoch"), axis.set_title(f"CFA: {layouts[0]} -> {layouts[-1]}", fontsize=10)
    figure.suptitle("learned camera design over training", fontsize=10)
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
        image, label = dataset[index]  # on the device when the run keeps its evaluation set there
        logits, sensed = model(image[None].to(device))
        image, label = image.cpu(), label.cpu()
        prediction = logits.argmax(dim=1)[0].cpu().numpy()
        sensor = sensed[0].float().cpu().clamp(0, 1).permute(1, 2, 0).numpy().squeeze()
        panels = [image.permute(1, 2, 0).numpy(), sensor, colorize(prediction, num_classes),
                  colorize(label.numpy(), num_classes)]
        titles = (f"input (sRGB), frame {index}", "sensor output", "prediction", "label")
        for axis, panel, title in zip(axes[row], panels, titles):
            axis.imshow(panel, cmap="gray" if panel.ndim == 2 else None)
            axis.set_title(title, fontsize=9)
            axis.axis("off")
    names = getattr(dataset, "classes", None) or [f"class {c}" for c in range(num_classes)]
    palette = colorize(np.arange(num_classes)[None], num_classes)[0] / 255.0
    shown = min(num_classes, len(names))
    # one row for up to 12 classes (CamVid's 11 fit a 12-inch figure), else two balanced rows
    figure.legend(handles=[Patch(color=palette[c], label=names[c]) for c in range(shown)],
                  loc="lower center", ncol=shown if shown <= 12 else -(-shown // 2), fontsize=8, frameon=False)
    figure.tight_layout(rect=(0, 0.6 / (2.6 * len(rows) + 0.6), 1, 1))
    figure.savefig(path, dpi=90)
    plt.close(figure)


def plot_sweep(rows: list[dict], path: str | Path, title: str = "") -> None:
    """mIoU against each swept factor, on one shared mIoU axis so the factors compare at a glance; the
    checkpoint's operating point (rows with ``operating_point``) is starred. ``title`` names what was swept (the
    checkpoint, the split and its image count)."""
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
    if title:
        figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def write_run_plots(run_dir: Path, model, val_set, device) -> None:
    """The run's plots (`RunDir.plot`): its curves and camera design over the epochs, its camera, predictions."""
    run = RunDir(run_dir)
    records = run.read_metrics()
    if records:
        plot_curves(records, run.plot("curves"))
        plot_design(records, run.plot("design"))
    plot_camera(model, run.plot("camera"))
    plot_predictions(model, val_set, device, run.plot("predictions"))
