"""Run the camera ablation ladder (issue 13) for several seeds, then print its results tables.

    python tools/ablation_matrix.py [--presets P1,P2,...] [--seeds 0,1] [--output-dir runs] [--set KEY=VALUE ...]
                                    [--dry-run]

Each (preset, seed) trains as `warpsense train --config PRESET --set run.seed=SEED --set run.name=PRESET-sSEED`
(preset "default" = configs/default.toml) with the given overrides, one after another, every run for the same
number of epochs. The matrix is resumable: a run whose directory already logged its last epoch is skipped, a run
with a checkpoint but fewer epochs is continued (`--resume-dir`). A run that fails is reported and the matrix goes
on. At the end `tools/results_table.py` prints the per-run and per-preset tables of every finished run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

LADDER = ("camvid_fixed_isp", "camvid_raw_fixed", "camvid_learned_cfa", "camvid_learned_cfa_exposure",
          "camvid_codesign")


def run_state(run_dir: Path) -> str:
    """"new", "partial" (a checkpoint to continue from) or "done" (the last epoch of its plan is logged). The plan
    is the one its last checkpoint records (a time budget may have shortened it), else the config's epochs."""
    if not (run_dir / "checkpoint_last.safetensors").is_file():
        return "new"
    state = json.loads((run_dir / "checkpoint_last.json").read_text())["state"]
    epochs = state.get("schedule", {}).get("epochs")
    if epochs is None:
        epochs = json.loads((run_dir / "config.json").read_text())["train"]["epochs"]
    lines = [line for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]
    logged = [json.loads(line)["epoch"] for line in lines]
    return "done" if logged and max(logged) + 1 >= epochs else "partial"


def command_for(preset: str, seed: int, output_dir: Path, overrides: list[str], state: str) -> list[str]:
    name = f"{preset}-s{seed}"
    if state == "partial":
        return [sys.executable, "-m", "warpsense", "train", "--resume-dir", str(output_dir / name), "--no-progress"]
    command = [sys.executable, "-m", "warpsense", "train", "--no-progress"]
    if preset != "default":
        command += ["--config", preset]
    for override in [f"run.seed={seed}", f"run.name={name}", f"run.output_dir={output_dir}", *overrides]:
        command += ["--set", override]
    return command


def main(argv: list[str] | None = None) -> dict[str, str]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default=",".join(LADDER), help="comma-separated presets ('default' = no preset)")
    parser.add_argument("--seeds", default="0,1", help="comma-separated seeds")
    parser.add_argument("--output-dir", default="runs", help="where the run directories go")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override for every run (repeatable)")
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    args = parser.parse_args(argv)
    output_dir = Path(args.output_dir)
    seeds = [int(seed) for seed in args.seeds.split(",") if seed.strip()]
    outcome = {}
    for preset in [p.strip() for p in args.presets.split(",") if p.strip()]:
        for seed in seeds:
            name = f"{preset}-s{seed}"
            state = run_state(output_dir / name)
            if state == "done":
                outcome[name] = "done before"
                print(f"{name}: finished earlier, skipped")
                continue
            command = command_for(preset, seed, output_dir, args.overrides, state)
            print(("would run: " if args.dry_run else "running: ") + " ".join(command[1:]), flush=True)
            if args.dry_run:
                outcome[name] = "dry run"
                continue
            code = subprocess.call(command)
            outcome[name] = "trained" if code == 0 else f"failed (exit {code})"
            if code != 0:
                print(f"{name}: failed with exit code {code}; going on with the matrix", file=sys.stderr)
    finished = [output_dir / name for name, result in outcome.items() if result in ("trained", "done before")]
    if finished:
        subprocess.call([sys.executable, str(Path(__file__).with_name("results_table.py")), *map(str, finished)])
    failed = [name for name, result in outcome.items() if result.startswith("failed")]
    if failed:
        print(f"failed runs: {', '.join(failed)}", file=sys.stderr)
    return outcome


if __name__ == "__main__":
    sys.exit(1 if any(result.startswith("failed") for result in main().values()) else 0)
