"""What the commands say to a reader: `warpsense --help`'s line for bench, and eval --latency's figures as a table
(warpsense/cli.py, warpsense/commands/bench.py, warpsense/commands/eval.py, warpsense/bench/timing.py)."""

import argparse
import json
import re

import pytest

from warpsense.bench import BENCH_SUITES
from warpsense.cli import build_parser, main


def _subcommands() -> dict:
    return next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_the_top_level_help_names_every_bench_suite(capsys):
    """Before: bench was "kernel microbenchmarks: error against run time", though it has train, time-to-accuracy
    and study suites."""
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    line = text.split(" bench ", 1)[1].split(" convert ", 1)[0]
    suites = [suite.replace("-", " ") for suite in BENCH_SUITES if suite != "all"]
    assert [suite for suite in suites if suite not in line] == []
    description = " ".join(_subcommands()["bench"].description.split())
    assert "kernel" in description and "study" in description and "training step" in description


def test_eval_latency_prints_a_table_of_the_figures_it_records(tmp_path, capsys):
    """Before: `eval --latency` printed the raw JSON dict ({"device": "cpu", "height": 32, ...})."""
    from tests.test_cli import _untrained_checkpoint

    checkpoint = _untrained_checkpoint(tmp_path / "c.safetensors", [], 11)
    out = tmp_path / "latency.json"
    assert main(["eval", "--checkpoint", checkpoint, "--latency", "--latency-size", "32x48", "--device", "cpu",
                 "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    record = json.loads(out.read_text())["latency"]
    assert "{" not in printed and "latency: batch 1 of 32x48 (HxW) on cpu" in printed
    for name, key in (("sensor + network", "sensor_plus_network_ms"), ("network alone", "network_ms")):
        [row] = [line for line in printed.splitlines() if line.strip().startswith(name + " ")]
        ms, rate = (float(x) for x in re.findall(r"([\d.]+) (?:ms|frames/s)", row))
        assert ms == pytest.approx(record[key], abs=5e-4) and rate == pytest.approx(1000 / record[key], abs=0.05)
    assert "CUDA graph" not in printed  # the CPU records no graph replays


def test_study_run_help_names_every_shipped_plan(capsys):
    """Before: its epilog said only "shipped plans: configs/studies/", naming none (issue 71, item 11)."""
    from pathlib import Path

    with pytest.raises(SystemExit):
        main(["study", "run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    epilog = text.split("shipped plans", 1)[1]
    plans = sorted(p.stem for p in (Path(__file__).resolve().parents[1] / "configs" / "studies").glob("*.toml"))
    assert len(plans) >= 3 and [plan for plan in plans if plan not in epilog] == []
