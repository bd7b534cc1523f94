import numpy as np
import pytest
import torch
from PIL import Image

from warpsense.config import load_config
from warpsense.data import KITTI360, CamVid, Cityscapes, DatasetError, StreetScenes, build_dataset
from warpsense.data.color import linear_to_srgb, srgb_to_linear


def _write_pair(image_path, label_path, label_ids, size=(8, 12)):
    image_path.parent.mkdir(parents=True, exist_ok=True)
    label_path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (*size, 3), dtype=np.uint8)).save(image_path)
    Image.fromarray(np.asarray(label_ids, dtype=np.uint8).reshape(size)).save(label_path)


LABEL_IDS = [7, 8, 11, 26, 24, 0, 33, 3] * 12  # road, sidewalk, building, car, person, unlabeled, bicycle, out of roi
TRAIN_IDS = [0, 1, 2, 13, 11, 255, 18, 255] * 12


def test_cityscapes_fixture_official_layout(tmp_path):
    stem = "aachen_000000_000019"
    _write_pair(tmp_path / "leftImg8bit/train/aachen" / f"{stem}_leftImg8bit.png",
                tmp_path / "gtFine/train/aachen" / f"{stem}_gtFine_labelIds.png", LABEL_IDS)
    image, label = Cityscapes(tmp_path, "train")[0]
    assert image.shape == (3, 8, 12) and image.dtype == torch.uint8
    assert label.flatten().tolist() == TRAIN_IDS
    with pytest.raises(DatasetError, match="leftImg8bit/val"):
        Cityscapes(tmp_path, "val")


def test_kitti360_fixture_official_layout(tmp_path):
    image = "data_2d_raw/2013_05_28_drive_0000_sync/image_00/data_rect/0000000250.png"
    label = "data_2d_semantics/train/2013_05_28_drive_0000_sync/image_00/semantic/0000000250.png"
    _write_pair(tmp_path / image, tmp_path / label, LABEL_IDS)
    listing = tmp_path / "data_2d_semantics/train/2013_05_28_drive_train_frames.txt"
    listing.write_text(f"{image} {label}\n")
    _, labels = KITTI360(tmp_path, "train")[0]
    assert labels.flatten().tolist() == TRAIN_IDS
    listing.write_text("only_one_column\n")
    with pytest.raises(DatasetError, match="frames.txt:1: expected 'image label'"):
        KITTI360(tmp_path, "train")


def test_camvid_real_data(shared_data):
    train = CamVid(shared_data / "camvid", "train")
    val = CamVid(shared_data / "camvid", "val")
    assert len(train) == 367 and len(val) == 101
    image, label = val[0]
    assert image.shape == (3, 360, 480) and label.shape == (360, 480)
    assert set(torch.unique(label).tolist()) <= set(range(11)) | {255}
    with pytest.raises(DatasetError, match="test.txt"):
        CamVid(shared_data / "camvid", "test")


def test_augmented_crops_fixed_size_deterministic():
    config = load_config(None, ["data.scale_min=0.5", "data.scale_max=1.5", "data.crop_height=40",
                                "data.crop_width=56"])
    dataset = build_dataset(config.data, "train", train=True)
    first = dataset[3]
    assert first[0].shape == (3, 40, 56) and first[1].shape == (40, 56)
    assert torch.equal(dataset[3][0], first[0])  # same (seed, epoch, index) -> same sample
    assert not torch.equal(dataset[len(dataset) + 3][0], first[0])  # epoch 1 (the epoch travels in the index)


def test_scenes_have_all_classes_and_are_reproducible():
    scenes = StreetScenes(16, 96, 128, seed=0)
    labels = torch.stack([scenes[i][1] for i in range(16)])
    assert set(torch.unique(labels).tolist()) == set(range(11))
    assert torch.equal(scenes[5][0], StreetScenes(16, 96, 128, seed=0)[5][0])


