"""Datasets, augmentation, colour conversion and raw-file I/O."""

from __future__ import annotations

from warpsense.data.datasets import KITTI360, CamVid, Cityscapes, DatasetError
from warpsense.data.scenes import StreetScenes
from warpsense.data.transforms import Augmented

DATASETS = {"camvid": CamVid, "cityscapes": Cityscapes, "kitti360": KITTI360, "scenes": StreetScenes}


def build_dataset(data_config, split: str, train: bool, seed: int = 0):
    """The dataset named by ``data_config.dataset`` for ``split``; training splits are augmented."""
    name = data_config.dataset
    if name not in DATASETS:
        raise KeyError(f"unknown dataset {name!r}; valid datasets: {', '.join(DATASETS)}")
    if name == "scenes":
        count = data_config.scenes_train if train else data_config.scenes_val
        # validation scenes come from a disjoint stream of the generator
        dataset = StreetScenes(count, data_config.scene_height, data_config.scene_width, seed=seed + (0 if train else 7919))
    else:
        if not data_config.root:
            raise DatasetError(f"data.root is empty: set it to the {name} folder (--set data.root=PATH)")
        limit = data_config.max_train_images if train else data_config.max_val_images
        dataset = DATASETS[name](data_config.root, split, limit=limit)
    if train:
        crop = (data_config.crop_height, data_config.crop_width)
        return Augmented(dataset, crop, (data_config.scale_min, data_config.scale_max), data_config.hflip, seed)
    return dataset


def load_raw(path):
    """Read a converted RAW file: (mosaic float32 [1, H, W], metadata dict). See `warpsense.data.raw`."""
    from warpsense.data.raw import load_raw as _load_raw

    return _load_raw(path)


__all__ = ["Augmented", "CamVid", "Cityscapes", "DATASETS", "DatasetError", "KITTI360", "StreetScenes",
           "build_dataset", "load_raw"]
