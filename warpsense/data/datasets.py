"""Segmentation datasets on disk: CamVid, Cityscapes, KITTI-360 (official folder layouts).

Each returns (image uint8 [3, H, W], label int64 [H, W]) with ignored pixels = 255; augmentation and the
sRGB -> radiance conversion happen later (`warpsense.data.transforms`, `warpsense.data.color`).
"""

from __future__ import annotations

import copy
import re
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch.utils.data import Dataset

from warpsense.data.labels import CAMVID_CLASSES, CITYSCAPES_CLASSES, IGNORE_INDEX, id_to_train_id_table
from warpsense.errors import first_line
from warpsense.files import located


class DatasetError(ValueError):
    """A dataset folder is missing or malformed; the message names the path."""


class Frames(Dataset):
    """Chosen frames of one or more datasets of the same classes, in the order given: the labelled splits joined
    (train + val) and cut by sequence (`sequence_fold`).

    Args:
        sources: datasets with ``classes`` and ``sequences`` (one name per frame).
        frames: (source index, frame index) pairs.
    """

    def __init__(self, sources: list, frames: list[tuple[int, int]]):
        self.sources, self.frames = list(sources), list(frames)
        self.classes = sources[0].classes
        self._names = [frame_sequences(source) for source in sources]
        self._numbers = [frame_numbers(source) for source in sources]

    @property
    def sequences(self) -> list[str]:
        """The sequence of each chosen frame (``frames`` may be cut after construction)."""
        return [self._names[source][index] for source, index in self.frames]

    @property
    def frame_numbers(self) -> list[int]:
        """The number of each chosen frame in its sequence (`frame_numbers` of its source)."""
        return [self._numbers[source][index] for source, index in self.frames]

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int):
        source, frame = self.frames[index]
        return self.sources[source][frame]


def frame_sequences(dataset) -> list[str]:
    """The sequence (drive, city, generator block) of each frame of ``dataset``; DatasetError naming the dataset
    when its frames carry no sequence names."""
    names = getattr(dataset, "sequences", None)
    if names is None:
        raise DatasetError(f"{type(dataset).__name__}: its frames carry no sequence names (a dataset is split by "
                           f"sequence only when each frame knows its drive)")
    return list(names)


def frame_numbers(dataset) -> list[int]:
    """The number of each frame of ``dataset`` in its sequence, in the sequence's time units: the dataset's own
    (``frame_numbers``: CamVid's video frame number from the file name, 30 a second) where it has them for every
    frame, else the frame's position among the frames of its sequence (0, 1, ...: consecutive frames one apart)."""
    numbers = getattr(dataset, "frame_numbers", None)
    if numbers is not None and None not in numbers:
        return [int(number) for number in numbers]
    seen: dict[str, int] = {}
    positions = []
    for name in frame_sequences(dataset):
        positions.append(seen.get(name, 0))
        seen[name] = positions[-1] + 1
    return positions


def sequence_fold(sources: list, held_out: str) -> tuple[Frames, Frames]:
    """(the frames of every other sequence, the frames of ``held_out``) of the ``sources`` joined, in order.

    Raises:
        DatasetError: ``held_out`` holds no frame, or no frame is left to train on.
    """
    frames = [(s, i) for s, source in enumerate(sources) for i in range(len(source))]
    names = [name for source in sources for name in frame_sequences(source)]
    held = [frame for frame, name in zip(frames, names) if name == held_out]
    rest = [frame for frame, name in zip(frames, names) if name != held_out]
    if not held:
        raise DatasetError(f"sequence {held_out!r} holds no frame; sequences: {', '.join(sorted(set(names)))}")
    if not rest:
        raise DatasetError(f"sequence {held_out!r} holds every frame: nothing is left to train on")
    return Frames(sources, rest), Frames(sources, held)


