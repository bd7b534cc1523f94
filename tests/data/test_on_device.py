import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, SequentialSampler

from tests.conftest import device_params
from warpsense.config import load_config, preset_names
from warpsense.data import StreetScenes
from warpsense.data.labels import CAMVID_CLASSES, IGNORE_INDEX
from warpsense.data.on_device import DeviceBatches
from warpsense.data.transforms import Augmented, EpochSampler, paste, paste_class_ids, reflect_index


class _Sequential(SequentialSampler):
    def set_epoch(self, epoch):
        pass


def test_augmentation_changes_between_epochs_with_persistent_workers():
    """set_epoch in the main process never reached persistent workers' copies: the epoch now travels in the index."""
    dataset = Augmented(StreetScenes(4, 48, 64, seed=0), (32, 40), (0.8, 1.2), seed=0)
    sampler = EpochSampler(_Sequential(dataset), len(dataset))
    loader = DataLoader(dataset, batch_size=4, sampler=sampler, num_workers=2, persistent_workers=True)
    epochs = []
    for epoch in range(2):
        sampler.set_epoch(epoch)
        epochs.append(next(iter(loader))[0])
    assert not torch.equal(epochs[0], epochs[1])
    sampler.set_epoch(0)
    assert torch.equal(next(iter(loader))[0], epochs[0])  # and an epoch repeats exactly


def _batches(scale=(1.0, 1.0), hflip=False, crop=(20, 24)):
    scenes = StreetScenes(6, 30, 40, seed=1)
    return scenes, DeviceBatches(scenes, "cpu", batch_size=3, crop=crop, scale_range=scale, hflip=hflip, seed=0,
                                 progress=False)


def test_device_batches_cardinality_and_epochs():
    _, batches = _batches((0.7, 1.4), True)
    assert len(batches) == 2
    first = [b for b in batches]
    assert all(images.shape == (3, 3, 20, 24) and images.dtype == torch.uint8 and labels.shape == (3, 20, 24)
               for images, labels in first)
    batches.set_epoch(1)
    assert not torch.equal(next(iter(batches))[0], first[0][0])
    batches.set_epoch(0)
    assert torch.equal(next(iter(batches))[0], first[0][0])


def test_device_batches_unscaled_crop_is_a_window_of_the_image():
    scenes, batches = _batches()
    generator = torch.Generator().manual_seed(3)
    images, labels = batches.augment(torch.tensor([2, 4]), generator)
    for k, index in enumerate((2, 4)):
        source, source_label = scenes[index]
        windows = [(y, x) for y in range(11) for x in range(17)
                   if torch.equal(source[:, y : y + 20, x : x + 24], images[k])]
        assert windows, "the batch is not a crop of its image"
        y, x = windows[0]
        assert torch.equal(source_label[y : y + 20, x : x + 24], labels[k])


def test_device_batches_flip():
    scenes, batches = _batches(hflip=True, crop=(30, 40))  # the whole image: a window at (0, 0)
    generator = torch.Generator().manual_seed(0)
    images, labels = batches.augment(torch.tensor([0, 0, 0, 0, 0, 0]), generator)
    source, source_label = scenes[0]
    plain = [k for k in range(6) if torch.equal(images[k], source)]
    flipped = [k for k in range(6) if torch.equal(images[k], source.flip(-1))]
    assert plain and flipped and len(plain) + len(flipped) == 6
    assert torch.equal(labels[flipped[0]], source_label.flip(-1))


def _padding_free(images, labels):
    """No ignore-labelled pixel (the source has none) and no black border row or column."""
    black_rows = (images.amax(dim=(1, 3)) == 0).any()
    black_cols = (images.amax(dim=(1, 2)) == 0).any()
    return bool((labels != IGNORE_INDEX).all()) and not black_rows and not black_cols


def test_downscale_never_pads_the_crop():
    """Normalising the camera output to mean 0.5 over a zero-padded crop brightened training frames by up to 1.74x
    against eval frames: the scale is raised until the image covers the crop, in both data paths."""
    scenes, batches = _batches(scale=(0.5, 0.6), crop=(28, 36))
    assert not (scenes[0][1] == IGNORE_INDEX).any()
    for images, labels in batches:
        assert _padding_free(images, labels)
    cpu_path = Augmented(scenes, (28, 36), (0.5, 0.6), hflip=True, seed=0)
    for index in range(len(cpu_path)):
        image, label = cpu_path[index]
        assert image.shape == (3, 28, 36) and _padding_free(image[None], label[None])


def test_reflect_index_is_numpys_symmetric_padding():
    size, pad = 7, 23  # farther out than the axis is long: the mirror repeats
    expected = np.pad(np.arange(size), pad, mode="symmetric")
    assert reflect_index(torch.arange(-pad, size + pad), size).tolist() == expected.tolist()
    floats = reflect_index(torch.arange(-pad, size + pad, dtype=torch.float32), torch.tensor(float(size)))
    assert floats.tolist() == expected.astype(float).tolist()


