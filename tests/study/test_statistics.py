"""The study's statistics against hand computations on fixed numbers."""

import math

import numpy as np
import pytest
import torch

from warpsense.study.statistics import (
    block_bootstrap_difference,
    block_weights,
    distinguishable,
    fold_interval,
    iou_from_counts,
    miou_from_counts,
    paired_difference,
    t_interval,
)
from warpsense.train.metrics import ConfusionMatrix

T_975_2 = 4.302652729911275  # Student t, 97.5% quantile, 2 degrees of freedom (tables)


def test_t_interval_by_hand():
    result = t_interval([0.5, 0.6, 0.7])
    half = T_975_2 * 0.1 / math.sqrt(3)  # sample sd 0.1
    assert result["mean"] == pytest.approx(0.6)
    assert result["low"] == pytest.approx(0.6 - half) and result["high"] == pytest.approx(0.6 + half)
    assert result["low"] == pytest.approx(0.351586, abs=1e-6)
    single = t_interval([0.42])
    assert single["mean"] == 0.42 and single["low"] is None and distinguishable(single) is None
    with pytest.raises(ValueError):
        t_interval([])


def test_paired_difference_by_hand_and_verdict():
    camera = {0: 0.60, 1: 0.70, 2: 0.65, 7: 0.1}  # seed 7 has no partner: left out
    reference = {0: 0.50, 1: 0.65, 2: 0.60}
    result = paired_difference(camera, reference)
    assert (result["higher"], result["lower"]) == (3, 0)
    tie = paired_difference({0: 0.5, 1: 0.4, 2: 0.6}, {0: 0.5, 1: 0.5, 2: 0.5})
    assert (tie["higher"], tie["lower"]) == (1, 1)  # a seed without a difference counts on neither side
    # differences 0.10, 0.05, 0.05: mean 1/15, sd sqrt(1/1200)
    half = T_975_2 * math.sqrt(1 / 1200) / math.sqrt(3)
    assert result["seeds"] == [0, 1, 2]
    assert result["mean"] == pytest.approx(1 / 15)
    assert result["low"] == pytest.approx(1 / 15 - half) and result["high"] == pytest.approx(1 / 15 + half)
    assert result["low"] < 0 < result["high"] and distinguishable(result) is False
    consistent = paired_difference({0: 0.61, 1: 0.62, 2: 0.63}, {0: 0.50, 1: 0.51, 2: 0.52})
    assert consistent["low"] == pytest.approx(0.11) and distinguishable(consistent) is True


def test_iou_from_counts_by_hand():
    counts = np.array([[3, 1, 0], [1, 0, 1], [0, 0, 0]])  # (TP, FP, FN) of 3 classes; the third is absent
    iou = iou_from_counts(counts)
    assert iou[0] == 0.75 and iou[1] == 0.5 and math.isnan(iou[2])
    assert miou_from_counts(counts) == pytest.approx(0.625)


def test_per_image_counts_agree_with_the_confusion_matrix():
    generator = torch.Generator().manual_seed(0)
    target = torch.randint(0, 4, (3, 5, 6), generator=generator)
    target[0, 0, :] = 255  # ignored pixels
    prediction = torch.randint(0, 4, (3, 5, 6), generator=generator)
    matrix = ConfusionMatrix(4, "cpu", per_image=True)
    matrix.update(prediction[:2], target[:2])
    matrix.update(prediction[2:], target[2:])
    counts = matrix.per_image_counts().numpy()
    assert counts.shape == (3, 4, 3)
    for image in range(3):  # one image by hand: TP, FP, FN of each class
        valid = target[image] != 255
        for k in range(4):
            p, t = prediction[image][valid] == k, target[image][valid] == k
            assert counts[image, k].tolist() == [int((p & t).sum()), int((p & ~t).sum()), int((~p & t).sum())]
    assert miou_from_counts(counts.sum(0)) == pytest.approx(matrix.compute()["miou"])
    # the reported confusion counts (rows: label, columns: prediction), by hand over the valid pixels
    valid = target != 255
    expected = [[int(((target == a) & (prediction == b) & valid).sum()) for b in range(4)] for a in range(4)]
    assert matrix.compute()["confusion"] == expected


