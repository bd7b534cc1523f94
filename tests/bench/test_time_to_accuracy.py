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


def test_quick_cpu_suite_on_camvid_over_two_seeds(shared_data, tmp_path, capsys):
    out, plot = tmp_path / "tta.json", tmp_path / "tta.png"
    assert main(["bench", "--suite", "time-to-accuracy", "--camvid", str(shared_data / "camvid"), "--quick",
                 "--seeds", "0,1", "--json", str(out), "--plot", str(plot)]) == 0
    records = json.loads(out.read_text())["records"]
    runs = [r for r in records if not r.get("summary")]
    assert [(r["method"], r["seed"]) for r in runs] == [("warpsense recipe", 0), ("torch_baseline", 0),
                                                        ("warpsense recipe", 1), ("torch_baseline", 1)]
    for record in runs:
        curve = record["curve"]
        assert [point["epoch"] for point in curve] == [0, 1]  # quick: 2 epochs, validated every epoch
        assert 0 < curve[0]["wall_s"] < curve[1]["wall_s"] == record["wall_s"]
        # the start: setup, then the first epoch, both before the first validation ends
        assert 0 < record["setup_s"] < record["setup_s"] + record["first_epoch_s"] < curve[0]["wall_s"]
        assert 0 <= record["final_val_miou"] == curve[-1]["val_miou"] <= 1
        assert set(record["time_to"]) == {f"{level:.2f}" for level in LEVELS}
    assert runs[0]["capture_s"] == 0  # a CPU run captures no CUDA graph
    # one untimed warm-up per seed, before either method, recorded with both
    for recipe, baseline in zip(runs[0::2], runs[1::2]):
        assert recipe["process_warmup_s"] == baseline["process_warmup_s"] > 0
    # the same network for both methods: the config's (the camvid presets' pyramid context included)
    assert runs[0]["network_parameters"] == runs[1]["network_parameters"] > 0
    for baseline in runs[1::2]:  # each seed's baseline reaches its own final val, at its end at the latest
        reached = baseline["time_to_baseline_final"]
        assert reached is not None and reached <= baseline["wall_s"]
    assert runs[0]["curve"] != runs[2]["curve"]  # the seeds train differently
    summaries = [r for r in records if r.get("summary")]
    assert [s["method"] for s in summaries] == ["warpsense recipe", "torch_baseline"]
    mean = (runs[1]["final_val_miou"] + runs[3]["final_val_miou"]) / 2
    assert summaries[1]["final_val_miou"]["mean"] == pytest.approx(mean)
    assert plot.stat().st_size > 0
    printed = capsys.readouterr().out
    assert "time-to-accuracy  warpsense recipe    1" in printed
    assert "time-to-accuracy summary over seeds [0, 1]" in printed


def test_summary_means_intervals_and_paired_differences_by_hand():
    from warpsense.bench.time_to_accuracy import summarise

    def run(method, seed, final, end, reached):
        return {"method": method, "seed": seed, "final_val_miou": final, "wall_s": end,
                "time_to_baseline_final": reached}

    records = [run("warpsense recipe", 0, 0.66, 150.0, 100.0), run("torch_baseline", 0, 0.65, 120.0, 110.0),
               run("warpsense recipe", 1, 0.68, 160.0, None), run("torch_baseline", 1, 0.64, 130.0, 125.0),
               run("warpsense recipe", 2, 0.67, 155.0, 90.0), run("torch_baseline", 2, 0.66, 125.0, 120.0)]
    recipe, baseline = summarise(records)
    assert recipe["seeds"] == [0, 1, 2] and recipe["final_val_miou"]["mean"] == pytest.approx(0.67)
    half = 4.302652729911275 * 5.0 / 3**0.5  # t(0.975, 2) x sd 5 / sqrt(3)
    assert recipe["wall_s"]["low"] == pytest.approx(155.0 - half)
    assert recipe["wall_s"]["high"] == pytest.approx(155.0 + half)
    # paired by seed: 30, 30, 30 s slower to the end; +0.01, +0.04, +0.01 val
    assert recipe["wall_s_difference"]["mean"] == pytest.approx(30.0) and recipe["wall_s_difference"]["higher"] == 3
    assert recipe["final_val_miou_difference"]["mean"] == pytest.approx(0.02)
    # seed 1 never reached its baseline's final val: no mean is claimed, and the count says why
    assert recipe["time_to_baseline_final"] is None and recipe["time_to_baseline_final_reached"] == 2
    assert baseline["time_to_baseline_final"]["mean"] == pytest.approx(355.0 / 3)
    assert "wall_s_difference" not in baseline


def test_exception_seeds_outside_the_time_to_accuracy_suite_or_repeated():
    assert main(["bench", "--suite", "kernels", "--quick", "--seeds", "0,1"]) != 0
    with pytest.raises(SystemExit):
        main(["bench", "--suite", "time-to-accuracy", "--seeds", "0,0"])


def test_exception_without_camvid_or_with_a_plot_of_another_suite(tmp_path):
    with pytest.raises(ValueError, match="needs --camvid"):
        from warpsense.bench.runner import run_bench

        run_bench(suite="time-to-accuracy")
    assert main(["bench", "--suite", "train", "--quick", "--plot", str(tmp_path / "x.png")]) != 0
