"""tools/aa_simulation.py: the seed spread measured in study directories and the A/A table printed from it."""

import json
import math

import pytest


def _study(root, plan: str, scores: dict) -> None:
    """A finished study directory: plan.json named ``plan`` and one evaluation per (camera, fold, seed)."""
    root.mkdir(parents=True)
    (root / "plan.json").write_text(json.dumps({"name": plan}))
    for (camera, fold, seed), miou in scores.items():
        run = root / "runs" / f"{camera}.night.{fold}.seed{seed}"
        run.mkdir(parents=True)
        (run / "evaluation.json").write_text(json.dumps({"splits": {"heldout": {"miou": miou}}}))


def test_measured_spread_and_the_table(load_tool, tmp_path, capsys):
    tool = load_tool("aa_simulation")
    scores = {("a", "f1", 0): 0.40, ("a", "f1", 1): 0.42, ("a", "f1", 2): 0.44,
              ("a", "f2", 0): 0.30, ("a", "f2", 1): 0.30, ("b", "f1", 0): 0.50, ("b", "f1", 1): 0.53}
    _study(tmp_path / "one" / "study", "p", scores)
    _study(tmp_path / "two" / "study", "p", {("a", "f1", 0): 0.99})  # a rerun of one plan's cell: counted once
    assert tool.main([str(tmp_path / "one"), str(tmp_path / "two"), "--replicates", "2000", "--min-seeds", "2",
                      "--max-seeds", "3", "--json", str(tmp_path / "aa.json")]) == 0
    out = capsys.readouterr().out
    sd = math.sqrt((0.02 ** 2 * 2 + 0.0 + 0.015 ** 2 * 2) / (2 + 1 + 1))  # centred sums of squares / (n - 1)s
    assert f"sd {sd:.4f} over 3 (camera, fold) groups, 7 runs" in out
    assert "| normal, measured sd | 5 |" in out and "| measured residuals, resampled | 1 |" in out
    assert "drive fold" not in out  # no fold measured on 50 runs: no fold-by-fold row
    record = json.loads((tmp_path / "aa.json").read_text())
    assert record["measured"]["sd"] == pytest.approx(sd) and len(record["results"]) == 6
    assert all(row["fixed"][0]["seeds"] == 2 and len(row["sequential"]) == 2 for row in record["results"])
