"""`warpsense bench --suite time-to-accuracy`: the quick CPU run of both methods on real CamVid frames, the
time-to-level rule, and its refusals."""

import json

import pytest

from warpsense.bench.time_to_accuracy import LEVELS, time_to
from warpsense.cli import main


def test_time_to_is_the_first_validation_at_or_above_the_level():
    curve = [{"wall_s": 10.0, "val_miou": 0.4}, {"wall_s": 20.0, "val_miou": 0.62}, {"wall_s": 30.0, "val_miou": 0.58},
             {"wall_s": 40.0, "val_miou": 0.66}]
    assert time_to(curve, 0.6) == 20.0
    assert time_to(curve, 0.62) == 20.0
    assert time_to(curve, 0.65) == 40.0
    assert time_to(curve, 0.7) is None


def test_quick_cpu_suite_on_camvid(shared_data, tmp_path, capsys):
    out, plot = tmp_path / "tta.json", tmp_path / "tta.png"
    assert main(["bench", "--suite", "time-to-accuracy", "--camvid", str(shared_data / "camvid"), "--quick",
                 "--json", str(out), "--plot", str(plot)]) == 0
    records = json.loads(out.read_text())["records"]
    assert [r["method"] for r in records] == ["warpsense recipe", "torch_baseline"]
    for record in records:
        curve = record["curve"]
        assert [point["epoch"] for point in curve] == [0, 1]  # quick: 2 epochs, validated every epoch
        assert 0 < curve[0]["wall_s"] < curve[1]["wall_s"] == record["wall_s"]
        # the start: setup, then the first epoch, both before the first validation ends
        assert 0 < record["setup_s"] < record["setup_s"] + record["first_epoch_s"] < curve[0]["wall_s"]
        assert 0 <= record["final_val_miou"] == curve[-1]["val_miou"] <= 1
        assert set(record["time_to"]) == {f"{level:.2f}" for level in LEVELS}
    assert records[0]["capture_s"] == 0  # a CPU run captures no CUDA graph
    # the same network for both methods: the config's (the camvid presets' pyramid context included)
    assert records[0]["network_parameters"] == records[1]["network_parameters"] > 0
    baseline = records[1]
    assert baseline["time_to_baseline_final"] is not None and baseline["time_to_baseline_final"] <= baseline["wall_s"]
    assert plot.stat().st_size > 0
    assert "time-to-accuracy  warpsense recipe" in capsys.readouterr().out


def test_exception_without_camvid_or_with_a_plot_of_another_suite(tmp_path):
    with pytest.raises(ValueError, match="needs --camvid"):
        from warpsense.bench.runner import run_bench

        run_bench(suite="time-to-accuracy")
    assert main(["bench", "--suite", "train", "--quick", "--plot", str(tmp_path / "x.png")]) != 0