def block_fold(sources: list, block: int, blocks: int, buffer: int) -> tuple[Frames, Frames]:
    """(the frames a block fold trains on, the frames it judges) of the ``sources`` joined: buffered blocked
    cross-validation (Roberts et al. 2017, Ecography 40: 913-929).

    Each sequence's frames, in the order of their numbers (`frame_numbers`), are cut into ``blocks`` contiguous
    blocks of equal count (the first ``j * n // blocks`` frames before block j); fold ``block`` (1-based) judges
    block ``block`` of every sequence and trains on the rest of the labelled frames, less a buffer: the frames of
    that sequence whose number lies within ``buffer`` of the held-out block's first or last frame (neighbours of a
    judged frame look like it, so a model that trained on them would be judged on what it has seen). The judged
    frames are in sequence and time order, so a bootstrap can draw them in blocks.

    Raises:
        DatasetError: the fold judges no frame, or trains on none.
    """
    if not 1 <= block <= blocks:
        raise DatasetError(f"block fold {block}: folds are 1..{blocks}")
    frames = [(s, i) for s, source in enumerate(sources) for i in range(len(source))]
    names = [name for source in sources for name in frame_sequences(source)]
    numbers = [number for source in sources for number in frame_numbers(source)]
    held, dropped = [], set()
    for name in dict.fromkeys(names):
        order = sorted((i for i, other in enumerate(names) if other == name), key=lambda i: numbers[i])
        n = len(order)
        chosen = order[(block - 1) * n // blocks: block * n // blocks]
        if not chosen:
            continue
        first, last = numbers[chosen[0]], numbers[chosen[-1]]
        held += chosen
        dropped |= {i for i in order if first - buffer <= numbers[i] <= last + buffer}
    train = [frames[i] for i in range(len(frames)) if i not in dropped]
    if not held:
        raise DatasetError(f"block fold {block} of {blocks}: no sequence has a frame in it (every sequence holds "
                           f"fewer than {blocks} frames); use fewer blocks")
    if not train:
        raise DatasetError(f"block fold {block} of {blocks} (buffer {buffer}): nothing is left to train on; use more "
                           f"blocks or a smaller buffer")
    return Frames(sources, train), Frames(sources, [frames[i] for i in held])


def _read_image(path: Path) -> np.ndarray:
    """The pixels of an image file as a writable array (torch.from_numpy needs one); DatasetError naming the file
    where it cannot be decoded (PIL's messages for a truncated or corrupt file, "image file is truncated", name
    none)."""
    try:
        with Image.open(path) as image:
            return np.array(image)
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such file") from None
    except (OSError, SyntaxError) as error:  # PIL reports a broken PNG chunk as a SyntaxError
        raise DatasetError(f"{path}: unreadable image ({first_line(error)})") from None


def _read_rgb(path: Path) -> np.ndarray:
    image = _read_image(path)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    return np.ascontiguousarray(image[..., :3])


def read_pair_list(listing: Path, resolve) -> list[tuple[Path, Path]]:
    """Parse a split list of "image label" lines (blank lines skipped); ``resolve`` maps each listed path to a
    file path. Malformed lines raise DatasetError naming the file and line, and so does a list without a pair."""
    pairs = []
    for line_number, line in enumerate(listing.read_text().splitlines(), 1):
        if not line.strip():
            continue
        parts = line.split()
        if len(parts) != 2:
            raise DatasetError(f"{listing}:{line_number}: expected 'image label', got {line!r}")
        pairs.append((Path(resolve(parts[0])), Path(resolve(parts[1]))))
    if not pairs:  # PairDataset's "no image/label pairs found" would not say which list is empty
        raise DatasetError(f"{listing}: no 'image label' lines")
    return pairs


def split_parts(split: str) -> list[str]:
    """The splits a joint split names, in order: "train+val" -> ["train", "val"] (a final model's training set)."""
    return split.split("+")


def read_split_lists(root: Path, split: str, resolve, kind: str) -> list[tuple[Path, Path]]:
    """The pairs of ``<root>/<part>.txt`` for each part of ``split`` ("train+val": both lists, in order: a final
    model's training set); DatasetError naming a missing list (``kind``: the dataset, for the message)."""
    pairs = []
    for part in split_parts(split):
        listing = root / f"{part}.txt"
        if not listing.is_file():
            raise DatasetError(f"{located(listing)}: {kind} split list not found (expected <root>/{part}.txt with "
                               "'image label' lines; the folder is data.root: --set data.root=DIR, or eval's "
                               "--data-root, bench's --camvid)")
        pairs += read_pair_list(listing, resolve)
    return pairs


class PairDataset(Dataset):
    """(image, label) pairs from explicit paths, with a label lookup table."""

    classes: tuple[str, ...] = ()

    def __init__(self, pairs: list[tuple[Path, Path]], label_table: np.ndarray, limit: int = 0):
        if not pairs:
            raise DatasetError("no image/label pairs found")
        self.pairs = pairs[:limit] if limit else pairs
        self.label_table = label_table

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def sequences(self) -> list[str]:
        """The sequence of each frame (`sequence_of` of its image path)."""
        return [self.sequence_of(image) for image, _ in self.pairs]

    @property
    def frame_numbers(self) -> list[int | None]:
        """The number of each frame in its sequence (`frame_number_of` of its image path; None: not known)."""
        return [self.frame_number_of(image) for image, _ in self.pairs]

    @staticmethod
    def sequence_of(image: Path) -> str:
        """The sequence a frame belongs to, from its image path (a dataset's own rule)."""
        raise DatasetError(f"{image}: this dataset's frames carry no sequence names")

    @staticmethod
    def frame_number_of(image: Path) -> int | None:
        """The frame's number in its sequence, from its image path (a dataset's own rule; None: not known, the
        frame's position in its sequence stands in)."""
        return None

    def split_by_prefix(self, prefix: str) -> tuple["PairDataset", "PairDataset"]:
        """(pairs whose image file name does not start with ``prefix``, those that do): e.g. a CamVid sequence
        ("0006R0") held out of training for model selection."""
        inside = [pair for pair in self.pairs if pair[0].name.startswith(prefix)]
        outside = [pair for pair in self.pairs if not pair[0].name.startswith(prefix)]
        if not inside or not outside:
            raise DatasetError(f"holdout prefix {prefix!r} matches {len(inside)} of {len(self.pairs)} images: it must "
                               f"select some but not all")
        rest, held = copy.copy(self), copy.copy(self)
        rest.pairs, held.pairs = outside, inside
        return rest, held

    def encode(self, label: np.ndarray, label_path: Path) -> np.ndarray:
        """A label image as read -> class indices int64 [H, W] (through ``label_table``). A label saved as RGB (or
        RGBA) with one value in every colour channel is read from its first; one whose channels differ is a colour
        label (e.g. CamVid's original colour-coded labels), which would have been scored as garbage: DatasetError
        naming it."""
        if label.ndim == 3:
            colours = label[..., :3] if label.shape[-1] >= 3 else label[..., :1]  # grey + alpha (LA): the grey
            if not (colours == colours[..., :1]).all():
                raise DatasetError(f"{label_path}: a colour label image (its channels differ): expected one class "
                                   "index a pixel (a grey PNG such as the SegNet release's CamVid labels)")
            label = label[..., 0]
        return self.label_table[label].astype(np.int64)

    def __getitem__(self, index: int):
        image_path, label_path = self.pairs[index]
        image = torch.from_numpy(_read_rgb(image_path)).permute(2, 0, 1).contiguous()
        label = torch.from_numpy(self.encode(_read_image(label_path), label_path))
        if label.shape != image.shape[1:]:
            raise DatasetError(f"{label_path}: label size {tuple(label.shape)} != image size {tuple(image.shape[1:])}")
        return image, label


class CamVid(PairDataset):
    """CamVid as distributed with the SegNet tutorial: ``<root>/<split>.txt`` lists "image label" paths relative
    to root (SegNet's absolute "/SegNet/CamVid/..." prefixes are also accepted); 11 classes, 11 = ignore. A split
    "train+val" joins the lists."""

    classes = CAMVID_CLASSES

    def __init__(self, root: str | Path, split: str = "train", limit: int = 0):
        root = Path(root)
        pairs = read_split_lists(root, split, lambda p: root / p.split("/CamVid/")[-1].lstrip("/"), "CamVid")
        table = np.arange(256, dtype=np.uint8)
        table[11:] = IGNORE_INDEX
        super().__init__(pairs, table, limit)

    @staticmethod
    def sequence_of(image: Path) -> str:
        """The drive: the file name's prefix before the first "_" ("0016E5_07959.png" -> "0016E5")."""
        if "_" not in image.name or not image.name.split("_", 1)[0]:
            raise DatasetError(f"{image}: no sequence prefix in the file name (CamVid names frames SEQUENCE_FRAME, "
                               f"e.g. 0016E5_07959.png)")
        return image.name.split("_", 1)[0]

    @staticmethod
    def frame_number_of(image: Path) -> int | None:
        """The video frame number after the prefix ("0016E5_07959.png" -> 7959, "0006R0_f00930.png" -> 930; 30
        a second), None where the name holds no digits there."""
        digits = re.sub(r"\D", "", Path(image).stem.split("_", 1)[-1]) if "_" in Path(image).name else ""
        return int(digits) if digits else None


class Cityscapes(PairDataset):
    """Cityscapes: ``leftImg8bit/<split>/<city>/*_leftImg8bit.png`` with
    ``gtFine/<split>/<city>/*_gtFine_labelIds.png``; label ids mapped to the 19 train ids."""

    classes = CITYSCAPES_CLASSES

    def __init__(self, root: str | Path, split: str = "train", limit: int = 0):
        root = Path(root)
        image_dir = root / "leftImg8bit" / split
        if not image_dir.is_dir():
            raise DatasetError(f"{image_dir}: Cityscapes images not found")
        pairs = []
        for image in sorted(image_dir.glob("*/*_leftImg8bit.png")):
            stem = image.name[: -len("_leftImg8bit.png")]
            label = root / "gtFine" / split / image.parent.name / f"{stem}_gtFine_labelIds.png"
            if not label.is_file():
                raise DatasetError(f"{label}: label file missing for {image}")
            pairs.append((image, label))
        super().__init__(pairs, id_to_train_id_table(), limit)

    @staticmethod
    def sequence_of(image: Path) -> str:
        """The city: the image's folder (leftImg8bit/<split>/<city>/...)."""
        return image.parent.name


class KITTI360(PairDataset):
    """KITTI-360 2D semantics: ``data_2d_semantics/train/2013_05_28_drive_<split>_frames.txt`` lists
    "data_2d_raw/.../image_00/data_rect/N.png data_2d_semantics/train/.../image_00/semantic/N.png" pairs relative to
    root; the semantic PNGs hold Cityscapes label ids, mapped to the 19 train ids."""

    classes = CITYSCAPES_CLASSES

    def __init__(self, root: str | Path, split: str = "train", limit: int = 0):
        root = Path(root)
        listing = root / "data_2d_semantics" / "train" / f"2013_05_28_drive_{split}_frames.txt"
        if not listing.is_file():
            raise DatasetError(f"{listing}: KITTI-360 split list not found")
        pairs = read_pair_list(listing, lambda p: root / p)
        super().__init__(pairs, id_to_train_id_table(), limit)

    @staticmethod
    def sequence_of(image: Path) -> str:
        """The drive: the path's ``2013_05_28_drive_NNNN_sync`` folder."""
        for part in image.parts:
            if "_drive_" in part:
                return part
        raise DatasetError(f"{image}: no drive folder (2013_05_28_drive_NNNN_sync) in the path")