def _both_paths(scale, crop, device="cpu", **options):
    """The device path's (on ``device``) and the CPU path's crops of 6 scenes, without flips, with the augmentation
    ``options`` both take (fill, paste_classes, paste_probability); item k: scene k % 6."""
    scenes = StreetScenes(6, 30, 40, seed=1)
    batches = DeviceBatches(scenes, device, batch_size=6, crop=crop, scale_range=scale, hflip=False, seed=0,
                            progress=False, **options)
    generator = torch.Generator(device).manual_seed(0)
    images, labels = batches.augment(torch.arange(6, device=device), generator)
    if options.get("paste_classes"):
        images, labels = batches.paste_donors(images, labels, generator)
    cpu = Augmented(scenes, crop, scale, hflip=False, seed=0, **options)
    return scenes, list(zip(images.cpu(), labels.cpu())) + [cpu[index] for index in range(len(cpu))]


@pytest.mark.parametrize("device", device_params())
def test_reflect_fill_mirrors_the_frame_into_the_crop(device):
    """At scale 1 a 30 x 40 frame sits somewhere inside a 36 x 48 crop, the rest its mirror image (NumPy's
    symmetric padding), labelled ignore: in both data paths."""
    scenes, pairs = _both_paths((1.0, 1.0), (36, 48), device, fill="reflect")
    offsets = set()
    for k, (image, label) in enumerate(pairs):
        source, source_label = scenes[k % 6]
        padded = np.pad(source.numpy(), ((0, 0), (6, 6), (8, 8)), mode="symmetric")
        found = [(y, x) for y in range(7) for x in range(9)
                 if np.array_equal(padded[:, 6 - y : 42 - y, 8 - x : 56 - x], image.numpy())]
        assert found, f"crop {k} is not the frame in its mirror image"
        y, x = found[0]
        expected = torch.full((36, 48), IGNORE_INDEX, dtype=torch.long)
        expected[y : y + 30, x : x + 40] = source_label
        assert torch.equal(label, expected)
        offsets.add((y, x))
    assert len(offsets) > 1  # the frame's place in the crop is drawn


@pytest.mark.parametrize("device", device_params())
def test_reflect_fill_zooms_out_without_black_pixels(device):
    """Below the covering scale the frame really shrinks (ignore labels where it does not reach, about the scaled
    frame's area labelled) and no black padding enters the crop, unlike zero padding."""
    _, pairs = _both_paths((0.5, 0.6), (28, 36), device, fill="reflect")
    for image, label in pairs:
        labelled = int((label != IGNORE_INDEX).sum())
        assert 0.5**2 * 30 * 40 * 0.8 <= labelled <= 0.6**2 * 30 * 40 * 1.2
        assert not bool((image.amax(dim=(0, 2)) == 0).any()) and not bool((image.amax(dim=(0, 1)) == 0).any())


def test_decoded_dataset_gives_the_items_and_the_same_evaluation():
    """The evaluation set kept decoded gives the dataset's own items (ignore pixels included) and so the same
    metrics."""
    from warpsense.config import load_config
    from warpsense.data.on_device import DecodedDataset
    from warpsense.system import build_system
    from warpsense.train.evaluate import evaluate

    dataset = StreetScenes(6, 24, 32, seed=3)
    decoded = DecodedDataset(dataset, "cpu")
    assert len(decoded) == 6 and decoded.classes == dataset.classes
    for index in range(6):
        image, label = dataset[index]
        label = label.clone()
        label[0, :3] = IGNORE_INDEX
        decoded.items[index] = (decoded.items[index][0], label.to(torch.uint8))
        got_image, got_label = decoded[index]
        assert torch.equal(got_image, image) and got_label.dtype == torch.int64 and torch.equal(got_label, label)
    torch.manual_seed(0)
    model = build_system(load_config(None, ["model.width=4"]), len(dataset.classes))
    plain = evaluate(model, DecodedDataset(dataset, "cpu"), "cpu", batch_size=4)
    assert plain == evaluate(model, dataset, "cpu", batch_size=4)


def test_decode_all_keeps_the_order_and_raises_an_items_own_error(monkeypatch):
    """The threaded decode gives the items in index order (more items than threads, uneven item costs), and a
    failing item raises its own error."""
    import time

    from warpsense.data import on_device

    class Slow(torch.utils.data.Dataset):
        def __len__(self):
            return 23

        def __getitem__(self, index):
            time.sleep(0.002 * (index % 3))  # later items finish first now and then
            if index == self.bad:
                raise ValueError(f"item {index}: broken file")
            return torch.full((1,), index), torch.tensor(index)

    monkeypatch.setattr(on_device, "DECODE_THREADS", 4)
    monkeypatch.setattr(on_device.os, "cpu_count", lambda: 4)
    dataset = Slow()
    dataset.bad = -1
    items = on_device.decode_all(dataset, "test")
    assert [int(image) for image, _ in items] == list(range(23))
    dataset.bad = 17
    with pytest.raises(ValueError, match="item 17: broken file"):
        on_device.decode_all(dataset, "test")


