"""A plan's [[search]]: its design space and design names, one-line errors before anything is written, the search's
rounds (warm start, proposals, successive halving over a design's cells, the budget) checked by hand with a stand-in
for training, resumed after Ctrl-C to the same designs, run through the Slurm executor, the report's "search" record
and figure; and the shipped smoke search trained for real, fewer cells than its grid."""

import json
import math
import shutil
from pathlib import Path

import pytest

from tests.study.fakes import FakeTraining, fake_cluster
from warpsense.cli import main
from warpsense.resources import CONFIG_DIR
from warpsense.study import load_plan, study_record, training
from warpsense.study.plan import Plan, PlanError
from warpsense.study.search import SEARCH_RECORD, read_search
from warpsense.study.search_report import plot_search, search_lines

pytest.importorskip("optuna")

TINY = ["train.epochs=1", "train.warmup_epochs=0", "train.eval_every=1", "data.scenes_train=8", "data.scenes_val=4",
        "data.scene_height=32", "data.scene_width=48", "data.crop_height=32", "data.crop_width=48", "data.batch_size=4"]


def _arguments(out: Path, overrides=(), plan: str = "smoke_search") -> list[str]:
    arguments = ["study", "run", plan, "--out", str(out)]
    for text in overrides:
        arguments += ["--set", text]
    return arguments


def _score(config, cell) -> float:
    """A smooth landscape with its top at f/2.8, 10 ms (log scales), seeds 0.002 apart."""
    f, t = config.optics.f_number, config.optics.exposure_ms
    return 0.5 - 0.05 * (math.log(f / 2.8) ** 2 + math.log(t / 10.0) ** 2) + 0.002 * cell.seed


def test_the_design_space_names_and_cells():
    plan = load_plan("smoke_search")
    spec = plan.search
    assert spec.parameters == ("optics.f_number", "optics.exposure_ms") and spec.log == (True, True)
    assert (spec.low, spec.high, spec.labels, spec.budget, spec.seeds) == ((1.4, 1.0), (8.0, 30.0), ("f", "t"), 10, 2)
    assert spec.known == ("start",) and spec.learned == ("learned",) and spec.start == ((2.8, 10.0),)
    assert spec.rounded((1.76349, 14.4449)) == (1.76, 14.4)
    assert spec.rounded((0.5, 99.0)) == (1.4, 30.0)  # clipped to the bounds
    assert spec.camera((1.76, 14.4)) == "search_f1p76_t14p4"
    assert spec.design_values("search_f1p76_t14p4") == (1.76, 14.4)
    for name in ("search_f1p76", "search_f1p763_t14p4", "search_f9_t14", "other_f2_t10", "search_t2_f10"):
        assert spec.design_values(name) is None  # not a design: too few keys, unrounded, outside, other names
    assert spec.rungs(1) == [1, 2] and spec.rungs(5) == [1, 3, 10] and spec.rungs(15) == [1, 3, 9, 30]
    assert spec.design_cost(5) == 10
    assert [[round(v, 3) for v in row] for row in spec.grid_values()] == [[1.4, 2.503, 4.475, 8.0],
                                                                          [1.0, 3.107, 9.655, 30.0]]
    cell = plan.cell("search_f1p76_t14p4/night/1")  # a design's cell resolves from its name (workers, Slurm tasks)
    config = plan.config(cell, "runs")
    assert (config.optics.f_number, config.optics.exposure_ms, config.run.seed) == (1.76, 14.4, 1)
    assert config.photons.analog_gain == 8.0 and config.run.name == "search_f1p76_t14p4.night.seed1"
    with pytest.raises(PlanError, match="no cell 'search_f1p763_t14p4/night/1'"):
        plan.cell("search_f1p763_t14p4/night/1")
    assert [c.id for c in plan.with_designs(["search_f2_t10"]).cells()][-2:] == ["search_f2_t10/night/0",
                                                                                "search_f2_t10/night/1"]
    assert "designs" not in plan.with_designs(["search_f2_t10"]).to_dict()
    assert Plan.from_dict(json.loads(json.dumps(plan.to_dict()))) == plan
    assert load_plan("smoke_search", ["search.budget=4"]).search.budget == 4


