"""The report's time per run (issue 60, defect 3): the total wall time, and beside it the steady time, in which each
process's first epoch (where a cold Warp cache compiles the kernels) counts at the median of its other epochs."""

import json

import pytest

from warpsense.study.run_times import run_seconds, steady_run_seconds


def _write(path, records):
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return path


def test_steady_time_counts_each_processs_first_epoch_at_the_median_of_its_others(tmp_path):
    # process 1: setup 2 s, a first epoch of 30 s (compilation), then epochs of 8, 9 and 8 s
    # process 2 (a resume): setup 1 s, a first epoch of 20 s, then 7 and 9 s
    records = [{"epoch": 0, "setup_s": 2.0, "epoch_time_s": 29.0, "wall_s": 32.0}, {"epoch": 1, "wall_s": 40.0},
               {"epoch": 2, "wall_s": 49.0}, {"epoch": 3, "wall_s": 57.0},
               {"epoch": 4, "setup_s": 1.0, "epoch_time_s": 19.0, "wall_s": 21.0}, {"epoch": 5, "wall_s": 28.0},
               {"epoch": 6, "wall_s": 37.0}]
    metrics = _write(tmp_path / "metrics.jsonl", records)
    assert run_seconds(metrics) == 57.0 + 37.0
    # process 1: 57 - 30 + median(8, 9, 8) = 35; process 2: 37 - 20 + median(7, 9) = 25
    assert steady_run_seconds(metrics) == pytest.approx(35.0 + 25.0)


def test_a_process_of_one_epoch_is_counted_as_it_ran(tmp_path):
    metrics = _write(tmp_path / "metrics.jsonl", [{"epoch": 0, "setup_s": 2.0, "wall_s": 32.0}])
    assert steady_run_seconds(metrics) == run_seconds(metrics) == 32.0
    assert steady_run_seconds(tmp_path / "none.jsonl") is None
    torn = tmp_path / "torn.jsonl"
    torn.write_text(json.dumps({"epoch": 0, "setup_s": 1.0, "wall_s": 5.0}) + "\n"
                    + json.dumps({"epoch": 1, "wall_s": 7.0}) + "\n{\"ep")
    assert steady_run_seconds(torn) == pytest.approx(7.0 - 4.0 + 2.0)  # the torn line dropped


def test_the_text_names_both_times(tmp_path):
    from warpsense.study.report import render_text
    from warpsense.study.statistics import t_interval

    group = {"camera": "rggb", "light": "night", "seeds": [0], "folds": [], "cells": 1, "run_s": 94.0,
             "timed_runs": 1, "steady_run_s": 60.0, "miou": t_interval([0.5]),
             "per_class_iou": {"road": t_interval([0.5])},
             "per_class_precision": {"road": None}, "per_class_recall": {"road": None}}
    record = {"study": "s", "directory": str(tmp_path), "level": 0.95, "missing": [], "cells": [], "reference": "rggb",
              "splits": {"val": {"groups": [group], "comparisons": [], "per_sequence": []}}}
    text = render_text(record)
    assert "94 s/run (60 steady)" in text and "one-off Warp kernel compilation" in text