def test_paste_matches_a_pixel_loop():
    generator = torch.Generator().manual_seed(5)
    image, donor_image = (torch.randint(0, 256, (2, 3, 6, 7), generator=generator, dtype=torch.uint8) for _ in "ab")
    label, donor_label = (torch.randint(0, 12, (2, 6, 7), generator=generator) for _ in "ab")
    donor_label[0, 0, 0] = IGNORE_INDEX
    pasted_image, pasted_label = paste(image, label, donor_image, donor_label, torch.tensor([2, 9]))
    expected_image, expected_label = image.numpy().copy(), label.numpy().copy()
    for b, y, x in np.ndindex(2, 6, 7):
        if int(donor_label[b, y, x]) in (2, 9):
            expected_image[b, :, y, x] = donor_image[b, :, y, x].numpy()
            expected_label[b, y, x] = int(donor_label[b, y, x])
    assert np.array_equal(pasted_image.numpy(), expected_image) and np.array_equal(pasted_label.numpy(), expected_label)
    assert (pasted_label != label).any()


def test_paste_class_names_are_checked():
    assert paste_class_ids(" pole, pedestrian ,", CAMVID_CLASSES) == (2, 9)
    assert paste_class_ids("", CAMVID_CLASSES) == ()
    with pytest.raises(ValueError, match="data.paste_classes: 'polee' is not a class.*valid: sky, building, pole"):
        paste_class_ids("pole,polee", CAMVID_CLASSES)


THIN = paste_class_ids("pole,sign_symbol,pedestrian,bicyclist", CAMVID_CLASSES)


@pytest.mark.parametrize("preset", preset_names())
def test_paste_classes_of_every_preset_are_classes_of_its_dataset(preset):
    """The camvid presets paste four CamVid classes since round 18 (the base preset sets them), and presets built on
    them for another dataset must name that dataset's classes: a wrong name would fail only when a run starts (the
    cityscapes preset inherited CamVid's names in round 18)."""
    from warpsense.data.labels import CITYSCAPES_CLASSES

    data = load_config(preset).data
    classes = {"camvid": CAMVID_CLASSES, "cityscapes": CITYSCAPES_CLASSES, "kitti360": CITYSCAPES_CLASSES}
    if data.dataset not in classes:
        assert data.paste_classes == "", f"{preset}: paste classes for {data.dataset} are not checked here"
        return
    ids = paste_class_ids(data.paste_classes, classes[data.dataset])
    assert preset != "camvid" or ids == THIN


def _paste_paths(probability, device="cpu"):
    """Crops that are the whole frame at scale 1, so the expected paste is exact; item k: scene k % 6."""
    return _both_paths((1.0, 1.0), (30, 40), device, paste_classes=THIN, paste_probability=probability)


@pytest.mark.parametrize("device", device_params())
def test_paste_puts_a_donors_class_pixels_on_the_crop(device):
    scenes, pairs = _paste_paths(1.0, device)
    changed = 0
    for k, (image, label) in enumerate(pairs):
        own_image, own_label = scenes[k % 6]
        candidates = [paste(own_image, own_label, *scenes[d], torch.tensor(THIN)) for d in range(6)]
        assert any(torch.equal(image, i) and torch.equal(label, lab) for i, lab in candidates), f"crop {k}"
        changed += not torch.equal(label, own_label)
    assert changed >= 4  # donors are drawn, and most carry thin-class pixels the crop did not have there


def test_ranks_batches_together_are_the_one_process_batch():
    """DDP's data: with 2 ranks of batch 2, each step's two shares hold exactly the images, crops, flips and pasted
    donors one process of batch 4 draws (round 22: each rank drew its own batch from the shared generator, so both
    ranks' k-th images had the same crop and donor)."""
    scenes = StreetScenes(9, 30, 40, seed=1)
    options = dict(crop=(20, 24), scale_range=(0.7, 1.4), hflip=True, seed=3, progress=False, paste_classes=THIN,
                   paste_probability=0.7)
    one = DeviceBatches(scenes, "cpu", batch_size=4, **options)
    ranks = [DeviceBatches(scenes, "cpu", batch_size=2, rank=r, world_size=2, **options) for r in range(2)]
    for batches in (one, *ranks):
        batches.set_epoch(1)
    assert len(one) == len(ranks[0]) == len(ranks[1]) == 2
    steps = 0
    for (images, labels), share0, share1 in zip(one, *ranks):
        assert share0[0].shape == (2, 3, 20, 24)
        torch.testing.assert_close(images[0::2], share0[0], rtol=0, atol=0)
        torch.testing.assert_close(images[1::2], share1[0], rtol=0, atol=0)
        torch.testing.assert_close(labels[0::2], share0[1], rtol=0, atol=0)
        torch.testing.assert_close(labels[1::2], share1[1], rtol=0, atol=0)
        assert not torch.equal(share0[0], share1[0])
        steps += 1
    assert steps == 2


@pytest.mark.parametrize("device", device_params())
def test_paste_probability_zero_pastes_nothing(device):
    scenes, pairs = _paste_paths(0.0, device)
    for k, (image, label) in enumerate(pairs):
        assert torch.equal(image, scenes[k % 6][0]) and torch.equal(label, scenes[k % 6][1])
