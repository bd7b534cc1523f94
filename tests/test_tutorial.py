"""docs/tutorial.md runs as written: its bash blocks, in order, in one shell that starts in the clone and moves to a
folder of its own (the page's step 0), and give what the page says.

Only what the code guarantees is asserted: the commands run, each writes what the page says it writes, the reports
hold the sections, cells and paths the page names, and nothing is written beside the clone's files. The scores of
runs this short depend on the CPU's floating-point order (the learned design's f-number went down on one machine and
up on another), so no score is asserted; the page gives its numbers as one machine's example."""

import json
import os
import re
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MARK = "@@ tutorial block {} @@"
OUTPUTS = ["two_cameras.toml", "study", "report.json", "report.png", "map", "map.json", "map.png", "map_map.png"]
"""What the page's commands write into the reader's folder."""


def run_tutorial(home: Path) -> tuple[Path, list[str]]:
    """Run every bash block of the page in one bash process from the clone's root, with HOME at ``home``; returns
    the folder the page works in and each block's stdout."""
    blocks = re.findall(r"```bash\n(.*?)```", (ROOT / "docs" / "tutorial.md").read_text(), flags=re.DOTALL)
    assert len(blocks) == 6
    script = "\n".join(f"echo '{MARK.format(n)}'\n{block}" for n, block in enumerate(blocks))
    environment = {**os.environ, "HOME": str(home),
                   "WARP_CACHE_PATH": os.environ.get("WARP_CACHE_PATH", str(home / "warp-cache")),
                   "MPLCONFIGDIR": os.environ.get("MPLCONFIGDIR", str(home / "matplotlib"))}
    result = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=ROOT, capture_output=True, text=True,
                            timeout=1500, env=environment)
    assert result.returncode == 0, f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    outputs = re.split(r"@@ tutorial block \d+ @@\n", result.stdout)[1:]
    assert len(outputs) == len(blocks)
    return home / "warpsense-tutorial", outputs


@pytest.mark.slow
def test_tutorial_commands_run_in_a_folder_of_their_own_and_give_what_the_page_says(tmp_path):
    started = time.time()
    folder, outputs = run_tutorial(tmp_path)
    check_outputs(folder, outputs, started)


def check_outputs(folder: Path, outputs: list[str], started: float) -> None:
    """What the page says its steps give, in ``folder`` (the reader's) and each block's stdout ``outputs``."""
    _, plan_only, _, report_text, map_text, example = outputs

    # item 12: everything lands in the reader's folder, nothing beside the clone's files
    assert all((folder / name).exists() for name in OUTPUTS)
    assert not [name for name in OUTPUTS if (ROOT / name).exists() and (ROOT / name).stat().st_mtime >= started]

    # 1: one command per cell, camera x light x fold x seed
    cells = [line.split("--cell ")[1].split()[0] for line in plan_only.splitlines() if "--cell " in line]
    assert len(cells) == 8 and "rccb/night/val0/1" in cells

    # 2: each cell is an ordinary run directory with its config, metrics, checkpoint and final evaluation
    runs = sorted(path.name for path in (folder / "study" / "runs").iterdir())
    assert runs == sorted(f"{camera}.night.{fold}.seed{seed}" for camera in ("rggb", "rccb")
                          for fold in ("train0", "val0") for seed in (0, 1))
    for run in runs:
        assert {"config.json", "metrics.jsonl", "evaluation.json"} <= {p.name for p in (folder / "study" / "runs" /
                                                                                       run).iterdir()}

    # 3: per camera the mean over (fold, seed) with an interval over the folds' means; the paired difference with a
    # bootstrap interval and a verdict that says better or worse only where both intervals exclude 0 on that side;
    # the per-sequence table; per-class IoU, precision and recall; each run's learned camera
    report = json.loads((folder / "report.json").read_text())
    part = report["splits"]["heldout"]
    assert {group["camera"]: (group["miou"]["n"], group["miou"]["folds"]) for group in part["groups"]} == {
        "rggb": (4, 2), "rccb": (4, 2)}
    assert all(set(group) >= {"per_class_iou", "per_class_precision", "per_class_recall"} for group in part["groups"])
    [comparison] = part["comparisons"]
    paired, bootstrap = comparison["paired"], comparison["bootstrap"]
    assert comparison["camera"] == "rccb" and bootstrap is not None and len(paired["seeds"]) == 4
    sides = {interval["low"] > 0 if interval["low"] > 0 or interval["high"] < 0 else None
             for interval in (paired, bootstrap)}
    expected = {frozenset({True}): "better", frozenset({False}): "worse"}.get(frozenset(sides), "not distinguishable")
    assert comparison["verdict"] == expected
    assert [row["sequence"] for row in part["per_sequence"]] == ["train0", "val0"]
    assert len(report["cells"]) == 8 and all("learned_camera" in cell for cell in report["cells"])
    for head in ("[heldout] mIoU", "difference to the reference camera 'rggb'", "per class", "learned cameras"):
        assert head in report_text
    assert re.search(r"^  night/train0 .*\n  night/val0 ", report_text, flags=re.MULTILINE)  # the per-sequence table
    # every interval here is over 2 values (2 folds' means, 2 seeds a sequence): within [0, 1], marked, explained
    assert "(2 folds, too few)" in report_text and "(n=2, too few)" in report_text
    assert "note: 'too few' marks an interval over fewer than 3 independent values" in report_text
    assert not re.search(r"\[-\d", report_text.split("difference to the reference camera")[0])
    assert (folder / "report.png").stat().st_size > 10_000

    # 4: the map: each grid point's score with its interval, the best point or the tie, the learned design's path
    # (start -> end of each run, every epoch recorded, within the learnable bounds) and score, and the cost
    [entry] = json.loads((folder / "map.json").read_text())["maps"]
    assert sorted(point["camera"] for point in entry["grid"]) == ["map_f1p4_t2", "map_f1p4_t20", "map_f5p6_t2",
                                                                 "map_f5p6_t20"]
    assert all(point["miou"]["n"] == 2 for point in entry["grid"])
    assert (entry["best"]["tied"] == []) == (entry["best"]["camera"] in [p["camera"] for p in entry["grid"]])
    [learned] = entry["learned"]
    assert learned["camera"] == "learned" and sorted(learned["learns"]) == ["optics.exposure_ms", "optics.f_number"]
    assert sorted(run["seed"] for run in learned["runs"]) == [0, 1]
    for run in learned["runs"]:
        assert run["epochs"] == [None, 0, 1, 2, 3, 4, 5] and run["path"][0] == [5.6, 2.0]
        assert all(1.4 <= f_number <= 8.0 and 1.0 <= exposure <= 30.0 for f_number, exposure in run["path"])
        assert run["path"][-1] != run["path"][0]  # the camera step moved the design (the page's path)
    assert entry["cost"]["points"] == 4 and entry["cost"]["runs"] == 8 and learned["cost"]["runs"] == 2
    assert "map of sweep 'map' at night" in map_text and "learned design 'learned'" in map_text
    assert re.search(r"learned/night/0: optics\.f_number 5\.6 -> [\d.]+, optics\.exposure_ms 2 -> [\d.]+ \(6 epochs\)",
                     map_text)
    assert (folder / "map_map.png").stat().st_size > 10_000

    # 5: the example from the clone, run from the reader's folder
    assert "exposure calibration: gain 1.0000 ->" in example