def test_block_bootstrap_difference():
    generator = np.random.default_rng(1)
    reference = generator.integers(0, 50, size=(3, 20, 4, 3))
    sequences = {"a": ["a"] * 20}
    same = block_bootstrap_difference([(r, r, "a") for r in reference], sequences, block=4, resamples=200)
    assert same["mean"] == 0 and same["low"] == 0 and same["high"] == 0
    better = reference.copy()
    better[..., 0] += 20  # more true positives on every image: every resample prefers it
    pairs = [(b, r, "a") for b, r in zip(better, reference)]
    result = block_bootstrap_difference(pairs, sequences, block=4, resamples=200)
    expected = (miou_from_counts(better.sum(1)) - miou_from_counts(reference.sum(1))).mean()
    assert result["mean"] == pytest.approx(expected) and 0 < result["low"] <= result["mean"] <= result["high"]
    assert result["block"] == 4
    assert block_bootstrap_difference(pairs, sequences, block=4, resamples=200) == result  # seeded: reproducible
    with pytest.raises(ValueError, match="one shape"):
        block_bootstrap_difference([(better[0, :5], reference[0], "a")], sequences, resamples=10)


def test_block_bootstrap_by_hand_two_frames():
    """Two frames, blocks of one: a resample is {A, A}, {A, B} or {B, B} with chances 1/4, 1/2, 1/4, so the 2.5%
    and 97.5% percentiles are the {A, A} and {B, B} differences, worked out by hand."""
    # one class; the camera: A has TP 1, FN 1 and B TP 3, FN 1; the reference: A and B TP 1, FN 1 (IoU 1/2)
    camera = np.array([[[1, 0, 1]], [[3, 0, 1]]])
    reference = np.array([[[1, 0, 1]], [[1, 0, 1]]])
    result = block_bootstrap_difference([(camera, reference, "s")], {"s": ["x", "x"]}, block=1, resamples=4000)
    assert result["mean"] == pytest.approx(4 / 6 - 1 / 2)  # both frames: TP 4, FN 2 against TP 2, FN 2
    assert result["low"] == pytest.approx(1 / 2 - 1 / 2)  # {A, A}: TP 2, FN 2
    assert result["high"] == pytest.approx(6 / 8 - 1 / 2)  # {B, B}: TP 6, FN 2


def test_block_weights_stay_within_sequences_and_keep_blocks_together():
    sequences = ["a"] * 7 + ["b"] * 3 + ["a"] * 2  # a sequence's frames need not be adjacent in the list
    weights = block_weights(sequences, block=3, resamples=500, generator=np.random.default_rng(0))
    a, b = np.array([s == "a" for s in sequences]), np.array([s == "b" for s in sequences])
    assert (weights[:, a].sum(1) == 9).all() and (weights[:, b].sum(1) == 3).all()  # each keeps its size
    # a's 9 frames come as 3 blocks of 3 consecutive ones; b, no longer than a block, in blocks of 3 // 2 = 1: drawn
    # whole as one block it would be the same in every resample
    assert weights[:, a].max() <= 3 and (weights[:, a] > 0).sum(1).min() >= 3
    assert len({tuple(row) for row in weights[:, b]}) > 1
    # a sequence shorter than the block (8 frames, blocks of 10: the smoke plan's val) still varies: two blocks of 4
    short = block_weights(["s"] * 8, block=10, resamples=500, generator=np.random.default_rng(2))
    assert (short.sum(1) == 8).all() and len({tuple(row) for row in short}) > 1
    windows = [set(range(start, start + 4)) for start in range(5)]
    for row in short[:50]:  # each draw is two runs of 4 consecutive frames (possibly overlapping)
        assert set(np.flatnonzero(row)) in [first | second for first in windows for second in windows]
    single = block_weights(["s"] * 5, block=1, resamples=2000, generator=np.random.default_rng(1))
    assert single.mean(0) == pytest.approx(np.ones(5), abs=0.1)  # blocks of one: the ordinary bootstrap


