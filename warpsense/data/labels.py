"""Label spaces: CamVid's 11 classes and Cityscapes' 19 train ids (from the official label ids)."""

from __future__ import annotations

import numpy as np

IGNORE_INDEX = 255

CAMVID_CLASSES = ("sky", "building", "pole", "road", "pavement", "tree", "sign_symbol", "fence", "car",
                  "pedestrian", "bicyclist")
CAMVID_COLORS = ((128, 128, 128), (128, 0, 0), (192, 192, 128), (128, 64, 128), (60, 40, 222), (128, 128, 0),
                 (192, 128, 128), (64, 64, 128), (64, 0, 128), (64, 64, 0), (0, 128, 192))

CITYSCAPES_CLASSES = ("road", "sidewalk", "building", "wall", "fence", "pole", "traffic_light", "traffic_sign",
                      "vegetation", "terrain", "sky", "person", "rider", "car", "truck", "bus", "train",
                      "motorcycle", "bicycle")
CITYSCAPES_COLORS = ((128, 64, 128), (244, 35, 232), (70, 70, 70), (102, 102, 156), (190, 153, 153),
                     (153, 153, 153), (250, 170, 30), (220, 220, 0), (107, 142, 35), (152, 251, 152),
                     (70, 130, 180), (220, 20, 60), (255, 0, 0), (0, 0, 142), (0, 0, 70), (0, 60, 100),
                     (0, 80, 100), (0, 0, 230), (119, 11, 32))
# official Cityscapes label id -> train id (cityscapesScripts' labels.py); all other ids are ignored
CITYSCAPES_ID_TO_TRAIN_ID = {7: 0, 8: 1, 11: 2, 12: 3, 13: 4, 17: 5, 19: 6, 20: 7, 21: 8, 22: 9, 23: 10, 24: 11,
                             25: 12, 26: 13, 27: 14, 28: 15, 31: 16, 32: 17, 33: 18}


def id_to_train_id_table() -> np.ndarray:
    """[256] uint8 lookup table from Cityscapes/KITTI-360 label ids to train ids (255 = ignore)."""
    table = np.full(256, IGNORE_INDEX, dtype=np.uint8)
    for label_id, train_id in CITYSCAPES_ID_TO_TRAIN_ID.items():
        table[label_id] = train_id
    return table


def colorize(label: np.ndarray, num_classes: int) -> np.ndarray:
    """[H, W] class indices -> [H, W, 3] uint8 colours (CamVid palette for 11 classes, Cityscapes for 19)."""
    palette = np.array(CAMVID_COLORS if num_classes <= len(CAMVID_COLORS) else CITYSCAPES_COLORS, dtype=np.uint8)
    out = np.zeros((*label.shape, 3), dtype=np.uint8)
    valid = label < len(palette)
    out[valid] = palette[label[valid]]
    return out
