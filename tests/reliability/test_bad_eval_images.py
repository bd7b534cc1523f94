"""Unreadable images of the sets a run evaluates (val, the held-out sequence, the held-out prefix, CamVid's test split):
`warpsense train` stops before its first epoch with one line naming the file, exit 2, and leaves no run folder
(it used to train until the first evaluation read the file, and leave the run behind)."""

import shutil

import pytest

from tests.reliability.conftest import assert_clean_failure

# two training sequences (0001TP, 0006R0) and val's 0016E5: enough for a held-out prefix and a held-out sequence
TRAIN = ["0001TP_006690", "0001TP_006720", "0001TP_006750", "0006R0_f00930"]
VAL = ["0016E5_07959", "0016E5_07961"]
TINY = ["data.dataset=camvid", "data.batch_size=2", "data.crop_height=32", "data.crop_width=48", "train.epochs=1",
        "train.warmup_epochs=0", "train.plots=false", "train.compile=off", "train.cuda_graph=false"]


def _mini_camvid(shared_data, root):
    """A CamVid copy of `TRAIN` and `VAL` (and a test split of VAL's first frame) in ``root``."""
    lists = {"train": TRAIN, "val": VAL, "test": VAL[:1]}
    for split, frames in lists.items():
        folder = "val" if split == "test" else split
        lines = []
        for frame in frames:
            for kind in (folder, f"{folder}annot"):
                (root / kind).mkdir(parents=True, exist_ok=True)
                shutil.copy(shared_data / "camvid" / kind / f"{frame}.png", root / kind)
            lines.append(f"{folder}/{frame}.png {folder}annot/{frame}.png\n")
        (root / f"{split}.txt").write_text("".join(lines))


@pytest.mark.parametrize("broken,settings,names", [
    ("val/0016E5_07961.png", [], ("of the val set",)),
    ("valannot/0016E5_07959.png", [], ("of the val set",)),
    ("val/0016E5_07961.png", ["data.holdout_sequence=0016E5"], ("of the held-out sequence 0016E5 set",)),
    ("train/0006R0_f00930.png", ["data.holdout_prefix=0006R0"], ("of the held-out prefix 0006R0 set",)),
], ids=["val image", "val label", "held-out sequence", "held-out prefix"])
def test_an_unreadable_evaluation_image_stops_the_run_before_it_trains(broken, settings, names, shared_data, tmp_path,
                                                                       capsys):
    root = tmp_path / "camvid"
    _mini_camvid(shared_data, root)
    (root / broken).write_bytes(b"junk\n")
    overrides = [*TINY, f"data.root={root}", f"run.output_dir={tmp_path / 'runs'}", *settings]
    assert_clean_failure(capsys, ["train", "--no-progress", *(f"--set={text}" for text in overrides)],
                         (f"{root / broken}: unreadable image", *names), watched=tmp_path)


def test_a_truncated_test_split_image_stops_the_run_before_it_trains(shared_data, tmp_path, capsys):
    """The final evaluation reads CamVid's test split (where the copy has one) after every epoch: checked up front
    too. A truncated PNG opens; its missing chunks are what the check finds."""
    root = tmp_path / "camvid"
    _mini_camvid(shared_data, root)
    (root / "test.txt").write_text(f"val/{VAL[0]}.png valannot/{VAL[0]}.png\nval/cut.png valannot/{VAL[0]}.png\n")
    whole = (root / "val" / f"{VAL[0]}.png").read_bytes()
    (root / "val" / "cut.png").write_bytes(whole[: len(whole) // 2])
    overrides = [*TINY, f"data.root={root}", f"run.output_dir={tmp_path / 'runs'}"]
    assert_clean_failure(capsys, ["train", "--no-progress", *(f"--set={text}" for text in overrides)],
                         (f"{root / 'val' / 'cut.png'}: unreadable image of the test set",), watched=tmp_path)
