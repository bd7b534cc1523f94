"""How early a study's cells rank cameras (warpsense.study.early_ranks) on hand-made studies whose answers are known,
read back from study directories (warpsense.study.archives) as the archives are, and tools/pruning_correlation.py."""

import importlib.util
import json
from pathlib import Path

import pytest

from warpsense.study.archives import archive_cells, run_cell
from warpsense.study.early_ranks import cell_ranks, epoch_ranks

FINAL = {"a": 0.50, "b": 0.45, "c": 0.40, "d": 0.35}


def _write(root: Path, cameras: dict, folds=("f1",), seeds=(0, 1), epochs: int = 20, early=None) -> None:
    """A finished study directory: per cell an evaluation (held-out mIoU: the camera's score + 0.001 x seed) and a
    metrics.jsonl validating every 5 epochs (``early(camera, seed, epoch)``, else the final score)."""
    root.mkdir(parents=True)
    (root / "plan.json").write_text(json.dumps({"name": root.name}))
    for camera, score in cameras.items():
        for fold in folds:
            for seed in seeds:
                run = root / "runs" / f"{camera}.night.{fold}.seed{seed}"
                run.mkdir(parents=True)
                final = score(fold, seed) if callable(score) else score + 0.001 * seed
                (run / "evaluation.json").write_text(json.dumps({"splits": {"heldout": {"miou": final}}}))
                records = [{"epoch": e, "val_miou": early(camera, seed, e) if early else final}
                           for e in range(4, epochs, 5)]
                (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_run_names_and_metrics_read_back(tmp_path):
    assert run_cell("map_f2_t10.night.block1.seed3") == ("map_f2_t10", "night", "block1", 3)
    assert run_cell("recipe.night.seed0") == ("recipe", "night", "", 0) and run_cell("x.seedy") is None
    _write(tmp_path / "s", {"a": 0.5})
    [first, _] = archive_cells([tmp_path], metrics=True)
    assert first["curve"] == {4: 0.5, 9: 0.5, 14: 0.5, 19: 0.5} and first["epochs"] == 20 and first["miou"] == 0.5


def test_early_epochs_that_order_cameras_backwards_then_right(tmp_path):
    """Until epoch 10 of 20 the cameras score in the reverse of their final order, from then on in it: the rank
    correlation is -1 at 10-50% of the run... and +1 later; across cells and cameras' means alike."""
    early = lambda camera, seed, epoch: (1 - FINAL[camera] if epoch < 10 else FINAL[camera]) + 0.001 * seed  # noqa: E731
    _write(tmp_path / "s", FINAL, early=early)
    ranks = epoch_ranks(archive_cells([tmp_path], metrics=True), fractions=(0.25, 0.75))
    assert ranks[0]["epochs_at"] == [4] and ranks[1]["epochs_at"] == [14]  # first validated epoch at/after 25%, 75%
    assert ranks[0]["cameras"]["median"] == pytest.approx(-1.0) and ranks[0]["cells"]["median"] < -0.9
    assert ranks[1]["cameras"]["median"] == pytest.approx(1.0) and ranks[1]["cells"]["median"] == pytest.approx(1.0)
    assert ranks[0]["cameras"]["groups"] == 1


def test_the_first_cell_and_whether_the_best_camera_passes_the_first_rung(tmp_path):
    """Fold f1 seed 0 (the first cell) ranks d first and a, the best over all cells, third of four: a top-third rung
    (1 of 4 kept) prunes a unless a margin covers its gap to d's first cell (0.05)."""
    first = {"a": 0.40, "b": 0.30, "c": 0.42, "d": 0.45}

    def score(camera):
        return lambda fold, seed: first[camera] if (fold, seed) == ("f1", 0) else FINAL[camera]

    _write(tmp_path / "s", {camera: score(camera) for camera in FINAL}, folds=("f1", "f2"))
    rows = archive_cells([tmp_path], metrics=True)
    strict = cell_ranks(rows)
    [study] = strict["studies"]
    assert study["cameras"] == 4 and study["folds"] == 2 and study["best_rank"] == 3 and not study["best_kept"]
    # first cells a 0.40, b 0.30, c 0.42, d 0.45 against means a 0.475, b 0.4125, c 0.405, d 0.375: ranks
    # (2, 1, 3, 4) against (4, 3, 2, 1), squared rank differences 4 + 4 + 1 + 9 = 18: 1 - 6 x 18 / (4 x 15) = -0.8
    assert study["first_cell"] == pytest.approx(-0.8)
    assert cell_ranks(rows, margin=0.05)["best_kept"] == 1 and cell_ranks(rows, margin=0.04)["best_kept"] == 0


def test_the_tool_prints_both_tables(tmp_path, capsys):
    _write(tmp_path / "s", FINAL)
    spec = importlib.util.spec_from_file_location(
        "pruning_correlation", Path(__file__).resolve().parents[2] / "tools" / "pruning_correlation.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    assert tool.main([str(tmp_path), "--json", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out
    assert "| 50% | 9 | +1.00 (lowest +1.00, 1 groups) | +1.00 (lowest +1.00, 1 groups) |" in out
    assert "passes a first rung keeping the top 1/3 (or within 0) in 1 of 1 studies" in out
    assert json.loads((tmp_path / "r.json").read_text())["cells"]["best_kept"] == 1
