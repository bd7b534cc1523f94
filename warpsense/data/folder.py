"""Your own data and classes: a CamVid-layout folder read with a class table of your own (``data.dataset =
"folder"``, ``data.classes_file = PATH``).

The folder: ``<root>/<split>.txt`` lists "image label" lines, paths relative to root (a split "train+val" joins the
lists, as CamVid's). Frame names follow CamVid's SEQUENCE_FRAME rule (`CamVid.sequence_of`), so sequence folds
(``data.holdout_sequence``) work.

The class table, a small TOML or JSON file::

    ignore = 255                  # label id of unlabelled pixels (optional; default 255)
    ignore_color = [0, 0, 0]      # colour of unlabelled pixels in RGB-coded label images (optional)
    [[classes]]
    name = "road"
    id = 3                        # the value of this class in single-channel label images
    color = [128, 64, 128]        # its colour in RGB-coded label images (and in plots)
    [[classes]]
    ...

(JSON: ``{"ignore": 255, "classes": [{"name": "road", "id": 3, "color": [128, 64, 128]}, ...]}``.) The network's
class i is the table's i-th entry. A single-channel label image (8- or 16-bit) holds ids; an RGB(A) one holds
colours. A label pixel whose id (or colour) is neither a class's nor the ignore one is an error naming the label
file, the value and the table: it is never silently ignored.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from warpsense.config import tomllib
from warpsense.data.datasets import CamVid, DatasetError, PairDataset, read_split_lists
from warpsense.data.labels import IGNORE_INDEX
from warpsense.files import located

MAX_LABEL_ID = 65535  # 16-bit label images


@dataclass(frozen=True)
class ClassTable:
    """A user's classes: names, label ids and colours (in the network's class order) and the ignore id/colour."""

    names: tuple[str, ...]
    ids: tuple[int, ...]
    colors: tuple[tuple[int, int, int], ...]
    ignore: int
    ignore_color: tuple[int, int, int] | None
    source: str

    def id_lookup(self) -> np.ndarray:
        """int64 [MAX_LABEL_ID + 1]: label id -> class index, the ignore id -> IGNORE_INDEX, anything else -> -1."""
        table = np.full(MAX_LABEL_ID + 1, -1, dtype=np.int64)
        table[self.ignore] = IGNORE_INDEX
        table[list(self.ids)] = np.arange(len(self.ids))
        return table


def _rgb(value, where: str) -> tuple[int, int, int]:
    if (not isinstance(value, list) or len(value) != 3
            or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255 for v in value)):
        raise DatasetError(f"{where}: a colour is [r, g, b] with integers 0..255, got {value!r}")
    return tuple(value)


def _label_id(value, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_LABEL_ID:
        raise DatasetError(f"{where}: a label id is an integer 0..{MAX_LABEL_ID}, got {value!r}")
    return value


def read_class_table(path: str | Path, root: str | Path | None = None) -> ClassTable:
    """Read and check a class table (TOML or JSON, by suffix); every problem is a one-line DatasetError naming the
    file and the entry. A relative ``path`` is read from the working directory, as every path of a config; a missing
    one is named with the absolute path looked at, and where the dataset folder ``root`` holds a file of its name,
    with the path that reads it."""
    path = Path(path)
    if not path.is_file():
        beside = Path(root) / path.name if root else None
        hint = f"; the dataset folder has one: --set data.classes_file={beside}" if beside and beside.is_file() \
            else ""
        raise DatasetError(f"data.classes_file {located(path)}: no such file (a relative path is read from the "
                           f"working directory){hint}")
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
        elif path.suffix.lower() == ".toml":
            data = tomllib.loads(path.read_text())
        else:
            raise DatasetError(f"data.classes_file {path}: expected a .toml or .json file")
    except (json.JSONDecodeError, tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: cannot parse it ({error})") from None
    if not isinstance(data, dict) or not isinstance(data.get("classes"), list) or not data["classes"]:
        raise DatasetError(f"{path}: expected a non-empty list 'classes' of {{name, id, color}} entries")
    unknown = set(data) - {"classes", "ignore", "ignore_color"}
    if unknown:
        raise DatasetError(f"{path}: unknown key(s) {', '.join(sorted(unknown))}; keys: classes, ignore, ignore_color")
    ignore = _label_id(data.get("ignore", IGNORE_INDEX), f"{path}: ignore")
    ignore_color = _rgb(data["ignore_color"], f"{path}: ignore_color") if "ignore_color" in data else None
    names, ids, colors = [], [], []
    for number, entry in enumerate(data["classes"], 1):
        where = f"{path}: classes entry {number}"
        if not isinstance(entry, dict) or set(entry) != {"name", "id", "color"}:
            raise DatasetError(f"{where}: expected exactly the keys name, id, color, got {entry!r}")
        if not isinstance(entry["name"], str) or not entry["name"].strip():
            raise DatasetError(f"{where}: name must be a non-empty string, got {entry['name']!r}")
        names.append(entry["name"])
        ids.append(_label_id(entry["id"], f"{where} ({entry['name']}) id"))
        colors.append(_rgb(entry["color"], f"{where} ({entry['name']}) color"))
    for kind, values in (("name", names), ("id", ids), ("color", colors)):
        repeated = sorted({str(v) for v in values if values.count(v) > 1})
        if repeated:
            raise DatasetError(f"{path}: class {kind}s must be distinct; repeated: {', '.join(repeated)}")
    if ignore in ids:
        raise DatasetError(f"{path}: the ignore id {ignore} is also the id of class {names[ids.index(ignore)]!r}")
    if ignore_color is not None and ignore_color in colors:
        raise DatasetError(f"{path}: ignore_color {list(ignore_color)} is also the colour of class "
                           f"{names[colors.index(ignore_color)]!r}")
    if len(names) >= IGNORE_INDEX:
        raise DatasetError(f"{path}: {len(names)} classes; at most {IGNORE_INDEX - 1} (index {IGNORE_INDEX} is "
                           "the loss's ignore index)")
    return ClassTable(tuple(names), tuple(ids), tuple(colors), ignore, ignore_color, str(path))


def _packed(rgb: np.ndarray) -> np.ndarray:
    rgb = rgb.astype(np.int64)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


class FolderDataset(PairDataset):
    """A CamVid-layout folder with a class table of the user's (`read_class_table`): labels are checked pixel by
    pixel against it when a frame is read."""

    def __init__(self, root: str | Path, split: str = "train", limit: int = 0, classes_file: str | Path = ""):
        if not classes_file:
            raise DatasetError('data.dataset = "folder" needs data.classes_file: a TOML/JSON class table (names, '
                               "label ids, colours, ignore id; see warpsense/data/folder.py)")
        self.table = read_class_table(classes_file, root)
        self.classes = self.table.names
        root = Path(root)
        pairs = read_split_lists(root, split, lambda p: root / p, "folder")
        super().__init__(pairs, self.table.id_lookup(), limit)
        colours = np.array([_packed(np.array(c)) for c in self.table.colors])
        self._colour_order = np.argsort(colours)
        self._colours_sorted = colours[self._colour_order]

    sequence_of = staticmethod(CamVid.sequence_of)
    frame_number_of = staticmethod(CamVid.frame_number_of)

    def _bad(self, label_path: Path, values: np.ndarray, kind: str) -> DatasetError:
        shown = ", ".join(str(v) for v in values[:5]) + (" ..." if len(values) > 5 else "")
        return DatasetError(f"{label_path}: label {kind} {shown} not in the class table {self.table.source} "
                            f"(ids {', '.join(map(str, self.table.ids))}; ignore {self.table.ignore})")

    def encode(self, label: np.ndarray, label_path: Path) -> np.ndarray:
        """A label image (ids [H, W], or colours [H, W, 3+]) -> class indices int64 [H, W] (IGNORE_INDEX for the
        ignore id or colour); DatasetError naming the file and the values outside the table."""
        if label.ndim == 3:
            packed = _packed(label[..., :3])
            position = np.clip(np.searchsorted(self._colours_sorted, packed), 0, len(self._colours_sorted) - 1)
            found = self._colours_sorted[position] == packed
            indices = np.where(found, self._colour_order[position], -1)
            if self.table.ignore_color is not None:
                indices[packed == _packed(np.array(self.table.ignore_color))] = IGNORE_INDEX
            if (indices < 0).any():
                bad = np.unique(label[..., :3][indices < 0], axis=0)
                colours = np.array([f"({r},{g},{b})" for r, g, b in bad])
                raise self._bad(label_path, colours, "colour(s)")
            return indices.astype(np.int64)
        if label.dtype.kind not in "ui" or label.size and (label.min() < 0 or label.max() > MAX_LABEL_ID):
            raise DatasetError(f"{label_path}: label ids must be integers 0..{MAX_LABEL_ID}, got {label.dtype}")
        indices = self.label_table[label.astype(np.int64)]
        if (indices < 0).any():
            raise self._bad(label_path, np.unique(label[indices < 0]), "value(s)")
        return indices
