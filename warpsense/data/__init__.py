"""Datasets, augmentation, colour conversion and raw-file I/O."""

from __future__ import annotations

from pathlib import Path

from warpsense.choices import SCENE_SPLITS
from warpsense.data.datasets import (
    KITTI360,
    CamVid,
    Cityscapes,
    DatasetError,
    Frames,
    block_fold,
    frame_numbers,
    frame_sequences,
    sequence_fold,
)
from warpsense.data.folder import FolderDataset
from warpsense.data.scenes import StreetScenes
from warpsense.data.transforms import Augmented, paste_class_ids

DATASETS = {"camvid": CamVid, "cityscapes": Cityscapes, "kitti360": KITTI360, "scenes": StreetScenes,
            "folder": FolderDataset}


HELDOUT_SPLIT = "heldout"
"""The name a run's evaluation gives a fold's judged frames (``data.holdout_sequence`` or ``data.holdout_block``)."""


def holds_out_fold(data_config) -> bool:
    """Whether a run of ``data_config`` is a fold of the labelled splits: a held-out sequence
    (``holdout_sequence``) or a held-out block of every sequence (``holdout_block``)."""
    return bool(data_config.holdout_sequence or data_config.holdout_block)


def fold_name(data_config) -> str:
    """The fold's name in words ("sequence 0016E5", "block 2 of 5"); "" without a fold."""
    if data_config.holdout_sequence:
        return f"sequence {data_config.holdout_sequence}"
    if data_config.holdout_block:
        return f"block {data_config.holdout_block} of {data_config.holdout_blocks}"
    return ""


def _source(data_config, split: str, train: bool, seed: int, limit: int = 0):
    """The un-augmented frames of ``split`` (generated scenes: the training stream when ``train``, else the
    validation stream, a disjoint part of the generator)."""
    name = data_config.dataset
    if name not in DATASETS:
        raise KeyError(f"unknown dataset {name!r}; valid datasets: {', '.join(DATASETS)}")
    if name == "scenes":
        if split not in SCENE_SPLITS:
            raise DatasetError(f"scenes: split {split!r}: the generated scenes have the splits "
                               f"{', '.join(SCENE_SPLITS)}")
        count = data_config.scenes_train if train else data_config.scenes_val
        count = min(count, limit) if limit else count  # max_train_images / max_val_images, as for files
        return StreetScenes(count, data_config.scene_height, data_config.scene_width,
                            seed=seed + (0 if train else 7919), sequence_blocks=data_config.scene_sequences,
                            stream="train" if train else "val")
    if not data_config.root:
        raise DatasetError(f"data.root is empty: set it to the {name} folder (train: --set data.root=PATH; "
                           f"eval: --data-root PATH)")
    if name == "folder":  # the user's class table
        return FolderDataset(data_config.root, split, limit=limit, classes_file=data_config.classes_file)
    return DATASETS[name](data_config.root, split, limit=limit)


def _augmented(data_config, dataset, seed: int):
    crop = (data_config.crop_height, data_config.crop_width)
    return Augmented(dataset, crop, (data_config.scale_min, data_config.scale_max), data_config.hflip, seed,
                     data_config.scale_fill, paste_class_ids(data_config.paste_classes, dataset.classes),
                     data_config.paste_probability)


def build_dataset(data_config, split: str, train: bool, seed: int = 0, part: str = "all"):
    """The dataset named by ``data_config.dataset`` for ``split``; training splits are augmented.

    ``part``: "all", or with ``data_config.holdout_prefix`` set, "rest" (the images outside the held-out prefix)
    or "holdout" (those inside it, never augmented: the model-selection set)."""
    limit = data_config.max_train_images if train else data_config.max_val_images
    dataset = _source(data_config, split, train, seed, limit if part == "all" else 0)
    if part != "all":
        if not data_config.holdout_prefix or not hasattr(dataset, "split_by_prefix"):
            raise DatasetError(f"data.holdout_prefix: a held-out part needs a prefix and a file-based dataset, "
                               f"got {data_config.holdout_prefix!r} for {data_config.dataset}")
        rest, held = dataset.split_by_prefix(data_config.holdout_prefix)
        # the limits apply after the split: max_train_images to the rest, max_val_images to the held-out part
        held.pairs = held.pairs[:data_config.max_val_images or None]
        if part == "holdout":
            return held
        dataset = rest
        dataset.pairs = dataset.pairs[:data_config.max_train_images or None]
    return _augmented(data_config, dataset, seed) if train else dataset


