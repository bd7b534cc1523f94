"""A training set held on the GPU: decoded once as uint8, augmented there in batches with fixed output shapes.

Same augmentation as `warpsense.data.transforms.scale_crop_flip` (random rescale, raised where needed to cover
the crop or mirrored into it, crop, horizontal flip) and `paste`, drawn per batch from a device generator, so a
training step needs no host work and no host-device copy.
"""

from __future__ import annotations

import contextlib
import os
from concurrent.futures import ThreadPoolExecutor

import torch
from torch.nn import functional as F
from tqdm import tqdm

from warpsense.data.datasets import DatasetError, frame_sequences
from warpsense.data.labels import IGNORE_INDEX
from warpsense.data.transforms import check_fill, paste, reflect_index

DECODE_THREADS = 8
"""Threads that decode a dataset's files at once (PIL and NumPy release the GIL while decoding, so threads overlap
the files' reads and decodes even on a machine of few cores)."""


def decode_all(dataset, description: str, progress: bool = False) -> list:
    """Every item of ``dataset``, in order, read by a pool of threads (items must not share state between indices,
    which holds for the datasets here: files, or scenes drawn from a generator seeded by the index). An item that
    fails raises its own error, as it would read one by one."""
    threads = max(1, min(DECODE_THREADS, os.cpu_count() or 1, len(dataset)))
    with ThreadPoolExecutor(threads) as pool:
        return list(tqdm(pool.map(dataset.__getitem__, range(len(dataset))), total=len(dataset), desc=description,
                         disable=not progress, leave=False))


def dataset_megabytes(dataset) -> float:
    """Decoded size of ``dataset`` (uint8 images + uint8 labels), from its first item."""
    image, _ = dataset[0]
    return len(dataset) * image.shape[1] * image.shape[2] * 4 / 1e6


class DecodedDataset(torch.utils.data.Dataset):
    """An evaluation set decoded once and kept on ``device``: items are (uint8 image [3, H, W], int64 label [H, W])
    as the wrapped dataset gives them, so a validation pass every few epochs decodes no file and copies nothing
    from the host. Labels are stored as uint8 (classes and the ignore index fit) and widened per item."""

    def __init__(self, dataset, device, progress: bool = False):
        self.items = [(image.to(device), label.clamp(max=IGNORE_INDEX).to(torch.uint8).to(device))
                      for image, label in decode_all(dataset, "loading the evaluation set onto the device", progress)]
        self.classes = getattr(dataset, "classes", ())
        with contextlib.suppress(DatasetError):  # the frames' sequence names, where they carry them
            self.sequences = frame_sequences(dataset)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int):
        image, label = self.items[index]
        return image, label.long()


