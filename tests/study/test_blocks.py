"""Block folds (buffered blocked cross-validation): every sequence cut into k contiguous blocks, fold j judges block j
of each and trains on the rest less a buffer of frame numbers around it; the study's plan, `--plan-only`'s fold
lines, `--cells`, a camera's seed offset (the A/A twin), the report's fold lines and detectable differences, and
records copied in from another machine counted as done."""

import json
import re
import shutil
from pathlib import Path

import pytest

from warpsense.cli import main
from warpsense.config import ConfigError, load_config
from warpsense.data import DatasetError, block_fold, build_fold, frame_numbers, labelled_sources
from warpsense.data.datasets import CamVid
from warpsense.data.scenes import StreetScenes
from warpsense.resources import CONFIG_DIR
from warpsense.study import load_plan, study_record
from warpsense.study.plan import Plan, PlanError, fold_lines, fold_sizes
from warpsense.study.report import render_text

FAST = ["train.epochs=2", "data.scenes_train=12", "data.scenes_val=6", "train.eval_every=2", "study.folds=blocks",
        "study.blocks=3", "study.block_buffer=1", "study.seeds=[0]", "data.scene_height=32", "data.scene_width=48",
        "data.crop_height=32", "data.crop_width=48"]


def _scenes(count: int, blocks: int = 1, stream: str = "train") -> StreetScenes:
    return StreetScenes(count=count, height=8, width=8, sequence_blocks=blocks, stream=stream)


def test_frame_numbers_from_names_or_positions():
    assert CamVid.frame_number_of(Path("train/0016E5_07959.png")) == 7959
    assert CamVid.frame_number_of(Path("train/0006R0_f00930.png")) == 930
    assert CamVid.frame_number_of(Path("train/0001TP_x.png")) is None
    assert frame_numbers(_scenes(6, blocks=2)) == [0, 1, 2, 0, 1, 2]  # no numbers: the position in the sequence


def test_block_fold_cardinality_every_frame_judged_once():
    train, val = _scenes(10, blocks=2), _scenes(5, stream="val")  # sequences train0 (5), train1 (5), val0 (5)
    judged = []
    for block in range(1, 6):
        rest, held = block_fold([train, val], block, 5, buffer=0)
        assert len(held) == 3 and len(rest) == 12  # one frame of each of the 3 sequences
        assert set(held.frames).isdisjoint(rest.frames)
        judged += held.frames
    assert sorted(judged) == [(s, i) for s, n in ((0, 10), (1, 5)) for i in range(n)]


def test_block_fold_buffer_drops_the_held_blocks_neighbours():
    train = _scenes(10)  # one sequence, positions 0..9
    rest, held = block_fold([train], 3, 5, buffer=1)  # block 3: positions 4, 5; buffer: 3 and 6
    assert held.frames == [(0, 4), (0, 5)] and held.frame_numbers == [4, 5]
    assert rest.frames == [(0, 0), (0, 1), (0, 2), (0, 7), (0, 8), (0, 9)]
    rest, held = block_fold([train], 1, 5, buffer=2)  # the first block has neighbours on one side only
    assert held.frames == [(0, 0), (0, 1)] and rest.frames == [(0, i) for i in range(4, 10)]
    assert (held[1][0] == train[1][0]).all()  # the frames themselves


def test_block_fold_errors():
    with pytest.raises(DatasetError, match="no sequence has a frame in it"):
        block_fold([_scenes(2)], 2, 5, buffer=0)  # 2 frames in 5 blocks: blocks 1, 3, 5 are empty
    with pytest.raises(DatasetError, match="nothing is left to train on"):
        block_fold([_scenes(4)], 1, 2, buffer=10)
    with pytest.raises(DatasetError, match="block fold 6: folds are 1..5"):
        block_fold([_scenes(10)], 6, 5, buffer=0)


def test_block_fold_config_checks():
    with pytest.raises(ConfigError, match="data.holdout_block = 6: the folds are 1..5"):
        load_config(None, ["data.holdout_block=6"])
    with pytest.raises(ConfigError, match="data.holdout_sequence and data.holdout_block both hold frames out"):
        load_config(None, ['data.holdout_sequence="train0"', "data.holdout_block=1"])
    with pytest.raises(ConfigError, match="data.holdout_blocks"):
        load_config(None, ["data.holdout_blocks=1"])


