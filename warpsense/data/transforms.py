"""Training augmentation: random rescale, crop to a fixed size (fixed batch shapes keep cudnn fast), flip."""

from __future__ import annotations

import torch
from torch.nn import functional as F
from torch.utils.data import Dataset, Sampler

from warpsense.choices import SCALE_FILLS
from warpsense.data.labels import IGNORE_INDEX


def check_fill(fill: str) -> str:
    """``fill`` if it is one of `warpsense.choices.SCALE_FILLS`, else a KeyError listing them."""
    if fill not in SCALE_FILLS:
        raise KeyError(f"unknown scale fill {fill!r}; valid: {', '.join(SCALE_FILLS)}")
    return fill


def reflect_index(index: torch.Tensor, size) -> torch.Tensor:
    """Positions ``index`` along an axis of length ``size`` (int or float tensor), mirrored into [0, size) with the
    edge repeated (..., 1, 0 | 0, 1, ..., size - 1 | size - 1, ...), as NumPy's ``pad(mode="symmetric")``, for any
    distance outside."""
    period = torch.remainder(index, 2 * size)
    return torch.where(period < size, period, 2 * size - 1 - period)


def _window(extent: int, crop: int, generator: torch.Generator) -> torch.Tensor:
    """Positions [crop] of a random crop along an axis of ``extent`` pixels; where the axis is shorter than the
    crop, the frame sits at a random offset inside it and the positions reach outside [0, extent)."""
    if extent >= crop:
        start = int(torch.randint(0, extent - crop + 1, (), generator=generator))
    else:
        start = -int(torch.randint(0, crop - extent + 1, (), generator=generator))
    return torch.arange(start, start + crop)


def scale_crop_flip(image: torch.Tensor, label: torch.Tensor, crop: tuple[int, int], scale_range: tuple[float, float],
                    hflip: bool, generator: torch.Generator, fill: str = "cover") -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 [3, H, W], int64 [H, W] -> a random (crop_h, crop_w) window after a random rescale and flip.

    ``fill`` (`warpsense.choices.SCALE_FILLS`) decides what happens where the rescaled image is smaller than the
    crop. ``cover`` raises the scale so the rescaled image covers the crop: zero padding would enter the camera (its
    mean normalisation, paper 4.4) and the network as black pixels that no eval frame has. ``reflect`` keeps the
    drawn scale (zoom-out below the crop's size), places the image at a random offset and fills the rest of the crop
    with its mirror image, labelled `IGNORE_INDEX`, so the crop's statistics stay those of a frame."""
    low, high = scale_range
    crop_h, crop_w = crop
    scale = low + (high - low) * float(torch.rand((), generator=generator))
    if fill == "cover":
        scale = max(scale, crop_h / image.shape[1], crop_w / image.shape[2])
    if abs(scale - 1.0) > 1e-6:
        size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[2] * scale)))
        if fill == "cover":
            size = (max(crop_h, size[0]), max(crop_w, size[1]))
        image = F.interpolate(image[None].float(), size=size, mode="bilinear", align_corners=False)[0]
        image = image.round().clamp(0, 255).to(torch.uint8)
        label = F.interpolate(label[None, None].float(), size=size, mode="nearest")[0, 0].long()
    rows = _window(image.shape[1], crop_h, generator)
    cols = _window(image.shape[2], crop_w, generator)
    inside = ((rows >= 0) & (rows < image.shape[1]))[:, None] & ((cols >= 0) & (cols < image.shape[2]))[None, :]
    rows, cols = reflect_index(rows, image.shape[1]), reflect_index(cols, image.shape[2])
    image = image[:, rows[:, None], cols[None, :]]
    label = torch.where(inside, label[rows[:, None], cols[None, :]], IGNORE_INDEX)
    if hflip and bool(torch.rand((), generator=generator) < 0.5):
        image, label = image.flip(-1), label.flip(-1)
    return image.contiguous(), label.contiguous()


def paste_class_ids(names: str, classes) -> tuple[int, ...]:
    """``data.paste_classes`` ("pole,pedestrian", or "") -> the class indices in ``classes``, with an error naming
    the key and the valid names for a name the dataset does not have."""
    ids = []
    for name in (part.strip() for part in names.split(",")):
        if not name:
            continue
        if name not in classes:
            raise ValueError(f"data.paste_classes: {name!r} is not a class of this dataset; "
                             f"valid: {', '.join(classes)}")
        ids.append(list(classes).index(name))
    return tuple(ids)


def paste(image: torch.Tensor, label: torch.Tensor, donor_image: torch.Tensor, donor_label: torch.Tensor,
          classes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Copy-paste augmentation (Ghiasi et al., CVPR 2021; for semantic labels ClassMix, Olsson et al., WACV 2021):
    the donor's pixels of ``classes`` (int64 [K]) replace the image's, their labels with them.

    Shapes: uint8 images [..., 3, H, W], int64 labels [..., H, W], batched or not, donor and image alike. It runs on
    the sRGB radiance before the camera, so pasted objects pass through the same optics and noise as the rest."""
    mask = torch.isin(donor_label, classes)
    return torch.where(mask.unsqueeze(-3), donor_image, image), torch.where(mask, donor_label, label)


class Augmented(Dataset):
    """Wraps a dataset with `scale_crop_flip` (and, with ``paste_classes``, `paste` from another augmented item
    drawn at random, with ``paste_probability``); sample i of epoch e draws from a generator seeded by (seed, e, i),
    so augmentation is the same whatever the worker count, and a resumed run repeats it exactly.

    The epoch travels inside the index (`EpochSampler` yields e * len + i): DataLoader workers, persistent ones
    included, hold their own copy of this object, which a `set_epoch` call in the main process never reaches.
    """

    def __init__(self, dataset, crop: tuple[int, int], scale_range=(1.0, 1.0), hflip: bool = True, seed: int = 0,
                 fill: str = "cover", paste_classes: tuple[int, ...] = (), paste_probability: float = 0.0):
        self.dataset, self.crop, self.scale_range, self.hflip, self.seed = dataset, crop, scale_range, hflip, seed
        self.fill = check_fill(fill)
        self.paste_classes, self.paste_probability = tuple(paste_classes), paste_probability
        self.classes = dataset.classes

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int):
        epoch, index = divmod(int(index), len(self.dataset))
        image, label = self.dataset[index]
        generator = torch.Generator().manual_seed((self.seed * 1_000_003 + epoch) * 1_000_003 + index)
        image, label = self._augment(image, label, generator)
        # the donor is drawn after the crop's own draws, so a run without pasting repeats its augmentation exactly
        if self.paste_classes and float(torch.rand((), generator=generator)) < self.paste_probability:
            donor = int(torch.randint(0, len(self.dataset), (), generator=generator))
            donor_image, donor_label = self._augment(*self.dataset[donor], generator)
            image, label = paste(image, label, donor_image, donor_label, torch.tensor(self.paste_classes))
        return image, label

    def _augment(self, image, label, generator):
        return scale_crop_flip(image, label, self.crop, self.scale_range, self.hflip, generator, self.fill)


class EpochSampler(Sampler):
    """Wraps a sampler with ``set_epoch`` (e.g. DistributedSampler) and yields epoch * dataset_size + index, the
    form `Augmented` reads its epoch from."""

    def __init__(self, sampler, dataset_size: int):
        self.sampler, self.dataset_size, self.epoch = sampler, dataset_size, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch
        self.sampler.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.sampler)

    def __iter__(self):
        return (self.epoch * self.dataset_size + index for index in self.sampler)
