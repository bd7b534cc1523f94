"""The designer's map: [[sweep]] tables in study plans (their cameras, names and errors), the map's statistics and
learned paths against a hand computation on fabricated runs, and the smoke map study run and reported on the CPU."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from warpsense.cli import main
from warpsense.study import load_plan, render_text
from warpsense.study.maps import map_path, plot_maps, trajectory
from warpsense.study.plan import Plan, PlanError, value_label
from warpsense.study.report import study_record
from warpsense.study.study_dir import record_plan, run_dir

PHOTONS = ('set = ["data.scenes_train=8", "data.scenes_val=4", "optics.enabled=true", "optics.normalize_mean=0.0", '
           '"exposure.enabled=false", "cfa.mode=\\"fixed\\"", "noise.enabled=false", "photons.enabled=true"]\n')
LIGHT = '\n[[light]]\nname = "night"\nscene = "night"\nanalog_gain = 8.0\n'
SWEEP = '''
[[sweep]]
name = "map"
grid = { "optics.f_number" = [1.4, 4.0], "optics.exposure_ms" = [3.0, 30.0] }
labels = { "optics.f_number" = "f", "optics.exposure_ms" = "t" }
'''
LEARNED = '''
[[camera]]
name = "learned"
set = ["optics.f_number=4.0", "optics.f_number_learnable=true"]
'''


def _plan(tmp_path: Path, body: str = SWEEP + LEARNED, reference: str = "map_f1p4_t30", study: str = "") -> Path:
    path = tmp_path / "plan.toml"
    path.write_text(f'[study]\nname = "m"\nbase = ""\n{PHOTONS}seeds = [0, 1]\nreference = "{reference}"\n{study}'
                    + body + LIGHT)
    return path


def test_value_labels_keep_names_plain():
    assert [value_label(v) for v in (1.4, 30.0, 2, -0.5, 1e-6, True, "RCCB")] == [
        "1p4", "30", "2", "m0p5", "1em06", "true", "RCCB"]


def test_a_sweep_is_the_grids_product_crossed_like_cameras(tmp_path, capsys):
    plan = load_plan(_plan(tmp_path))
    names = ["learned", "map_f1p4_t3", "map_f1p4_t30", "map_f4_t3", "map_f4_t30"]
    assert [camera.name for camera in plan.cameras] == names
    assert plan.reference == "map_f1p4_t30"  # the reference may be a grid point
    assert [cell.id for cell in plan.cells()] == [f"{name}/night/{seed}" for seed in (0, 1) for name in names]
    config = plan.config(plan.cell("map_f1p4_t30/night/1"), tmp_path)
    assert (config.optics.f_number, config.optics.exposure_ms, config.run.seed) == (1.4, 30.0, 1)
    assert config.run.name == "map_f1p4_t30.night.seed1"
    sweep = plan.sweeps[0]
    assert sweep.parameters == ("optics.f_number", "optics.exposure_ms") and sweep.labels == ("f", "t")
    assert sweep.points[1] == ("map_f1p4_t30", (1.4, 30.0))
    # plan.json keeps where the cameras came from; a plan without sweeps records as before
    assert Plan.from_dict(json.loads(json.dumps(plan.to_dict()))) == plan
    assert "sweeps" not in load_plan("smoke").to_dict()
    # default labels: the key's last part; a [sweep.grid] sub-table names the same keys
    body = '\n[[sweep]]\nname = "g"\n[sweep.grid.optics]\nf_number = [2.0]\nexposure_ms = [10.0, 20.0]\n'
    plan = load_plan(_plan(tmp_path, body, reference="g_f_number2_exposure_ms10"))
    assert [c.name for c in plan.cameras] == ["g_f_number2_exposure_ms10", "g_f_number2_exposure_ms20"]
    assert main(["study", "run", str(tmp_path / "plan.toml"), "--out", str(tmp_path / "s"), "--plan-only"]) == 0
    assert "--cell g_f_number2_exposure_ms20/night/1" in capsys.readouterr().out
    assert not (tmp_path / "s").exists()
    with pytest.raises(PlanError, match=r"camera: at least one \[\[camera\]\] or \[\[sweep\]\] table is needed"):
        load_plan(_plan(tmp_path, ""))


@pytest.mark.parametrize(("body", "message"), [
    (SWEEP.replace("optics.f_number\" = [", "optics.f_numbr\" = ["), "sweep[0].grid.optics.f_numbr: "
     "'optics.f_numbr' is not a config key"),
    (SWEEP.replace("[1.4, 4.0]", "[]"), "sweep[0].grid.optics.f_number: expected a non-empty list of values"),
    (SWEEP.replace("[1.4, 4.0]", "1.4"), "sweep[0].grid.optics.f_number: expected a non-empty list of values, got 1.4"),
    (SWEEP.replace("[1.4, 4.0]", "[1.4, 1.4]"), "sweep[0].grid.optics.f_number: expected distinct numbers"),
    (SWEEP.replace("[1.4, 4.0]", "[2.0, 2]"), "sweep[0].labels: points (2.0, 3.0) and (2, 3.0) are both named "
     "'map_f2_t3'"),
    (SWEEP.replace('"optics.exposure_ms" = "t"', '"optics.exposure" = "t"'), "sweep[0].labels.optics.exposure: not "
     "a key of the grid"),
    (SWEEP.replace('name = "map"', 'name = "map"\nsteps = 3'), "sweep[0].steps: unknown key"),
    (SWEEP.replace('grid = {', 'xgrid = {'), "sweep[0].xgrid: unknown key"),
    (SWEEP + '\n[[camera]]\nname = "map_f4_t3"\n', "camera.name: duplicate name 'map_f4_t3' (also a [[camera]] or "
     "another sweep's point)"),
    (SWEEP + SWEEP, "sweep.name: duplicate name 'map'"),
    (SWEEP.replace('name = "map"', 'name = "m.ap"'), "sweep.name: 'm.ap' must be a plain name"),
    (SWEEP.replace('name = "map"', 'name = "m"') + SWEEP.replace('name = "map"', 'name = "m_f1p4"').replace(
        '"optics.f_number" = [1.4, 4.0], ', '').replace('"optics.f_number" = "f", ', ''), "camera.name: duplicate "
     "name 'm_f1p4_t3' (also a [[camera]] or another sweep's point)"),
    (SWEEP.replace("[3.0, 30.0]", "[-5.0]"), "optics.exposure_ms"),  # the config's own check, at the point
])
def test_bad_sweeps_are_one_line_errors_with_nothing_written(tmp_path, body, message, capsys):
    plan = _plan(tmp_path, body, reference="map_f4_t3" if "[-5.0]" not in body else "map_f4_tm5")
    out = tmp_path / "study"
    assert main(["study", "run", str(plan), "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and str(plan) in error and message in error, error
    assert not out.exists()


def _fabricate(study_dir: Path, plan, scores: dict, paths: dict) -> None:
    """Finished runs without training: each cell's evaluation.json (its mIoU from ``scores[camera][(fold, seed)]``),
    and for the learned camera its metrics.jsonl (f-number per epoch from ``paths``) and config.json."""
    record_plan(plan, study_dir)
    classes = ["sky", "road"]
    for cell in plan.cells():
        directory = run_dir(study_dir, cell)
        directory.mkdir(parents=True)
        miou = scores[cell.camera][(cell.fold, cell.seed)]
        split = {"miou": miou, "per_class_iou": {"sky": miou, "road": miou}, "image_sequences": [cell.fold] * 2,
                 "image_counts": [[[10, 5, 5], [10, 5, 5]], [[10, 5, 5], [10, 5, 5]]]}
        (directory / "evaluation.json").write_text(json.dumps(
            {"epoch": 2, "network_parameters": 10, "camera": {}, "class_names": classes, "splits": {"heldout": split},
             "holdout_sequence": cell.fold}))
        config = plan.config(cell, study_dir / "runs").to_dict()
        (directory / "config.json").write_text(json.dumps(config))
        records = [{"epoch": epoch, "wall_s": 10.0 * (epoch + 1), **({"f_number": f} if cell.camera == "learned"
                                                                      else {})}
                   for epoch, f in enumerate(paths[(cell.fold, cell.seed)])]
        (directory / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_the_map_statistics_and_paths_by_hand(tmp_path):
    plan = load_plan(_plan(tmp_path), ["study.folds=sequence"])
    assert plan.sequences == ("train0", "val0")
    keys = [(fold, seed) for fold in ("train0", "val0") for seed in (0, 1)]
    base = {"map_f1p4_t3": 0.40, "map_f1p4_t30": 0.50, "map_f4_t3": 0.30, "map_f4_t30": 0.45, "learned": 0.47}
    offsets = {("train0", 0): 0.00, ("train0", 1): 0.02, ("val0", 0): -0.04, ("val0", 1): 0.01}
    scores = {camera: {key: value + offsets[key] for key in keys} for camera, value in base.items()}
    paths = {key: [4.0, 3.0 - n * 0.1, 2.5 - n * 0.1] for n, key in enumerate(keys)}
    study = tmp_path / "study"
    _fabricate(study, plan, scores, paths)

    record = study_record(study, resamples=20, block=2)
    [entry] = record["maps"]
    assert (entry["split"], entry["sweep"], entry["light"]) == ("heldout", "map", "night")
    assert entry["parameters"] == ["optics.f_number", "optics.exposure_ms"]
    assert entry["values"] == [[1.4, 4.0], [3.0, 30.0]]
    # the best point's interval by hand: the t interval (1 degree of freedom) over the two folds' means
    best = entry["best"]
    assert best["camera"] == "map_f1p4_t30" and best["values"] == [1.4, 30.0]
    fold_means = [0.50 + (offsets[(f, 0)] + offsets[(f, 1)]) / 2 for f in ("train0", "val0")]
    half = stats.t.ppf(0.975, 1) * np.std(fold_means, ddof=1) / math.sqrt(2)
    mean = 0.50 + np.mean(list(offsets.values()))
    assert best["miou"]["mean"] == pytest.approx(mean) and best["miou"]["folds"] == 2 and best["miou"]["n"] == 4
    assert (best["miou"]["low"], best["miou"]["high"]) == pytest.approx((mean - half, mean + half))
    grid = {point["camera"]: point for point in entry["grid"]}
    assert grid["map_f4_t3"]["values"] == [4.0, 3.0] and grid["map_f4_t3"]["miou"]["mean"] == pytest.approx(mean - 0.2)
    assert grid["map_f4_t3"]["cells"] == 4
    # the learned design: its score beside the best's, inside the best's interval (0.03 below, the half-width is wider)
    [learned] = entry["learned"]
    assert learned["camera"] == "learned" and learned["learns"] == ["optics.f_number"]
    assert learned["difference_to_best"] == pytest.approx(-0.03) and half > 0.03
    assert learned["inside_best_interval"] is True
    run = next(r for r in learned["runs"] if r["cell"] == "learned/night/val0/1")
    # the path: the config's start, then each epoch's learned f-number; the exposure it does not learn stays put
    assert run["epochs"] == [None, 0, 1, 2]
    assert run["path"] == [[4.0, 10.0], [4.0, 10.0], [2.7, 10.0], [2.2, 10.0]]
    assert run["miou"] == pytest.approx(0.47 + offsets[("val0", 1)])
    assert entry["cost"] == {"points": 4, "runs": 16, "run_s": pytest.approx(16 * 30.0)}
    assert learned["cost"] == {"runs": 4, "run_s": pytest.approx(4 * 30.0)}

    text = render_text(record)
    assert "map of sweep 'map' at night" in text and f"*{mean:.4f} [{mean - half:.4f}, {mean + half:.4f}]" in text
    assert "inside the best point's interval" in text and "optics.f_number 4 -> 2.2" in text
    assert "cost: grid 4 points, 16 runs, 480 s; learned design 'learned' 4 runs, 120 s" in text
    # sequence folds: the means are over (fold, seed) cells; the learned camera is named once, as a design
    assert "map of sweep 'map' at night: mIoU mean over (fold, seed) [95% interval]" in text
    assert "learned design 'learned' (learns optics.f_number): " in text and "learned learned" not in text
    assert plot_maps(record, tmp_path / "map.png") and (tmp_path / "map.png").stat().st_size > 10_000

    # a learned design outside the best's interval
    scores["learned"] = {key: 0.30 + offsets[key] for key in keys}
    for cell in plan.cells():
        if cell.camera == "learned":
            path = run_dir(study, cell) / "evaluation.json"
            evaluation = json.loads(path.read_text())
            evaluation["splits"]["heldout"]["miou"] = scores["learned"][(cell.fold, cell.seed)]
            path.write_text(json.dumps(evaluation))
    [entry] = study_record(study, resamples=20, block=2)["maps"]
    assert entry["learned"][0]["inside_best_interval"] is False
    assert entry["learned"][0]["difference_to_best"] == pytest.approx(-0.20)


def test_a_trajectory_needs_recorded_epochs(tmp_path):
    config = {"optics": {"f_number": 2.0, "f_number_learnable": True, "exposure_ms": 10.0}}
    assert trajectory(tmp_path, ["optics.f_number"], config) is None  # no metrics.jsonl yet
    (tmp_path / "metrics.jsonl").write_text('{"epoch": 0, "f_number": 1.9}\n{"epoch": 1, "f_number": 1.8}\n'
                                            '{"epoch": 1, "f_number": 1.7}\n')  # a resumed run repeats epoch 1
    assert trajectory(tmp_path, ["optics.f_number"], config) == {"epochs": [None, 0, 1], "path": [[2.0], [1.9], [1.7]]}
    assert map_path("out/report.png") == Path("out/report_map.png")


def test_the_smoke_map_runs_and_reports_its_map(tmp_path, capsys):
    """The mechanics only (one seed, 2 epochs: too short to learn); tests/test_tutorial.py runs the plan as shipped
    and checks that its map is not flat."""
    out = tmp_path / "study"
    assert main(["study", "run", "smoke_map", "--out", str(out), "--set", "study.seeds=[0]", "--set",
                 "train.epochs=2", "--set", "train.eval_every=2", "--set", "data.scenes_train=16", "--set",
                 "data.scenes_val=4"]) == 0
    report, plot = tmp_path / "report.json", tmp_path / "report.png"
    assert main(["study", "report", str(out), "--json", str(report), "--plot", str(plot), "--resamples", "20"]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {tmp_path / 'report_map.png'}" in printed and "map of sweep 'map' at night" in printed
    # no folds: the means are over seeds; one run is "1 run"
    assert "map of sweep 'map' at night: mIoU mean over seeds [95% interval]" in printed
    assert "; learned design 'learned' 1 run, " in printed and "learned learned" not in printed
    assert (tmp_path / "report_map.png").stat().st_size > 10_000
    [entry] = json.loads(report.read_text())["maps"]
    assert entry["parameters"] == ["optics.f_number", "optics.exposure_ms"]
    assert [point["camera"] for point in entry["grid"]] == ["map_f1p4_t2", "map_f1p4_t20", "map_f5p6_t2",
                                                             "map_f5p6_t20"]
    assert all(point["miou"]["n"] == 1 for point in entry["grid"])
    [learned] = entry["learned"]
    assert learned["learns"] == ["optics.f_number", "optics.exposure_ms"]
    [run] = learned["runs"]
    assert run["epochs"] == [None, 0, 1] and run["path"][0] == [5.6, 2.0]
    assert all(1.4 <= f <= 8.0 and 1.0 <= t <= 30.0 for f, t in run["path"])


def test_a_one_key_sweep_is_a_curve_with_the_learned_path_at_its_score(tmp_path):
    body = ('\n[[sweep]]\nname = "t"\ngrid = { "optics.exposure_ms" = [3.0, 30.0] }\n'
            '\n[[camera]]\nname = "learned"\nset = ["optics.exposure_learnable=true"]\n'
            '\n[[camera]]\nname = "fixed"\nset = []\n')
    plan = load_plan(_plan(tmp_path, body, reference="t_exposure_ms3"))
    keys = [("", 0), ("", 1)]
    scores = {"t_exposure_ms3": {("", 0): 0.2, ("", 1): 0.3}, "t_exposure_ms30": {("", 0): 0.5, ("", 1): 0.6},
              "learned": {("", 0): 0.4, ("", 1): 0.4}, "fixed": {("", 0): 0.1, ("", 1): 0.1}}
    _fabricate(tmp_path / "study", plan, scores, {key: [12.0, 14.0] for key in keys})
    for seed in (0, 1):  # the learned exposure time in every epoch's record (a record without it is refused)
        (tmp_path / "study" / "runs" / f"learned.night.seed{seed}" / "metrics.jsonl").write_text(
            '{"epoch": 0, "exposure_ms": 12.0}\n{"epoch": 1, "exposure_ms": 14.0}\n')
    record = study_record(tmp_path / "study", resamples=20, block=2)
    [entry] = record["maps"]
    assert entry["labels"] == ["exposure_ms"] and entry["best"]["camera"] == "t_exposure_ms30"
    assert [x["camera"] for x in entry["learned"]] == ["learned"]  # "fixed" learns no swept key
    half = stats.t.ppf(0.975, 1) * np.std([0.5, 0.6], ddof=1) / math.sqrt(2)
    assert (entry["best"]["miou"]["low"], entry["best"]["miou"]["high"]) == pytest.approx((0.55 - half, 0.55 + half))
    learned = entry["learned"][0]
    assert half > 0.15 and learned["inside_best_interval"] is True and learned["runs"][0]["path"] == [
        [10.0], [12.0], [14.0]]
    assert "t_exposure_ms30  optics.exposure_ms 30: *0.5500" in render_text(record)
    assert plot_maps(record, tmp_path / "curve.png") and (tmp_path / "curve.png").stat().st_size > 10_000


def _plot_texts(record: dict, path: Path, monkeypatch) -> list[tuple[str, list[str]]]:
    """`plot_maps`'s figure as written: per map axis, its title and legend entries."""
    import matplotlib.figure

    texts, save = [], matplotlib.figure.Figure.savefig

    def saving(figure, *args, **kwargs):
        for axis in figure.axes:
            if axis.get_title():
                legend = axis.get_legend()
                texts.append((axis.get_title(), [t.get_text() for t in legend.get_texts()] if legend else []))
        return save(figure, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", saving)
    assert plot_maps(record, path) and path.stat().st_size > 10_000
    return texts


def test_a_flat_map_names_no_best_point(tmp_path, monkeypatch):
    """Every point at the same mean (runs too short to learn, as in a smoke run): the report, the plot's title and
    its legend say that the points tie and that no point is best, instead of starring whichever came first (or
    titling "best None")."""
    body = ('\n[[sweep]]\nname = "t"\ngrid = { "optics.exposure_ms" = [3.0, 10.0, 30.0] }\n'
            '\n[[camera]]\nname = "learned"\nset = ["optics.exposure_learnable=true"]\n')
    plan = load_plan(_plan(tmp_path, body, reference="t_exposure_ms3"))
    keys = [("", 0), ("", 1)]
    flat = {("", 0): 0.0005, ("", 1): 0.0005}
    _fabricate(tmp_path / "study", plan, {"t_exposure_ms3": flat, "t_exposure_ms10": flat, "learned": flat,
                                          "t_exposure_ms30": {("", 0): 0.0004, ("", 1): 0.0005}},
               {key: [12.0, 14.0] for key in keys})
    for seed in (0, 1):
        (tmp_path / "study" / "runs" / f"learned.night.seed{seed}" / "metrics.jsonl").write_text(
            '{"epoch": 0, "exposure_ms": 10.0}\n{"epoch": 1, "exposure_ms": 10.0}\n')
    record = study_record(tmp_path / "study", resamples=20, block=2)
    [entry] = record["maps"]
    assert entry["best"]["tied"] == ["t_exposure_ms3", "t_exposure_ms10"]
    [learned] = entry["learned"]
    assert learned["inside_best_interval"] is None  # no best point, so no best point's interval to be inside
    text = render_text(record)
    assert "best: none, 2 points tie at 0.0005 (t_exposure_ms3, t_exposure_ms10)" in text and ": *0." not in text
    assert ("learned design 'learned' (learns optics.exposure_ms): 0.0005 [0.0005, 0.0005] (n=2, too few), +0.0000 "
            "to the tied points; no point is best: the grid ties") in text
    assert "map of sweep 't' at night: mIoU mean over seeds [95% interval]" in text  # a plan without folds
    [(title, legend)] = _plot_texts(record, tmp_path / "flat.png", monkeypatch)
    assert title == "t at night (heldout): no best point, 2 points tie at 0.001" and "None" not in title
    assert legend == ["learned: 0.001 (no point is best: the grid ties)"]


def test_the_plot_names_the_best_point_and_the_learned_designs_place(tmp_path, monkeypatch):
    plan = load_plan(_plan(tmp_path))
    keys = [("", 0), ("", 1)]
    base = {"map_f1p4_t3": 0.40, "map_f1p4_t30": 0.50, "map_f4_t3": 0.30, "map_f4_t30": 0.45, "learned": 0.20}
    scores = {camera: {("", 0): value, ("", 1): value + 0.02} for camera, value in base.items()}
    _fabricate(tmp_path / "study", plan, scores, {key: [4.0, 3.0, 2.5] for key in keys})
    record = study_record(tmp_path / "study", resamples=20, block=2)
    [(title, legend)] = _plot_texts(record, tmp_path / "map.png", monkeypatch)
    assert title == "map at night (heldout): best map_f1p4_t30 0.510"
    assert legend == ["learned: 0.210 (outside the best point's interval)"]