def test_camvid_block_folds_train_on_most_frames_none_beside_a_judged_one(shared_data):
    """The CamVid default (5 blocks, 1 s of buffer): each fold trains on >= 75% of the 468 labelled frames, and no
    trained frame is within 30 video frames of a judged frame of its drive (computed here from the file names)."""
    root = f'data.root="{shared_data / "camvid"}"'
    names = [pair[0].stem for source in labelled_sources(load_config("camvid", [root]).data) for pair in source.pairs]
    assert len(names) == 468
    judged_all = []
    for block in range(1, 6):
        config = load_config("camvid", [root, f"data.holdout_block={block}"])
        held, train = build_fold(config.data, train=False), build_fold(config.data, train=True)
        assert len(train) >= 351 and len(train) + len(held) <= 468
        held_names = [names[i] for i in _indices(held)]
        train_names = [names[i] for i in _indices(train.dataset)]
        judged_all += held_names
        for name in held_names:
            drive, number = name.split("_")[0], int(re.sub(r"\D", "", name.split("_", 1)[1]))
            assert not any(other.startswith(drive) and abs(int(re.sub(r"\D", "", other.split("_", 1)[1])) - number)
                           <= 30 for other in train_names)
        assert set(held.sequences) == {"0001TP", "0006R0", "0016E5"}  # a block of every drive
    assert sorted(judged_all) == sorted(names)  # every labelled frame judged once


def _indices(frames) -> list[int]:
    offsets = [0, len(frames.sources[0])]
    return [offsets[source] + index for source, index in frames.frames]


def test_shipped_camvid_plans_use_block_folds_with_a_control_and_a_twin(shared_data, capsys):
    root = f'data.root="{shared_data / "camvid"}"'
    for name in ("camvid_cameras", "camvid_photon_map"):
        plan = load_plan(name, [root])
        assert plan.folds == "blocks" and plan.fold_names() == tuple(f"block{j}" for j in range(1, 6))
        assert all(row["train"] >= 351 for row in fold_sizes(plan))
    plan = load_plan("camvid_cameras", [root])
    cameras = {camera.name: camera for camera in plan.cameras}
    control = plan.config(next(c for c in plan.cells() if c.camera == "clean_srgb"), "runs")
    assert control.model.input == "srgb" and not control.noise.enabled and not control.optics.enabled
    twin = next(c for c in plan.cells() if c.camera == "fixed_isp_twin" and c.seed == 2)
    assert cameras["fixed_isp_twin"].preset == cameras["fixed_isp"].preset
    assert plan.config(twin, "runs").run.seed == 102  # its own training: an independent replicate
    assert main(["study", "run", "camvid_cameras", "--out", "unused", "--plan-only", "--set", root,
                 "--cells", "clean_srgb/night/block2/*"]) == 0
    lines = capsys.readouterr().out.splitlines()
    folds = [line for line in lines if line.startswith("# fold ")]
    assert len(folds) == 5 and all(int(line.split("train ")[1].split()[0]) >= 351 for line in folds)
    assert [line.split("--cell ")[1].split()[0] for line in lines if "--cell" in line] == [
        f"clean_srgb/night/block2/{seed}" for seed in range(3)]
    assert not Path("unused").exists()


def _plan_file(tmp_path: Path, extra: str = "") -> Path:
    text = (CONFIG_DIR / "studies" / "smoke.toml").read_text()
    path = tmp_path / "plan.toml"
    path.write_text(text + extra)
    return path


def test_plan_keys_seed_offset_and_round_trip(tmp_path):
    twin = '\n[[camera]]\nname = "rggb_twin"\nset = ["cfa.mode=\\"fixed\\"", "exposure.learnable=false"]\n' \
           'seed_offset = 100\n'
    plan = load_plan(_plan_file(tmp_path, twin), FAST)
    assert [cell.id for cell in plan.cells()][:4] == ["rggb/night/block1/0", "rccb/night/block1/0",
                                                      "learned/night/block1/0", "rggb_twin/night/block1/0"]
    config = plan.config(plan.cell("rggb_twin/night/block2/0"), tmp_path)
    assert (config.data.holdout_block, config.data.holdout_blocks, config.data.block_buffer) == (2, 3, 1)
    assert config.run.seed == 100 and config.run.name == "rggb_twin.night.block2.seed0"
    assert Plan.from_dict(json.loads(json.dumps(plan.to_dict()))) == plan
    assert "blocks" not in load_plan("smoke").to_dict()  # a plan without block folds records what it did before
    assert [c.seed_offset for c in plan.cameras] == [0, 0, 0, 100]
    # 12 + 6 frames less 4 + 2 judged, less the buffer: one frame of each sequence at the ends, two in the middle
    assert [row["train"] for row in fold_sizes(plan)] == [10, 8, 10]
    assert fold_lines(fold_sizes(plan))[0] == ("fold block1: train 10 frames (56% of the labelled frames), judge 6 "
                                               "frames")