class DeviceBatches:
    """Iterates batches (uint8 images [B, 3, h, w], int64 labels [B, h, w]) of a dataset kept on ``device``.

    Images of different sizes are padded to the largest (with 0 / the ignore label) and remember their own size, so
    the crop never samples the padding as if it were image. Per epoch the order is a permutation drawn from a
    generator seeded by (seed, epoch), so resumed runs repeat it. With ``world_size`` > 1 every rank draws the
    randomness of the global batch (``batch_size`` x ``world_size`` images: their scales, crops, flips and pasted
    donors) and takes its share, every ``world_size``-th image from its ``rank``: the ranks' batches together are
    the batch one process draws (ranks that drew one batch's randomness each from the same generator would give
    rank r's k-th image rank 0's crop and donor: every donor twice in the global batch).
    """

    def __init__(self, dataset, device, batch_size: int, crop: tuple[int, int], scale_range=(1.0, 1.0),
                 hflip: bool = True, seed: int = 0, rank: int = 0, world_size: int = 1, progress: bool = True,
                 fill: str = "cover", paste_classes: tuple[int, ...] = (), paste_probability: float = 0.0):
        items = decode_all(dataset, "loading training set onto the device", progress)
        sizes = [image.shape[1:] for image, _ in items]
        height = max(size[0] for size in sizes)
        width = max(size[1] for size in sizes)
        self.images = torch.zeros(len(items), 3, height, width, dtype=torch.uint8, device=device)
        self.labels = torch.full((len(items), height, width), IGNORE_INDEX, dtype=torch.uint8, device=device)
        for index, (image, label) in enumerate(items):
            self.images[index, :, : image.shape[1], : image.shape[2]] = image.to(device)
            self.labels[index, : label.shape[0], : label.shape[1]] = label.clamp(max=IGNORE_INDEX).to(device)
        self.sizes = torch.tensor(sizes, dtype=torch.float32, device=device)  # [N, 2] (height, width)
        self.device, self.batch_size, self.crop = torch.device(device), batch_size, crop
        self.scale_range, self.hflip, self.seed, self.fill = scale_range, hflip, seed, check_fill(fill)
        self.paste_classes = torch.tensor(paste_classes, dtype=torch.long, device=device)
        self.paste_probability = paste_probability
        self.rank, self.world_size = rank, world_size
        self.epoch = 0
        self.classes = dataset.classes

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.images) // self.world_size // self.batch_size

    def __iter__(self):
        generator = torch.Generator(device=self.device).manual_seed(self.seed * 1_000_003 + self.epoch)
        order = torch.randperm(len(self.images), generator=generator, device=self.device)
        size = self.batch_size * self.world_size  # the global batch
        for step in range(len(self)):
            indices = order[step * size : (step + 1) * size]
            images, labels = self.augment(indices, generator)
            if len(self.paste_classes):
                images, labels = self.paste_donors(images, labels, generator)
            yield images, labels

    def paste_donors(self, images: torch.Tensor, labels: torch.Tensor, generator: torch.Generator):
        """`warpsense.data.transforms.paste` onto each crop with ``paste_probability``, from a training image drawn
        at random and augmented on its own (as `Augmented` does on the CPU path); drawn after the batch's own
        augmentation, so that a run without pasting repeats its batches exactly. The draws are the global batch's;
        ``images`` and ``labels`` are this rank's share of it."""
        size = images.shape[0] * self.world_size
        chosen = torch.rand(size, generator=generator, device=self.device)[self.share] < self.paste_probability
        donors = torch.randint(0, len(self.images), (size,), generator=generator, device=self.device)
        donor_images, donor_labels = self.augment(donors, generator)
        donor_labels = torch.where(chosen[:, None, None], donor_labels, IGNORE_INDEX)  # not chosen: nothing to paste
        return paste(images, labels, donor_images, donor_labels, self.paste_classes)

    @property
    def share(self) -> slice:
        """This rank's images of a global batch."""
        return slice(self.rank, None, self.world_size)

    def augment(self, indices: torch.Tensor, generator: torch.Generator):
        """Scale, crop and flip this rank's share of the global batch's images at ``indices`` into one fixed-shape
        batch (bilinear images, nearest labels), all on the device; where a scaled image is smaller than the crop
        (``fill`` "reflect"), it sits at a random offset and the rest of the crop mirrors it, labelled ignore."""
        draws = torch.rand(indices.shape[0], 4, generator=generator, device=self.device)[self.share]
        indices = indices[self.share]
        batch = indices.shape[0]
        crop_h, crop_w = self.crop
        low, high = self.scale_range
        size = self.sizes[indices]  # [B, 2] source height, width
        scale = low + (high - low) * draws[:, 0]
        if self.fill == "cover":  # raised where needed so the scaled image covers the crop (as in scale_crop_flip)
            scale = torch.maximum(scale, torch.maximum(crop_h / size[:, 0], crop_w / size[:, 1]) * (1 + 1e-6))
        scaled_h, scaled_w = size[:, 0] * scale, size[:, 1] * scale
        # top-left corner of the crop in the scaled image (negative where the image is smaller: it sits inside)
        top = (draws[:, 1] * (scaled_h - crop_h)).floor()
        left = (draws[:, 2] * (scaled_w - crop_w)).floor()
        flip = (draws[:, 3] < 0.5) if self.hflip else torch.zeros(batch, dtype=torch.bool, device=self.device)
        # output pixel (i, j) -> scaled pixel (top + i, left + j), mirrored into the scaled image -> source pixel
        # centre / scale, in the padded store
        rows = torch.arange(crop_h, device=self.device, dtype=torch.float32)
        cols = torch.arange(crop_w, device=self.device, dtype=torch.float32)
        cols = torch.where(flip[:, None], crop_w - 1 - cols[None, :], cols[None, :])
        scaled_y = top[:, None] + rows[None, :]
        scaled_x = left[:, None] + cols
        inside_y = (scaled_y >= 0) & (scaled_y < scaled_h[:, None])
        inside_x = (scaled_x >= 0) & (scaled_x < scaled_w[:, None])
        source_y = (reflect_index(scaled_y, scaled_h[:, None]) + 0.5) / scale[:, None] - 0.5
        source_x = (reflect_index(scaled_x, scaled_w[:, None]) + 0.5) / scale[:, None] - 0.5
        store_h, store_w = self.images.shape[-2:]
        grid_y = (source_y + 0.5) / store_h * 2 - 1
        grid_x = (source_x + 0.5) / store_w * 2 - 1
        grid = torch.stack(torch.broadcast_tensors(grid_x[:, None, :], grid_y[:, :, None]), dim=-1)
        images = F.grid_sample(self.images[indices].float(), grid, mode="bilinear", padding_mode="border",
                               align_corners=False)
        labels = F.grid_sample(self.labels[indices, None].float(), grid, mode="nearest", padding_mode="border",
                               align_corners=False)[:, 0]
        inside = inside_y[:, :, None] & inside_x[:, None, :]
        images = images.round_().clamp_(0, 255).to(torch.uint8)
        labels = torch.where(inside, labels, float(IGNORE_INDEX)).long()
        return images, labels
