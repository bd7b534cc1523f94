import json

from tests.train.test_training import TINY


def test_dry_run_lists_every_preset_and_seed(tmp_path, capsys, load_tool):
    outcome = load_tool("ablation_matrix").main(["--seeds", "0,1", "--output-dir", str(tmp_path), "--dry-run"])
    assert len(outcome) == 10 and set(outcome.values()) == {"dry run"}
    printed = capsys.readouterr().out
    assert "--config camvid_learned_cfa --set run.seed=1 --set run.name=camvid_learned_cfa-s1" in printed
    assert list(tmp_path.iterdir()) == []


def test_matrix_trains_goes_on_past_a_failure_and_skips_finished_runs(tmp_path, capsys, load_tool):
    tool = load_tool("ablation_matrix")
    arguments = ["--presets", "default,no_such_preset", "--seeds", "0", "--output-dir", str(tmp_path)]
    for override in TINY + ["train.epochs=1", "train.warmup_epochs=0"]:
        arguments += ["--set", override]
    outcome = tool.main(arguments)
    assert outcome["default-s0"] == "trained" and outcome["no_such_preset-s0"].startswith("failed")
    records = [json.loads(line) for line in (tmp_path / "default-s0" / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in records] == [0]
    assert tool.main(arguments)["default-s0"] == "done before"  # resumable: nothing retrained
    assert "finished earlier, skipped" in capsys.readouterr().out


def test_a_run_shortened_by_its_time_budget_counts_as_done(tmp_path, load_tool):
    """config.json keeps the requested epochs; the shortened plan is in the last checkpoint's state."""
    tool = load_tool("ablation_matrix")
    run = tmp_path / "camvid_codesign-s0"
    run.mkdir()
    (run / "checkpoint_last.safetensors").write_bytes(b"")
    (run / "config.json").write_text(json.dumps({"train": {"epochs": 5}}))
    (run / "metrics.jsonl").write_text("".join(json.dumps({"epoch": e}) + "\n" for e in (0, 1)))
    (run / "checkpoint_last.json").write_text(json.dumps({"state": {"epoch": 1, "schedule": {"epochs": 2}}}))
    assert tool.run_state(run) == "done"
    (run / "checkpoint_last.json").write_text(json.dumps({"state": {"epoch": 1}}))  # written before schedules
    assert tool.run_state(run) == "partial"