@pytest.mark.parametrize(("study", "overrides", "message"), [
    ('blocks = 3\n', [], 'study.blocks: block folds\' blocks needs folds = "blocks"'),
    ('folds = "blocks"\nblocks = 1\n', [], "study.blocks: blocks must be >= 2"),
    ('folds = "blocks"\nblock_buffer = -1\n', [], "study.block_buffer: blocks must be >= 2 (folds), block_buffer >= 0"),
    ('folds = "blocks"\nblocks = 50\n', [], "fold block1: data: block fold 1 of 50: no sequence has a frame"),
    ('folds = "blocks"\nblock_buffer = 99\n', [], "nothing is left to train on"),
    ('folds = "blocks"\nblock_buffer = 0\n', ["data.holdout_prefix=train"],
     "data.holdout_block and data.holdout_prefix both"),
])
def test_bad_block_plans_are_one_line_errors_with_nothing_written(tmp_path, study, overrides, message, capsys):
    text = (CONFIG_DIR / "studies" / "smoke.toml").read_text().replace('reference = "rggb"\n',
                                                                         f'reference = "rggb"\n{study}')
    plan = tmp_path / "plan.toml"
    plan.write_text(text)
    out = tmp_path / "study"
    arguments = ["study", "run", str(plan), "--out", str(out), "--set", "data.scenes_train=40"]
    for text in overrides:
        arguments += ["--set", text]
    assert main(arguments) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and str(plan) in error and message in error
    assert not out.exists()


def test_cells_patterns_select_and_unknown_pattern_is_refused(tmp_path, capsys):
    plan = load_plan(_plan_file(tmp_path), FAST)
    assert [c.id for c in plan.select(["rccb/*", "*/block3/0"])] == [
        "rccb/night/block1/0", "rccb/night/block2/0", "rggb/night/block3/0", "rccb/night/block3/0",
        "learned/night/block3/0"]
    assert plan.select([]) == plan.cells()
    with pytest.raises(PlanError, match=r"--cells 'mono/\*' matches no cell; cells are camera/light/fold/seed"):
        plan.select(["mono/*"])
    out = tmp_path / "s"
    assert main(["study", "run", str(_plan_file(tmp_path)), "--out", str(out), "--cells", "x/*", "--cell",
                 "rggb/night/0"]) == 2
    assert "give one of them" in capsys.readouterr().err and not out.exists()


def test_a_device_the_machine_lacks_is_refused_before_anything_is_written(tmp_path, capsys):
    """`study run --set run.device=cuda` on a machine without CUDA wrote plan.json, failed every cell and then
    refused the corrected command as another plan; now one line naming the key, nothing written, and the corrected
    command runs."""
    import torch

    if torch.cuda.is_available():
        pytest.skip("a machine with CUDA runs these cells")
    out = tmp_path / "s"
    for overrides in (["run.device=\"cuda\""], ["train.cuda_graph=true"]):
        arguments = ["study", "run", "smoke", "--out", str(out)]
        for text in overrides:
            arguments += ["--set", text]
        assert main(arguments) == 2
        error = capsys.readouterr().err.strip()
        assert len(error.splitlines()) == 1 and "cell rggb/night/0" in error and overrides[0].split("=")[0] in error
        assert not out.exists()


def test_a_block_study_runs_reports_its_folds_and_grows_from_copied_records(tmp_path, capsys):
    """Cells run on one machine (`--cells`), their records copied back without weights into the study directory of
    another, count as done there: the rest of the study completes around them and the report judges all."""
    plan_file = _plan_file(tmp_path)
    overrides = [text for text in FAST if not text.startswith("study.")] + ["model.width=8", "train.plots=false"]
    study = ["--set", "study.folds=blocks", "--set", "study.blocks=3", "--set", "study.block_buffer=1", "--set",
             "study.seeds=[0]"]
    for text in overrides:
        study += ["--set", text]
    lease = tmp_path / "lease"
    assert main(["study", "run", str(plan_file), "--out", str(lease), "--cells", "*/block1/*", *study]) == 0
    out = capsys.readouterr().out
    assert out.count("study: fold block") == 3 and "study: fold block1: train 10 frames" in out
    home = tmp_path / "home"
    shutil.copytree(lease, home, ignore=shutil.ignore_patterns("*.safetensors", "*.png"))
    assert not list(home.rglob("*.safetensors"))
    assert main(["study", "run", str(plan_file), "--out", str(home), "--cells", "rggb/*", "--cells", "rccb/*",
                 *study]) == 0
    out = capsys.readouterr().out
    assert "rggb/night/block1/0: finished earlier, skipped" in out and "rggb/night/block2/0: done" in out
    record = study_record(home, resamples=50, block=2)
    assert record["missing"] == ["learned/night/block2/0", "learned/night/block3/0"]
    assert [row["fold"] for row in record["fold_sizes"]] == ["block1", "block2", "block3"]
    assert record["fold_sizes"][0] == {"fold": "block1", "train": 10, "judged": 6, "labelled": 18}
    comparison = next(c for c in record["splits"]["heldout"]["comparisons"] if c["camera"] == "rccb")
    assert comparison["paired"]["n"] == 3
    half = max((comparison["paired"]["high"] - comparison["paired"]["low"]) / 2,
               (comparison["bootstrap"]["high"] - comparison["bootstrap"]["low"]) / 2)
    assert comparison["detectable"] == pytest.approx(half)
    text = render_text(record)
    assert "block folds (3 blocks of every sequence, buffer 1 frame numbers)" in text
    assert "  fold block1: train 10 frames (56% of the labelled frames), judge 6 frames" in text
    assert f"detects +-{half:.4f}" in text and "note: [heldout] frames come from sequences" not in text