def test_generated_scenes_take_the_image_limits_as_files_do():
    """data.max_train_images / max_val_images cut generated scenes to their first N, as they cut a file list (the
    scenes ignored them)."""
    config = load_config(None, ["data.scenes_train=6", "data.scenes_val=4", "data.max_train_images=3",
                                "data.max_val_images=2", "data.scene_height=16", "data.scene_width=24"])
    train = build_dataset(config.data, config.data.train_split, train=True)
    val = build_dataset(config.data, config.data.val_split, train=False)
    assert (len(train), len(val)) == (3, 2)
    whole = build_dataset(load_config(None, ["data.scenes_val=4", "data.scene_height=16", "data.scene_width=24"]).data,
                          config.data.val_split, train=False)
    assert len(whole) == 4 and torch.equal(val[1][0], whole[1][0]) and torch.equal(val[1][1], whole[1][1])


def test_srgb_round_trip_and_known_values():
    values = torch.linspace(0, 1, 11)
    torch.testing.assert_close(linear_to_srgb(srgb_to_linear(values)), values, atol=1e-6, rtol=0)
    assert srgb_to_linear(torch.tensor([0.5])).item() == pytest.approx(0.2140, abs=1e-4)


@pytest.mark.parametrize("broken", ["image", "label"])
@pytest.mark.parametrize("damage", ["truncated", "corrupt"])
def test_an_unreadable_file_is_an_error_naming_it(tmp_path, broken, damage):
    """PIL's messages for a truncated or corrupt PNG ("image file is truncated", "broken data stream when reading
    image file") name no file: `warpsense eval` and training stopped with one of them alone."""
    _write_pair(tmp_path / "val" / "0016E5_00001.png", tmp_path / "valannot" / "0016E5_00001.png", [3] * 64 * 96,
                size=(64, 96))
    (tmp_path / "val.txt").write_text("val/0016E5_00001.png valannot/0016E5_00001.png\n")
    path = tmp_path / ("val" if broken == "image" else "valannot") / "0016E5_00001.png"
    content = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(content[: len(content) * 3 // 4])
    else:  # a flipped byte inside the pixel data (IDAT): the header still opens
        middle = bytearray(content)
        middle[len(middle) // 2] ^= 0xFF
        path.write_bytes(bytes(middle))
    with pytest.raises(DatasetError, match=f"^{path}: unreadable image \\("):
        CamVid(tmp_path, "val")[0]


def test_a_listed_file_that_is_missing_or_an_empty_list_is_named(tmp_path):
    """A missing file was "unreadable image ([Errno 2] No such file or directory: ...)"; an empty split list was
    "no image/label pairs found", naming no list."""
    (tmp_path / "val.txt").write_text("val/0016E5_00001.png valannot/0016E5_00001.png\n")
    with pytest.raises(DatasetError, match=f"^{tmp_path / 'val' / '0016E5_00001.png'}: no such file$"):
        CamVid(tmp_path, "val")[0]
    (tmp_path / "val.txt").write_text("\n\n")
    with pytest.raises(DatasetError, match=f"^{tmp_path / 'val.txt'}: no 'image label' lines$"):
        CamVid(tmp_path, "val")


def test_a_colour_label_image_is_refused_and_a_grey_one_saved_as_rgb_is_read(tmp_path):
    """CamVid's original colour-coded labels (RGB, channels differ) were read through their red channel and scored
    as garbage with exit 0; a grey label saved as RGB (one value in every channel) reads as the grey one does."""
    (tmp_path / "val.txt").write_text("val/0016E5_00001.png valannot/0016E5_00001.png\n")
    indices = np.arange(96, dtype=np.uint8).reshape(8, 12) % 12
    _write_pair(tmp_path / "val" / "0016E5_00001.png", tmp_path / "valannot" / "0016E5_00001.png", indices)
    grey = CamVid(tmp_path, "val")[0][1]
    label = tmp_path / "valannot" / "0016E5_00001.png"
    Image.fromarray(np.repeat(indices[..., None], 3, axis=2)).save(label)
    assert torch.equal(CamVid(tmp_path, "val")[0][1], grey)
    Image.fromarray(np.stack([indices, np.full_like(indices, 255)], axis=2), mode="LA").save(label)  # grey + alpha
    assert torch.equal(CamVid(tmp_path, "val")[0][1], grey)
    colours = np.stack([indices, indices, (indices + 1) % 12], axis=2)  # blue differs
    Image.fromarray(colours).save(label)
    with pytest.raises(DatasetError, match=f"^{label}: a colour label image \\(its channels differ\\)"):
        CamVid(tmp_path, "val")[0]
