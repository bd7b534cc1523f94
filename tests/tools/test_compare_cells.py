"""tools/compare_cells.py: per-cell scores of two study directories, their differences and the cells of one."""

import json


def _study(root, scores: dict[str, float], split: str = "val"):
    for cell, miou in scores.items():
        run = root / "runs" / cell
        run.mkdir(parents=True)
        (run / "evaluation.json").write_text(json.dumps({"splits": {split: {"miou": miou}}}))
    (root / "runs" / "unfinished.night.seed9").mkdir(parents=True)  # no evaluation: not a finished cell
    return root


def test_differences_the_largest_and_the_cells_of_one(load_tool, tmp_path, capsys):
    tool = load_tool("compare_cells")
    a = _study(tmp_path / "a", {"x.night.seed0": 0.5, "y.night.seed0": 0.25, "z.night.seed0": 0.1})
    b = _study(tmp_path / "b", {"x.night.seed0": 0.5, "y.night.seed0": 0.375})
    assert tool.main([str(a), str(b), "--json", str(tmp_path / "c.json")]) == 0
    record = json.loads((tmp_path / "c.json").read_text())
    assert [c["cell"] for c in record["cells"]] == ["x.night.seed0", "y.night.seed0"]
    assert [c["difference"] for c in record["cells"]] == [0.0, 0.125]
    assert record["max_abs_difference"] == 0.125 and record["identical"] is False
    assert record["only_a"] == ["z.night.seed0"] and record["only_b"] == []
    out = capsys.readouterr().out
    assert "largest |B - A| 0.1250" in out and "only in A: z.night.seed0" in out
    assert tool.compare({"x": 0.5}, {"x": 0.5})["identical"] is True
    assert tool.compare({}, {})["identical"] is False  # nothing compared is not "identical"


def test_bad_directories_and_splits_are_one_line_errors(load_tool, tmp_path, capsys):
    tool = load_tool("compare_cells")
    a = _study(tmp_path / "a", {"x.night.seed0": 0.5})
    assert tool.main([str(a), str(tmp_path / "nowhere")]) == 2
    error = capsys.readouterr().err.strip()
    assert "nowhere" in error and "runs/" in error and "\n" not in error
    assert tool.main([str(a), str(a), "--split", "test"]) == 2
    error = capsys.readouterr().err.strip()
    assert "evaluation.json" in error and "'test'" in error and "\n" not in error