def _plan_file(tmp_path: Path, old: str, new: str) -> Path:
    text = (CONFIG_DIR / "studies" / "smoke_search.toml").read_text()
    assert old in text
    path = tmp_path / "plan.toml"
    path.write_text(text.replace(old, new))
    return path


@pytest.mark.parametrize(("old", "new", "message"), [
    ("sampler = \"gp\"", "sampler = \"cma\"", "search[0].sampler: 'cma' is not a sampler; samplers: gp, tpe"),
    ("seed = 0\n", "seed = 0\nwarm = 1\n", "search[0].warm: unknown key"),
    ("\"optics.f_number\" = [1.4, 8.0]", "\"optics.f_number\" = [8.0, 1.4]", "expected [low, high] with low < high"),
    ("\"optics.f_number\" = [1.4, 8.0]", "\"optics.fnumber\" = [1.4, 8.0]", "'optics.fnumber' is not a config key"),
    ("\"optics.f_number\" = [1.4, 8.0]", "\"optics.f_number\" = [1.4, 8.0], \"quantize.bits\" = [8, 12]",
     "'quantize.bits' is not a continuous (float) config key"),
    ("labels = { \"optics.f_number\" = \"f\", ", "labels = { \"optics.f_number\" = \"fp\", ",
     "search[0].labels.optics.f_number: expected a short name of letters"),
    ("labels = { \"optics.f_number\" = \"f\", ", "labels = { ", "search[0].labels.optics.f_number: give a label"),
    ("\"optics.exposure_ms\" = 10.0 }]", "\"optics.exposure_ms\" = 50.0 }]",
     "search[0].start[0].optics.exposure_ms: expected a number within the bounds"),
    ("learned = [\"learned\"]", "learned = [\"start\"]", "search[0].learned: camera 'start' learns none"),
    ("known = [\"start\"]", "known = [\"nope\"]", "search[0].known: 'nope' is not a camera of the plan"),
    ("name = \"start\"                # the reference: f/5.6, 2 ms\nset = [\"optics.f_number=5.6\"",
     "name = \"start\"\nset = [\"optics.f_number=11.0\"", "search[0].known: camera 'start' has optics.f_number = 11.0"),
    ("scene = \"night\"\nbits = 10", "scene = \"night\"\nanalog_gain = 4.0\nbits = 10\nset = [\"optics.f_number=2.0\"]",
     "search[0].bounds.optics.f_number: design search_f1p4_t1 trains with optics.f_number = 2.0"),
    ("budget = 10 ", "budget = 0 ", "search[0].budget: expected an integer >= 1"),
    ("seeds = 2 ", "seeds = 3 ", "search[0].seeds: 3 seeds per design, the study has 2"),
    ("reference = \"start\"", "reference = \"start\"\nsequential = {min_seeds = 2, max_seeds = 3, tolerance = 0.01}",
     "study.sequential: a plan with a [[search]]"),
    ("[[light]]\nname = \"night\"", "[[light]]\nname = \"day\"\nscene = \"day\"\n\n[[light]]\nname = \"night\"",
     "search[0].light: the plan has 2 light levels"),
])
def test_bad_searches_are_one_line_errors_with_nothing_written(tmp_path, old, new, message, capsys):
    out = tmp_path / "study"
    assert main(_arguments(out, plan=str(_plan_file(tmp_path, old, new)))) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and message in error, error
    assert not out.exists()


def test_search_set_without_a_search_is_refused(tmp_path, capsys):
    assert main(_arguments(tmp_path / "s", ["search.budget=3"], plan="smoke")) == 2
    assert "--set search.KEY: the plan has no [[search]] table" in capsys.readouterr().err


def _by_hand(record: dict, scores: dict, reduction: int = 3, margin: float = 0.0) -> None:
    """Each design's rung-1 decision as successive halving takes it, one design at a time: its first cell's score
    ranks among the first cells of the designs before it (batch 1: every earlier design has reached rung 1)."""
    designs = [d for d in record["designs"] if d["state"] != "duplicate"]
    for index, design in enumerate(designs):
        firsts = sorted((scores[f"{d['camera']}/night/0"] for d in designs[:index + 1]), reverse=True)
        mine = scores[f"{design['camera']}/night/0"]
        rank = firsts.index(mine) + 1
        kept = rank <= max(1, math.ceil(len(firsts) / reduction)) or firsts[0] - mine <= margin
        assert design["rungs"][0] == {"cells": 1, "mean": pytest.approx(mine), "rank": rank, "of": len(firsts),
                                      "best": pytest.approx(firsts[0]), "kept": kept}
        assert design["state"] == ("complete" if kept else "pruned")


