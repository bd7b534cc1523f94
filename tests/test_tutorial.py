"""docs/tutorial.md runs as written: its bash blocks, in order, in a fresh folder, and give what the page says."""

import json
import os
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_tutorial_commands_run_and_give_what_the_page_says(tmp_path):
    blocks = re.findall(r"```bash\n(.*?)```", (ROOT / "docs" / "tutorial.md").read_text(), flags=re.DOTALL)
    assert len(blocks) == 5
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    environment = {**os.environ, "WARP_CACHE_PATH": os.environ.get("WARP_CACHE_PATH", str(tmp_path / "cache"))}
    outputs = []
    for block in blocks:
        result = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=tmp_path, capture_output=True,
                                text=True, timeout=600, env=environment)
        assert result.returncode == 0, f"{block}\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}"
        outputs.append(result.stdout)
    cells = [line.split("--cell ")[1].split()[0] for line in outputs[0].splitlines()]
    assert len(cells) == 8 and "rccb/night/val0/1" in cells  # camera x light x fold x seed, as the page says
    report = json.loads((tmp_path / "report.json").read_text())
    part = report["splits"]["heldout"]
    assert [row["sequence"] for row in part["per_sequence"]] == ["train0", "val0"]
    assert part["comparisons"][0]["camera"] == "rccb" and "bootstrap" in part["comparisons"][0]
    # the plan trains enough to learn something (collapsed to one class, every cell scored ~0.014 and both cameras
    # the same), as the page says
    scores = {group["camera"]: group["miou"]["mean"] for group in part["groups"]}
    assert min(scores.values()) > 0.04 and scores["rggb"] != scores["rccb"]
    assert (tmp_path / "report.png").stat().st_size > 10_000 and (tmp_path / "map_map.png").is_file()
    # the map learned something (with 2 epochs every cell predicted one class, 0.0005, and the map was flat): every
    # point well above the one-class level, one best point, and the learned design moved off its start toward the
    # brighter side, as the page says
    [entry] = json.loads((tmp_path / "map.json").read_text())["maps"]
    assert min(point["miou"]["mean"] for point in entry["grid"]) > 0.01 and entry["best"]["tied"] == []
    assert entry["best"]["miou"]["mean"] > 0.08
    [learned] = entry["learned"]
    assert len(learned["runs"]) == 2 and all(run["path"][-1][0] < 5.0 for run in learned["runs"])
    assert "exposure calibration: gain 1.0000 ->" in outputs[4]
