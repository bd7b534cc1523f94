"""Datasets, augmentation, colour conversion and raw-file I/O."""

from __future__ import annotations

from pathlib import Path

from warpsense.data.datasets import KITTI360, CamVid, Cityscapes, DatasetError
from warpsense.data.scenes import StreetScenes
from warpsense.data.transforms import Augmented, paste_class_ids

DATASETS = {"camvid": CamVid, "cityscapes": Cityscapes, "kitti360": KITTI360, "scenes": StreetScenes}


def build_dataset(data_config, split: str, train: bool, seed: int = 0, part: str = "all"):
    """The dataset named by ``data_config.dataset`` for ``split``; training splits are augmented.

    ``part``: "all", or with ``data_config.holdout_prefix`` set, "rest" (the images outside the held-out prefix)
    or "holdout" (those inside it, never augmented: the model-selection set)."""
    name = data_config.dataset
    if name not in DATASETS:
        raise KeyError(f"unknown dataset {name!r}; valid datasets: {', '.join(DATASETS)}")
    if name == "scenes":
        count = data_config.scenes_train if train else data_config.scenes_val
        # validation scenes come from a disjoint stream of the generator
        dataset = StreetScenes(count, data_config.scene_height, data_config.scene_width, seed=seed + (0 if train else 7919))
    else:
        if not data_config.root:
            raise DatasetError(f"data.root is empty: set it to the {name} folder (train: --set data.root=PATH; "
                               f"eval: --data-root PATH)")
        limit = data_config.max_train_images if train else data_config.max_val_images
        dataset = DATASETS[name](data_config.root, split, limit=limit if part == "all" else 0)
    if part != "all":
        if not data_config.holdout_prefix or not hasattr(dataset, "split_by_prefix"):
            raise DatasetError(f"data.holdout_prefix: a held-out part needs a prefix and a file-based dataset, "
                               f"got {data_config.holdout_prefix!r} for {name}")
        rest, held = dataset.split_by_prefix(data_config.holdout_prefix)
        # the limits apply after the split: max_train_images to the rest, max_val_images to the held-out part
        held.pairs = held.pairs[:data_config.max_val_images or None]
        if part == "holdout":
            return held
        dataset = rest
        dataset.pairs = dataset.pairs[:data_config.max_train_images or None]
    if train:
        crop = (data_config.crop_height, data_config.crop_width)
        return Augmented(dataset, crop, (data_config.scale_min, data_config.scale_max), data_config.hflip, seed,
                         data_config.scale_fill, paste_class_ids(data_config.paste_classes, dataset.classes),
                         data_config.paste_probability)
    return dataset


def evaluation_splits(data_config) -> list[str]:
    """The labelled splits a finished run is judged on: the val split, and CamVid's test split where the copy has
    one (``<root>/test.txt``, as the SegNet release does)."""
    splits = [data_config.val_split]
    if data_config.dataset == "camvid" and "test" not in splits and (Path(data_config.root) / "test.txt").is_file():
        splits.append("test")
    return splits


def load_raw(path):
    """Read a converted RAW file: (mosaic float32 [1, H, W], metadata dict). See `warpsense.data.raw`."""
    from warpsense.data.raw import load_raw as _load_raw

    return _load_raw(path)


__all__ = ["Augmented", "CamVid", "Cityscapes", "DATASETS", "DatasetError", "KITTI360", "StreetScenes",
           "build_dataset", "evaluation_splits", "load_raw"]