def test_the_search_warm_starts_prunes_losers_holds_its_budget_and_resumes(tmp_path, monkeypatch, capsys):
    overrides = ["search.budget=12", "search.prune_margin=0.0"]
    fake = FakeTraining(_score)
    monkeypatch.setattr(training, "train_cell", fake)
    out = tmp_path / "whole"
    assert main(_arguments(out, overrides)) == 0
    printed = capsys.readouterr().out
    record = read_search(out)
    designs = record["designs"]
    assert "study: search: design 2 search_f2p8_t10 (2.8, 10) started (start)" in printed
    assert f"cells of a budget of 12; best search_f2p8_t10 {designs[1]['value']:.4f}" in printed
    assert [d["source"] for d in designs[:3]] == ["camera:start", "start", "learned:learned"]
    assert designs[0]["camera"] == "start" and designs[0]["known"] and designs[0]["values"] == [5.6, 2.0]
    assert designs[2]["values"] == [5.04, 2.4]  # the learned camera's end (f x 0.9, t x 1.2 in the stand-in), rounded
    assert all(d["source"] == "sampler" for d in designs[3:]) and len(designs) > 4
    plan = load_plan("smoke_search", overrides)
    # the plan's cells first, then each design's first seed, its second only where it was kept
    assert fake.trained[:4] == [cell.id for cell in plan.cells()]
    scores = {cell_id: _score(plan.config(plan.cell(cell_id), "runs"), plan.cell(cell_id)) for cell_id in fake.trained}
    scores.update({f"start/night/{s}": _score(plan.config(plan.cell(f"start/night/{s}"), "runs"),
                                              plan.cell(f"start/night/{s}")) for s in (0, 1)})
    _by_hand(record, scores)
    trained = {d["camera"]: [c for c in fake.trained if c.startswith(d["camera"] + "/")] for d in designs[1:]}
    for design in designs[1:]:
        assert len(trained[design["camera"]]) == (2 if design["state"] == "complete" else 1)
        if design["state"] == "complete":
            assert design["value"] == pytest.approx((scores[trained[design["camera"]][0]]
                                                    + scores[trained[design["camera"]][1]]) / 2)
    spent = sum(len(cells) for cells in trained.values())
    assert spent <= 12 and spent + 2 > 12  # stopped when the next design would pass the budget
    assert any(d["state"] == "pruned" for d in designs)
    capsys.readouterr()
    assert main(["study", "status", str(out)]) == 0  # the designs' cells trained so far, not only the plan's
    status = capsys.readouterr().out
    assert f"{4 + spent} cells: {4 + spent} done, 0 running, 0 pending, 0 failed" in status
    assert "search_f2p8_t10/night/1" in status

    # the same study interrupted (Ctrl-C in its 7th cell), then run again: the same designs, in the same order
    interrupted = FakeTraining(_score, stop_after=6)
    monkeypatch.setattr(training, "train_cell", interrupted)
    resumed = tmp_path / "resumed"
    assert main(_arguments(resumed, overrides)) == 130
    assert len(interrupted.trained) == 6 and (resumed / SEARCH_RECORD).is_file()
    rest = FakeTraining(_score)
    monkeypatch.setattr(training, "train_cell", rest)
    assert main(_arguments(resumed, overrides)) == 0
    assert interrupted.trained + rest.trained == fake.trained  # nothing trained twice, nothing left out
    assert read_search(resumed) == record
    again = FakeTraining(_score)
    monkeypatch.setattr(training, "train_cell", again)
    assert main(_arguments(resumed, overrides)) == 0 and again.trained == []  # finished: nothing more
    shutil.rmtree(resumed / "runs" / "search_f2p8_t10.night.seed1")  # deleted to retrain it: trained again, alone
    assert main(_arguments(resumed, overrides)) == 0 and again.trained == ["search_f2p8_t10/night/1"]
    assert read_search(resumed) == record

    # the report's search record and figure
    report = study_record(out, resamples=20)
    search = report["search"]
    assert search["cells"] == spent and search["grid_cells"] == 32 and search["grid"]["source"] == "implied"
    assert search["budget"] == 12 and report["missing"] == []
    assert [p["camera"] for p in search["proposals"]] == [d["camera"] for d in designs]
    complete = [d for d in designs if d["state"] == "complete"]
    best = max(complete, key=lambda d: d["value"])
    assert search["best"]["camera"] == best["camera"] and search["best"]["cells"] == (0 if best.get("known") else 2)
    assert search["best"]["miou"]["mean"] == pytest.approx(best["value"])
    assert search["gpu_seconds"] == pytest.approx(5.0 * spent)  # each stand-in run's wall_s
    assert search["grid_gpu_seconds"] == pytest.approx(5.0 * 32) and search["grid_seconds_estimated"]
    assert search["warm_start"] == {"cameras": ["learned"], "cells": 2, "gpu_seconds": 10.0}
    pruned = next(p for p in search["proposals"] if p["state"] == "pruned")
    assert pruned["cells"] == 1 and pruned["miou"]["n"] == 1
    text = "\n".join(search_lines(search))
    assert f"{spent} cells of a budget of 12" in text and "the grid it replaces (implied by the bounds: 4 x 4 points"\
        in text and "32 cells" in text and f"best: {best['camera']}" in text
    assert f"pruned after 1 cell(s), rank {pruned['rungs'][0]['rank']} of {pruned['rungs'][0]['of']}" in text
    assert plot_search(report, tmp_path / "search.png") and (tmp_path / "search.png").stat().st_size > 10_000
    plot = tmp_path / "report.png"
    assert main(["study", "report", str(out), "--plot", str(plot), "--resamples", "20"]) == 0
    assert f"wrote {tmp_path / 'report_search.png'}" in capsys.readouterr().out


