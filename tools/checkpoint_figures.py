"""The camera and prediction figures of docs/results.md (docs/img/<name>_camera.png, <name>_predictions.png),
redrawn from checkpoints, so the pictures always show the checkpoints the repository ships.

    python tools/checkpoint_figures.py CHECKPOINT [CHECKPOINT ...] [--data-root DIR] [--out-dir docs/img]
        [--count 4] [--device cpu]

Each checkpoint is loaded as `warpsense eval` loads it; its config names the dataset and validation split
(``--data-root`` replaces the config's data.root, which is relative to the repository root in the presets). The
figures are `warpsense.train.plots.plot_camera` (one panel per camera stage with a picture) and `plot_predictions`
(``--count`` validation frames spread over the split). A checkpoint that cannot be read or drawn is reported on
stderr and the others go on; the exit status is 1 if any failed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch


def draw(checkpoint: Path, out_dir: Path, data_root: str | None, count: int, device: str) -> list[Path]:
    """Write ``<stem>_camera.png`` (when the camera has a picture) and ``<stem>_predictions.png``; the paths."""
    from warpsense.data import build_dataset
    from warpsense.system import load_system
    from warpsense.train.plots import plot_camera, plot_predictions

    model, config, _ = load_system(checkpoint, torch.device(device))
    if data_root:
        config.data.root = data_root
    val_set = build_dataset(config.data, config.data.val_split, train=False, seed=config.run.seed)
    stem = checkpoint.name.removesuffix(".safetensors")
    camera_path, predictions_path = out_dir / f"{stem}_camera.png", out_dir / f"{stem}_predictions.png"
    written = [camera_path] if plot_camera(model, camera_path) else []
    plot_predictions(model, val_set, torch.device(device), predictions_path, count=count)
    return written + [predictions_path]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+", type=Path, metavar="CHECKPOINT")
    parser.add_argument("--data-root", help="dataset folder (default: each checkpoint's data.root)")
    parser.add_argument("--out-dir", type=Path, default=Path("docs/img"))
    parser.add_argument("--count", type=int, default=4, help="validation frames in the predictions figure")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    args = parser.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    failed = 0
    for checkpoint in args.checkpoints:
        try:
            for path in draw(checkpoint, args.out_dir, args.data_root, args.count, args.device):
                print(path)
        except (OSError, ValueError, KeyError) as error:
            print(f"{checkpoint}: {error}", file=sys.stderr)
            failed += 1
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
