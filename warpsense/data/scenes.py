"""Procedurally generated street scenes with labels: the embedded default dataset (no download needed).

Scenes use CamVid's 11 classes: a sky above a horizon, buildings with windows, trees, a road in perspective with
lane markings, pavements, fences, thin poles carrying signs, cars, pedestrians and bicyclists, with texture,
per-scene illumination and sensor-scale detail (1-3 pixel poles) so that optics, noise and the CFA matter.
Scene i is a pure function of (seed, i).
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from warpsense.data.labels import CAMVID_CLASSES

SKY, BUILDING, POLE, ROAD, PAVEMENT, TREE, SIGN, FENCE, CAR, PEDESTRIAN, BICYCLIST = range(11)


def _paint(image, label, mask, color, cls, rng, texture=0.06):
    count = int(mask.sum())
    if count == 0:
        return
    shade = 1.0 + texture * rng.standard_normal((count, 1))
    image[mask] = np.clip(np.asarray(color)[None, :] * shade, 0, 1)
    label[mask] = cls


def render_scene(height: int, width: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One scene: sRGB image float [H, W, 3] in [0, 1] and labels uint8 [H, W]."""
    image = np.zeros((height, width, 3))
    label = np.full((height, width), SKY, dtype=np.uint8)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    horizon = int(height * rng.uniform(0.35, 0.5))
    sky_top, sky_low = np.array([0.35, 0.55, 0.9]), np.array([0.75, 0.85, 0.95])
    t = (yy / max(horizon, 1)).clip(0, 1)[..., None]
    image[:] = sky_top * (1 - t) + sky_low * t
    # buildings along the horizon
    x = 0
    while x < width:
        w = int(rng.uniform(0.12, 0.3) * width)
        top = int(horizon - rng.uniform(0.1, 0.35) * height)
        mask = (xx >= x) & (xx < x + w) & (yy >= top) & (yy < horizon + 4)
        _paint(image, label, mask, rng.uniform(0.3, 0.75, 3) * [1.0, 0.9, 0.8], BUILDING, rng)
        step = max(4, w // 4)
        windows = mask & ((xx - x) % step > step // 2) & ((yy - top) % 6 < 3)
        image[windows] *= 0.5
        x += w + int(rng.integers(0, 6))
    # trees
    for _ in range(int(rng.integers(1, 4))):
        cx, cy = rng.uniform(0, width), horizon - rng.uniform(0, 0.15) * height
        ry, rx = rng.uniform(0.08, 0.2) * height, rng.uniform(0.05, 0.15) * width
        mask = ((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 < 1
        _paint(image, label, mask, [0.2, rng.uniform(0.35, 0.55), 0.15], TREE, rng, texture=0.2)
    # road in perspective, pavements beside it
    depth = (yy - horizon) / max(height - horizon, 1)
    centre = width * rng.uniform(0.4, 0.6)
    half_road = depth * width * rng.uniform(0.45, 0.7)
    below = yy >= horizon
    road = below & (np.abs(xx - centre) < half_road)
    pavement = below & ~road & (np.abs(xx - centre) < half_road * 1.6 + 2)
    _paint(image, label, pavement, [0.55, 0.5, 0.45], PAVEMENT, rng)
    _paint(image, label, road, [0.3, 0.3, 0.32], ROAD, rng, texture=0.04)
    dashes = (yy * 0.25 + 8 / (np.abs(depth) + 0.05)) % 6 < 3
    marks = road & (np.abs(xx - centre) < np.maximum(depth * 3, 0.6)) & dashes
    image[marks] = [0.9, 0.9, 0.85]
    # fence along one pavement edge
    if rng.random() < 0.6:
        side = 1 if rng.random() < 0.5 else -1
        edge = centre + side * half_road * 1.6
        fence = below & (np.abs(xx - edge) < 4 + depth * 10) & (yy < horizon + depth * 0 + (height - horizon) * 0.5)
        fence &= ((xx.astype(int) % 3) == 0) | ((yy.astype(int) % 4) == 0)
        _paint(image, label, fence, [0.45, 0.35, 0.25], FENCE, rng)
    # cars on the road
    for _ in range(int(rng.integers(0, 4))):
        d = rng.uniform(0.15, 0.9)
        cy = horizon + d * (height - horizon)
        cw, ch = d * width * 0.22, d * height * 0.16
        cx = centre + rng.uniform(-0.8, 0.8) * d * width * 0.45
        body = (np.abs(xx - cx) < cw / 2) & (yy > cy - ch) & (yy < cy)
        _paint(image, label, body, rng.uniform(0.05, 0.9, 3), CAR, rng, texture=0.03)
        glass = body & (yy < cy - ch * 0.6) & (np.abs(xx - cx) < cw * 0.35)
        image[glass] = [0.15, 0.2, 0.25]
    # poles with signs, pedestrians and bicyclists on the pavements
    for _ in range(int(rng.integers(1, 5))):
        d = rng.uniform(0.1, 1.0)
        base = horizon + d * (height - horizon)
        side = 1 if rng.random() < 0.5 else -1
        px = centre + side * d * width * rng.uniform(0.75, 0.95)
        thickness = max(0.6, d * 2.0)
        top = base - d * height * 0.7 - 6
        pole = (np.abs(xx - px) < thickness) & (yy > top) & (yy < base)
        _paint(image, label, pole, [0.5, 0.5, 0.5], POLE, rng, texture=0.02)
        if rng.random() < 0.7:
            size = max(2.0, d * 9)
            sign = (np.abs(xx - px) < size) & (np.abs(yy - top) < size)
            _paint(image, label, sign, [[0.85, 0.1, 0.1], [0.1, 0.3, 0.85], [0.9, 0.8, 0.1]][rng.integers(3)], SIGN,
                   rng, texture=0.02)
    for _ in range(int(rng.integers(0, 4))):
        d = rng.uniform(0.15, 1.0)
        base = horizon + d * (height - horizon)
        side = 1 if rng.random() < 0.5 else -1
        px = centre + side * d * width * rng.uniform(0.55, 0.8)
        h = d * height * 0.35 + 3
        cls = PEDESTRIAN if rng.random() < 0.7 else BICYCLIST
        body = (((xx - px) / max(d * 3.5, 1.0)) ** 2 + ((yy - (base - h * 0.45)) / (h * 0.45)) ** 2) < 1
        head = ((xx - px) ** 2 + (yy - (base - h * 0.98)) ** 2) < max(d * 2.2, 1.0) ** 2
        mask = body | head
        if cls == BICYCLIST:
            for wheel in (-1, 1):
                mask |= np.abs(np.hypot(xx - px - wheel * h * 0.25, yy - base + h * 0.15) - h * 0.15) < 0.8
        _paint(image, label, mask, rng.uniform(0.1, 0.8, 3), cls, rng)
    illumination = rng.uniform(0.35, 1.0)
    return np.clip(image * illumination, 0, 1), label


class StreetScenes(Dataset):
    """``count`` generated scenes of ``height`` x ``width``; returns (uint8 [3, H, W], int64 [H, W]).

    ``sequences`` cut the scenes into blocks of consecutive generator indices, as a drive is a block of frames:
    scene i of ``count`` belongs to block ``i * sequence_blocks // count``, named "<stream><k>" (``stream``: "train"
    or "val", the generator streams `warpsense.data.build_dataset` draws each split from, which share no scene)."""

    classes = CAMVID_CLASSES

    def __init__(self, count: int = 256, height: int = 96, width: int = 128, seed: int = 0,
                 sequence_blocks: int = 1, stream: str = "train"):
        self.count, self.height, self.width, self.seed = count, height, width, seed
        self.sequence_blocks, self.stream = sequence_blocks, stream

    def __len__(self) -> int:
        return self.count

    @property
    def sequences(self) -> list[str]:
        return [f"{self.stream}{i * self.sequence_blocks // self.count}" for i in range(self.count)]

    def __getitem__(self, index: int):
        rng = np.random.default_rng([self.seed, index])
        image, label = render_scene(self.height, self.width, rng)
        image = torch.from_numpy((image * 255 + 0.5).astype(np.uint8)).permute(2, 0, 1).contiguous()
        return image, torch.from_numpy(label.astype(np.int64))