def test_the_search_runs_through_the_slurm_executor(tmp_path, monkeypatch, capsys):
    """--executor slurm --wait: each round is one job array; the tasks (submitit's CellTask, here run at once as a
    cluster would) resolve a design's cell from its name alone."""
    fake = FakeTraining(_score)
    monkeypatch.setattr(training, "train_cell", fake)
    arrays = []
    fake_cluster(monkeypatch, arrays)
    out = tmp_path / "study"
    assert main(_arguments(out, ["search.budget=6"]) + ["--executor", "slurm", "--wait"]) == 0
    assert arrays[0] == [cell.id for cell in load_plan("smoke_search").cells()]  # the plan's own cells first
    assert arrays[1] == ["search_f2p8_t10/night/0"] and arrays[2] == ["search_f2p8_t10/night/1"]
    assert sum(len(cells) for cells in arrays[1:]) <= 6
    assert study_record(out, resamples=10)["search"]["cells"] == sum(len(cells) for cells in arrays[1:])


def test_the_smoke_search_trains_fewer_cells_than_its_grid(tmp_path, capsys):
    """The shipped plan trained for real, made tiny (1 epoch on 8 scenes of 32 x 48, one small PSF, a budget of 4
    cells): the mechanics, not its answer (every design scores alike after one epoch). docs/results.md has the plan
    as shipped."""
    lens = json.loads((CONFIG_DIR / "lenses" / "phone_68deg.json").read_text())
    lens.update(psf_grid=[1, 1], psf_kernel_size=7, oversampling=3, pupil_samples=32)  # one small PSF: cheap to render
    (tmp_path / "lens.json").write_text(json.dumps(lens))
    out = tmp_path / "study"
    overrides = [*TINY, "search.budget=4", f'optics.lens="{tmp_path / "lens.json"}"']
    assert main(_arguments(out, overrides)) == 0
    report = tmp_path / "report.json"
    assert main(["study", "report", str(out), "--json", str(report), "--resamples", "20"]) == 0
    search = json.loads(report.read_text())["search"]
    assert 0 < search["cells"] <= 4 < search["grid_cells"] == 32
    assert [p["source"] for p in search["proposals"]][:3] == ["camera:start", "start", "learned:learned"]
    assert search["best"] is not None and search["gpu_seconds"] > 0
    assert [p["state"] for p in search["proposals"]] == ["complete"] * len(search["proposals"])


