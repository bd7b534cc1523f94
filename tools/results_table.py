"""Markdown tables for docs/results.md from training run directories (issue 16: docs tables come from run JSON).

    python tools/results_table.py RUN_DIR [RUN_DIR ...] [--out FILE]

Each run directory is what `warpsense train` writes: `config.json`, `metrics.jsonl` and, when the run selected one,
`checkpoint_best.json`. Two tables are printed:

- one row per run: its preset (the config's `run.name` without a trailing `-s<seed>`), seed, epochs, the last
  evaluated epoch's val and held-out mIoU, the selected checkpoint (epoch, held-out, val) and the best val;
- one row per preset: the mean +- standard deviation over its seeds of the last val and held-out mIoU.

Only evaluated epochs count (runs evaluated every N epochs log the others without scores). A run directory with no
evaluated epoch is reported on stderr and left out; the tables go on without it.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
from pathlib import Path


def read_run(run_dir: Path) -> dict:
    """The figures of one run directory; ValueError naming the file when one is missing or unreadable."""
    config_path, metrics_path = run_dir / "config.json", run_dir / "metrics.jsonl"
    for path in (config_path, metrics_path):
        if not path.is_file():
            raise ValueError(f"{path}: missing (not a warpsense run directory?)")
    config = json.loads(config_path.read_text())
    records = []
    for number, line in enumerate(metrics_path.read_text().splitlines(), 1):
        if line.strip():
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                raise ValueError(f"{metrics_path}:{number}: not JSON") from None
    evaluated = [r for r in records if "val_miou" in r]
    if not evaluated:
        raise ValueError(f"{metrics_path}: no evaluated epoch")
    last = evaluated[-1]
    best_val = max(evaluated, key=lambda r: r["val_miou"])
    run = {
        "name": config["run"]["name"], "preset": re.sub(r"-s\d+$", "", config["run"]["name"]),
        "seed": config["run"]["seed"], "epochs": last["epoch"] + 1,
        "val": last["val_miou"], "held_out": last.get("selection_miou"),
        "best_val": best_val["val_miou"], "best_val_epoch": best_val["epoch"] + 1, "selected": None,
    }
    best_json = run_dir / "checkpoint_best.json"
    if best_json.is_file():
        record = json.loads(best_json.read_text())["state"]["record"]
        run["selected"] = (record["epoch"] + 1, record.get("selection_miou"), record.get("val_miou"))
    return run


def _figure(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def _spread(values: list[float]) -> str:
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.3f}"
    return f"{statistics.mean(values):.3f} +- {statistics.stdev(values):.3f}"


def tables(runs: list[dict]) -> str:
    """Per-run and per-preset markdown tables."""
    lines = ["| preset | seed | epochs | val mIoU (last) | held-out (last) | selected: epoch, held-out, val "
             "| best val (epoch) |", "|---|---|---|---|---|---|---|"]
    for run in sorted(runs, key=lambda r: (r["preset"], r["seed"])):
        selected = "-" if run["selected"] is None else \
            f"{run['selected'][0]}, {_figure(run['selected'][1])}, {_figure(run['selected'][2])}"
        lines.append(f"| {run['preset']} | {run['seed']} | {run['epochs']} | {_figure(run['val'])} | "
                     f"{_figure(run['held_out'])} | {selected} | {run['best_val']:.3f} ({run['best_val_epoch']}) |")
    lines += ["", "| preset | seeds | val mIoU (last), mean +- std | held-out (last), mean +- std |",
              "|---|---|---|---|"]
    presets = sorted({run["preset"] for run in runs})
    for preset in presets:
        group = [run for run in runs if run["preset"] == preset]
        held_out = [run["held_out"] for run in group if run["held_out"] is not None]
        lines.append(f"| {preset} | {len(group)} | {_spread([run['val'] for run in group])} | {_spread(held_out)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="run directories")
    parser.add_argument("--out", help="also write the tables to this file")
    args = parser.parse_args(argv)
    runs = []
    for run_dir in args.runs:
        try:
            runs.append(read_run(Path(run_dir)))
        except (ValueError, KeyError, json.JSONDecodeError) as error:
            print(f"results_table: skipped {run_dir}: {error}", file=sys.stderr)
    if not runs:
        raise SystemExit("results_table: no readable run directory")
    text = tables(runs)
    print(text, end="")
    if args.out:
        Path(args.out).write_text(text)
    return text


if __name__ == "__main__":
    main()