def test_fold_interval_by_hand():
    # one fold: the t interval over its seeds
    one = fold_interval({("", 0): 0.5, ("", 1): 0.6, ("", 2): 0.7})
    assert one["mean"] == pytest.approx(0.6) and one["low"] == pytest.approx(0.6 - T_975_2 * 0.1 / math.sqrt(3))
    assert one["folds"] == 1 and one["n"] == 3
    # three folds of two seeds: fold means 0.4, 0.5, 0.6 (sd 0.1), t over the folds with 2 degrees of freedom
    values = {("a", 0): 0.35, ("a", 1): 0.45, ("b", 0): 0.5, ("b", 1): 0.5, ("c", 0): 0.7, ("c", 1): 0.5}
    three = fold_interval(values)
    half = T_975_2 * 0.1 / math.sqrt(3)
    assert three["mean"] == pytest.approx(0.5) and three["n"] == 6 and three["folds"] == 3
    assert three["low"] == pytest.approx(0.5 - half) and three["high"] == pytest.approx(0.5 + half)
    with pytest.raises(ValueError):
        fold_interval({})


def test_paired_difference_over_fold_seed_pairs():
    camera = {("a", 0): 0.60, ("a", 1): 0.70, ("b", 0): 0.65, ("b", 1): 0.2}
    reference = {("a", 0): 0.50, ("a", 1): 0.65, ("b", 0): 0.60}  # ("b", 1) unpaired: left out
    result = paired_difference(camera, reference)
    assert result["seeds"] == [("a", 0), ("a", 1), ("b", 0)]
    assert result["mean"] == pytest.approx(1 / 15)  # as the seed-paired case by hand above
    assert result["low"] == pytest.approx(1 / 15 - T_975_2 * math.sqrt(1 / 1200) / math.sqrt(3))


T_975_1 = 12.706204736174707  # Student t, 97.5% quantile, 1 degree of freedom (tables)


def test_a_score_interval_is_clipped_to_its_range_and_marked_over_too_few_values():
    """Before: the report printed '0.0723 [-0.2872, 0.4319]' for two seeds, an mIoU interval below 0, with no word
    that two values make a t interval 12.7 times their distance wide."""
    from warpsense.study.statistics import interval_text

    two = t_interval([0.0723 - 0.0283, 0.0723 + 0.0283])
    assert two["low"] == pytest.approx(0.0723 - T_975_1 * 0.0283)  # the record keeps the t interval as computed
    assert interval_text(two) == f"0.0723 [0.0000, {0.0723 + T_975_1 * 0.0283:.4f}] (n=2, too few)"
    assert interval_text(t_interval([0.5, 0.6, 0.7])) == "0.6000 [0.3516, 0.8484]"  # 3 values: as before
    low = 0.9745 - T_975_1 * 0.0245
    assert interval_text(t_interval([0.95, 0.999])) == f"0.9745 [{low:.4f}, 1.0000] (n=2, too few)"
    difference = {"mean": -0.4, "low": -1.7, "high": 0.9, "n": 2}  # a difference of scores lies in [-1, 1]
    assert interval_text(difference, signed=True) == "-0.4000 [-1.0000, +0.9000] (n=2, too few)"
    assert interval_text(t_interval([0.42])) == "0.4200 [n=1, no interval]"
    # clustered by fold: the folds' means are the values, however many seeds each fold has
    two_folds = fold_interval({("a", 0): 0.5, ("a", 1): 0.6, ("b", 0): 0.55, ("b", 1): 0.65})
    assert interval_text(two_folds).endswith(" (2 folds, too few)")
    assert not interval_text(fold_interval({(f, s): 0.5 + 0.01 * s + 0.02 * f for f in range(3)
                                            for s in range(2)})).endswith("too few)")

    # the report says once what the mark means, with the t quantiles that make it so; nothing where none is marked
    from warpsense.study.statistics import few_values_note

    [note] = few_values_note({"groups": [{"miou": two}, {"miou": t_interval([0.5, 0.6, 0.7])}],
                              "per_class_iou": {"road": t_interval([0.1])}})
    assert note.startswith("note: 'too few' marks an interval over fewer than 3 independent values")
    assert f"{T_975_1:.2f} over 2" in note and f"at least 3 values (t {T_975_2:.2f})" in note
    assert few_values_note({"groups": [{"miou": t_interval([0.5, 0.6, 0.7])}],
                            "per_class_iou": {"road": two}}) == []  # per-class intervals are not printed
