import importlib.util
import json
from pathlib import Path

TOOL = Path(__file__).resolve().parents[2] / "tools" / "ablation_matrix.py"
TINY = ["data.scenes_train=8", "data.scenes_val=2", "data.batch_size=4", "data.scene_height=32", "data.scene_width=48",
        "data.crop_height=32", "data.crop_width=48", "train.plots=false", "train.compile=off",
        "train.cuda_graph=false", "train.epochs=1", "train.warmup_epochs=0"]


def _tool():
    spec = importlib.util.spec_from_file_location("ablation_matrix", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_dry_run_lists_every_preset_and_seed(tmp_path, capsys):
    outcome = _tool().main(["--seeds", "0,1", "--output-dir", str(tmp_path), "--dry-run"])
    assert len(outcome) == 10 and set(outcome.values()) == {"dry run"}
    printed = capsys.readouterr().out
    assert "--config camvid_learned_cfa --set run.seed=1 --set run.name=camvid_learned_cfa-s1" in printed
    assert list(tmp_path.iterdir()) == []


def test_matrix_trains_goes_on_past_a_failure_and_skips_finished_runs(tmp_path, capsys):
    tool = _tool()
    arguments = ["--presets", "default,no_such_preset", "--seeds", "0", "--output-dir", str(tmp_path)]
    for override in TINY:
        arguments += ["--set", override]
    outcome = tool.main(arguments)
    assert outcome["default-s0"] == "trained" and outcome["no_such_preset-s0"].startswith("failed")
    records = [json.loads(line) for line in (tmp_path / "default-s0" / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in records] == [0]
    assert tool.main(arguments)["default-s0"] == "done before"  # resumable: nothing retrained
    assert "finished earlier, skipped" in capsys.readouterr().out
