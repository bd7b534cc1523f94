import json

import pytest


@pytest.fixture
def tool(load_tool):
    return load_tool("results_table")


def _run(root, name, seed, vals, held_out, best_epoch=None):
    run = root / name
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"run": {"name": name, "seed": seed}}))
    records = []
    for epoch, (val, held) in enumerate(zip(vals, held_out)):
        record = {"epoch": epoch}
        if val is not None:
            record.update(val_miou=val, selection_miou=held)
        records.append(record)
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    if best_epoch is not None:
        (run / "checkpoint_best.json").write_text(json.dumps({"state": {"record": records[best_epoch]}}))
    return run


def test_tables_from_run_directories(tool, tmp_path, capsys):
    runs = [_run(tmp_path, "codesign-s0", 0, [0.5, None, 0.6], [0.30, None, 0.35], best_epoch=2),
            _run(tmp_path, "codesign-s1", 1, [0.7, None, 0.64], [0.40, None, 0.33], best_epoch=0),
            _run(tmp_path, "fixed-s0", 0, [None, None], [None, None])]  # never evaluated: skipped, reported
    text = tool.main([str(run) for run in runs] + ["--out", str(tmp_path / "t.md")])
    lines = text.splitlines()
    assert "| codesign | 0 | 3 | 0.600 | 0.350 | 3, 0.350, 0.600 | 0.600 (3) |" in lines
    assert "| codesign | 1 | 3 | 0.640 | 0.330 | 1, 0.400, 0.700 | 0.700 (1) |" in lines
    # mean and sample standard deviation of (0.60, 0.64) and (0.35, 0.33)
    assert "| codesign | 2 | 0.620 +- 0.028 | 0.340 +- 0.014 |" in lines
    assert not any(line.startswith("| fixed") for line in lines)
    assert "skipped" in capsys.readouterr().err and (tmp_path / "t.md").read_text() == text


def test_no_readable_run_is_an_error(tool, tmp_path):
    with pytest.raises(SystemExit, match="no readable run"):
        tool.main([str(tmp_path)])