def labelled_sources(data_config, seed: int = 0) -> list:
    """The un-augmented frames of the labelled splits, ``train_split`` then ``val_split`` (every labelled frame a
    user has: what sequence folds are cut from)."""
    return [_source(data_config, data_config.train_split, True, seed),
            _source(data_config, data_config.val_split, False, seed)]


def sequence_names(data_config, seed: int = 0) -> list[str]:
    """The sequences of the labelled splits, sorted; DatasetError when the frames carry no sequence names."""
    return sorted({name for source in labelled_sources(data_config, seed) for name in frame_sequences(source)})


def fold_frames(data_config, seed: int = 0) -> tuple[Frames, Frames]:
    """(the frames a fold trains on, the frames it judges), un-augmented and uncut: ``data_config.holdout_sequence``
    (`sequence_fold`: every other sequence's frames, the held-out one's) or ``data_config.holdout_block``
    (`block_fold`: block j of every sequence judged, the rest less a buffer of ``block_buffer`` frame numbers around
    it trained on). DatasetError when the fold judges no frame or trains on none."""
    sources = labelled_sources(data_config, seed)
    if data_config.holdout_sequence:
        return sequence_fold(sources, data_config.holdout_sequence)
    return block_fold(sources, data_config.holdout_block, data_config.holdout_blocks, data_config.block_buffer)


def build_fold(data_config, train: bool, seed: int = 0):
    """A fold of the labelled splits (`fold_frames`): with ``train``, the frames it trains on, augmented (at most
    ``max_train_images``); else the frames it judges, in sequence and time order (at most ``max_val_images``).
    DatasetError when the fold judges no frame or trains on none."""
    rest, held = fold_frames(data_config, seed)
    if not train:
        held.frames = held.frames[:data_config.max_val_images or None]
        return held
    rest.frames = rest.frames[:data_config.max_train_images or None]
    return _augmented(data_config, rest, seed)


def build_training(data_config, seed: int = 0):
    """The augmented training set a run of ``data_config`` trains on: its fold's training frames
    (``holdout_sequence``, ``holdout_block``), the train split outside the held-out prefix (``holdout_prefix``), or the
    train split."""
    if holds_out_fold(data_config):
        return build_fold(data_config, train=True, seed=seed)
    part = "rest" if data_config.holdout_prefix else "all"
    return build_dataset(data_config, data_config.train_split, train=True, seed=seed, part=part)


def evaluation_splits(data_config) -> list[str]:
    """The labelled splits a finished run is judged on: the fold's judged frames (`HELDOUT_SPLIT`) with a fold
    (`holds_out_fold`); else the val split, and CamVid's test split where the copy has one (``<root>/test.txt``, as the
    SegNet release does)."""
    if holds_out_fold(data_config):
        return [HELDOUT_SPLIT]
    splits = [data_config.val_split]
    if data_config.dataset == "camvid" and "test" not in splits and (Path(data_config.root) / "test.txt").is_file():
        splits.append("test")
    return splits


def load_raw(path):
    """Read a converted RAW file: (mosaic float32 [1, H, W], metadata dict). See `warpsense.data.raw`."""
    from warpsense.data.raw import load_raw as _load_raw

    return _load_raw(path)


__all__ = ["Augmented", "CamVid", "Cityscapes", "DATASETS", "DatasetError", "FolderDataset", "Frames", "HELDOUT_SPLIT",
           "KITTI360",
           "StreetScenes", "block_fold", "build_dataset", "build_fold", "build_training", "evaluation_splits",
           "fold_frames", "fold_name", "frame_numbers", "frame_sequences", "holds_out_fold", "labelled_sources",
           "load_raw", "sequence_fold", "sequence_names"]