def test_the_camvid_photon_search_plan(shared_data):
    """The shipped CamVid search: block folds that train on >= 75% of the labelled frames, three searched keys on
    log scales, the preset known, the learned camera and the dark corner tried first, a budget under a quarter of
    the 4 x 4 grid's 240 cells with the learned camera's 15."""
    plan = load_plan("camvid_photon_search", [f'data.root="{shared_data / "camvid"}"'])
    from warpsense.study.plan import fold_sizes

    assert plan.folds == "blocks" and all(row["train"] >= 351 for row in fold_sizes(plan))
    spec = plan.search
    assert spec.parameters == ("optics.f_number", "optics.exposure_ms", "photons.analog_gain") and all(spec.log)
    assert spec.known == ("preset",) and spec.learned == ("learned_from_f2_t10",) and spec.start == ((4.0, 3.0, 8.0),)
    assert spec.rungs(5) == [1, 5] and spec.design_cost(5) == 5
    grid = math.prod(spec.grid_points) * len(plan.fold_names()) * len(plan.seeds)
    learned = sum(cell.camera == "learned_from_f2_t10" for cell in plan.cells())
    assert grid == 240 and spec.budget + learned <= grid / 4
    config = plan.config(plan.cell("search_f1p76_t14p4_g11p3/night/block2/0"), "runs")
    assert (config.optics.f_number, config.optics.exposure_ms, config.photons.analog_gain) == (1.76, 14.4, 11.3)
    assert config.data.holdout_block == 2 and config.optics.corner_speed_px_per_ms == 0.3  # the preset's motion blur
    preset = plan.config(plan.cell("preset/night/block1/0"), "runs")
    assert (preset.optics.f_number, preset.optics.exposure_ms, preset.photons.analog_gain) == (2.0, 10.0, 8.0)


def test_the_designs_are_drawn_over_a_sweeps_map():
    """A plan with a sweep over the search's first two keys: each design sits on the map at its values (grid points
    0, 1 on each axis, log-interpolated between: f/2.8 halfway from f/1.4 to f/5.6), the best starred."""
    from warpsense.study.maps import maps_figure

    interval = {"mean": 0.4, "low": 0.35, "high": 0.45, "n": 2}
    grid = [{"camera": f"map_f{f}_t{t}", "values": [f, t], "miou": {**interval, "mean": 0.3 + 0.01 * i}, "cells": 2}
            for i, (f, t) in enumerate(((1.4, 2.0), (1.4, 20.0), (5.6, 2.0), (5.6, 20.0)))]
    entry = {"split": "val", "sweep": "map", "light": "night", "parameters": ["optics.f_number", "optics.exposure_ms"],
             "labels": ["f", "t"], "values": [[1.4, 5.6], [2.0, 20.0]], "grid": grid, "learned": [], "folds": "none",
             "best": {"camera": grid[3]["camera"], "values": [5.6, 20.0], "miou": grid[3]["miou"], "tied": []},
             "cost": {"points": 4, "runs": 8, "run_s": None}}
    proposals = [{"number": 1, "camera": "search_f2p8_t6p32", "values": {"optics.f_number": 2.8,
                                                                         "optics.exposure_ms": 6.32},
                  "state": "complete", "rungs": [], "miou": interval},
                 {"number": 2, "camera": "search_f1p4_t20", "values": {"optics.f_number": 1.4,
                                                                       "optics.exposure_ms": 20.0},
                  "state": "pruned", "rungs": [{"cells": 1, "mean": 0.2}], "miou": None}]
    search = {"parameters": ["optics.f_number", "optics.exposure_ms"], "light": "night", "split": "val",
              "proposals": proposals, "best": {"camera": "search_f2p8_t6p32"}}
    figure = maps_figure({"study": "s", "maps": [entry], "search": search})
    axis = figure.axes[0]
    drawn = {line.get_marker(): (float(line.get_xdata()[0]), float(line.get_ydata()[0])) for line in axis.lines}
    assert drawn["*"] == pytest.approx((0.5, 0.5), abs=2e-3) and drawn["x"] == pytest.approx((0.0, 1.0))
    assert sorted(text.get_text() for text in axis.texts if text.get_text() in ("1", "2")) == ["1", "2"]
    import matplotlib.pyplot as plt

    plt.close(figure)
    other = maps_figure({"study": "s", "maps": [entry], "search": {**search, "light": "day"}})
    assert not [line for line in other.axes[0].lines if line.get_marker() in ("*", "x")]  # another light: not drawn
    plt.close(other)
