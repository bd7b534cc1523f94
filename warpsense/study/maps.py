"""The camera designer's map: per ``[[sweep]]`` of a study plan, light level and split, the score of every grid point
(mean over (fold, seed) cells, over seeds in a plan without folds, with the groups' interval,
`warpsense.study.statistics.fold_interval`), the best point (none where the best mean is tied), and each learned
design's path through the same parameters over its epochs, with its final score beside the grid's.

A camera is drawn on a sweep's map when its config learns at least one of the swept keys (`LEARNED_KEYS`); a swept
key it does not learn stays at its config value along the path. The path starts at the config's value and then
follows the learned values each epoch's record of the run's metrics.jsonl holds (`Camera.summary`).

`design_maps` builds the JSON-ready record (the report's ``maps``), `map_lines` its console text and `plot_maps` the
figure (a curve for one swept key, a heatmap for two; grids of more keys are in the text and JSON only).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from warpsense.study.keys import LEARNED_KEYS  # swept key -> (its learnable flag, its learned value's key)
from warpsense.study.plan import Plan, PlanError
from warpsense.study.statistics import bounded, interval_text
from warpsense.study.study_dir import StudyDir, read_record
from warpsense.train.run_dir import RunDir


def _lookup(config: dict, key: str):
    section, _, name = key.partition(".")
    return config.get(section, {}).get(name)


def learned_parameters(config: dict, parameters) -> list[str]:
    """The swept ``parameters`` a run's resolved ``config`` (`RunDir.CONFIG`) learns."""
    return [key for key in parameters if key in LEARNED_KEYS and _lookup(config, LEARNED_KEYS[key][0]) is True]


def trajectory(directory: Path, parameters, config: dict) -> dict | None:
    """A learned run's path through ``parameters``: its start (the config's values) and each epoch's values.

    Args:
        directory: the run directory (its metrics, `RunDir.METRICS`).
        parameters: the sweep's keys.
        config: the run's resolved config.

    Returns:
        {"epochs": [None (the start), 0, 1, ...], "path": [[value per parameter], ...]}, or None when a coordinate
        is unknown (a fixed key that is not a number, or no epoch recorded yet).
    """
    learned = set(learned_parameters(config, parameters))
    by_epoch = {}
    for record in RunDir(directory).read_metrics():  # a resumed run may repeat an epoch: its last record counts
        if "epoch" in record:
            by_epoch[record["epoch"]] = record
    if not by_epoch:
        return None
    epochs, path = [], []
    for epoch, record in [(None, None), *sorted(by_epoch.items())]:
        point = []
        for key in parameters:
            value = _lookup(config, key)
            if key in learned and record is not None:
                value = _learned_value(directory, epoch, record, key)
            elif key in learned and not value:  # f_number 0: the lens file's, known from the first record
                value = _learned_value(directory, min(by_epoch), by_epoch[min(by_epoch)], key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                return None
            point.append(float(value))
        epochs.append(epoch)
        path.append(point)
    return {"epochs": epochs, "path": path}


def _learned_value(directory: Path, epoch: int, record: dict, key: str) -> float:
    """The learned value of swept ``key`` in a run's metrics record of ``epoch``; a one-line PlanError naming the
    file, epoch and field where it is missing or not a finite number (a damaged record: the path would otherwise
    be left off the map without a word)."""
    field = LEARNED_KEYS[key][1]
    value = record.get(field)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise PlanError(f"{RunDir(directory).metrics}: epoch {epoch}: {field}: expected the learned value (a finite "
                        f"number), got {value!r}")
    return value


def _read_config(path: Path) -> dict:
    """A finished run's config (`RunDir.CONFIG`), its sections objects; a one-line PlanError naming the file and
    section where it is missing or damaged: a learned camera is never left off a map without a word."""
    config = read_record(path, dict)
    for section, value in config.items():
        if not isinstance(value, dict):
            raise PlanError(f"{path}: [{section}]: expected an object of keys, got {value!r}")
    return config


def _inside(interval: dict | None, value: float | None) -> bool | None:
    if interval is None or interval["low"] is None or value is None:
        return None
    return bool(interval["low"] <= value <= interval["high"])


def _cost(groups: list[dict]) -> dict:
    """Runs and measured wall seconds (summed over the timed runs) of ``groups``."""
    timed = [g for g in groups if g.get("run_s") is not None]
    return {"runs": sum(g["cells"] for g in groups),
            "run_s": float(sum(g["run_s"] * g["timed_runs"] for g in timed)) if timed else None}


def design_maps(study_dir: str | Path, plan: dict, cells: list[dict], splits: dict) -> list[dict]:
    """The report's ``maps``: one per sweep, light level and split with a scored grid point.

    Args:
        study_dir: the study directory (the learned runs' metrics and configs).
        plan: the study's plan.json.
        cells: the report's evaluated cells (`warpsense.study.report.study_record`'s ``cells``).
        splits: the report's per-split records (their ``groups``: mean mIoU with its interval per camera and light).

    Returns:
        Per map: split, sweep, light, parameters (the swept keys), labels, values (per key), grid (per point: camera,
        values, miou interval or None, cells), best (the grid point of highest mean; ``tied``: the points that share
        that mean where more than one does, and then no point is the best), learned (per learned camera: its learned
        keys, miou interval, difference to the best mean, whether its mean lies inside the best point's interval
        (None without one, or where the points tie), and per run its trajectory and final score), cost (runs and
        seconds of the grid and of each learned camera) and folds (the plan's: "blocks", "sequence" or "none").
    """
    study_dir, plan_spec = Path(study_dir), Plan.from_dict(plan)
    swept = {camera for sweep in plan_spec.sweeps for camera, _ in sweep.points}
    finished = {cell["cell"]: cell for cell in cells}
    configs: dict[str, dict | None] = {}  # per camera: the config of one of its finished runs
    for cell in plan_spec.cells():
        if cell.camera not in swept and cell.id in finished and configs.get(cell.camera) is None:
            configs[cell.camera] = _read_config(StudyDir(study_dir).run(cell).config)
    maps = []
    for sweep in plan_spec.sweeps:
        for light in plan_spec.lights:
            for split, part in splits.items():
                groups = {g["camera"]: g for g in part["groups"] if g["light"] == light.name}
                grid = [{"camera": camera, "values": list(values),
                         "miou": groups[camera]["miou"] if camera in groups else None,
                         "cells": groups[camera]["cells"] if camera in groups else 0}
                        for camera, values in sweep.points]
                scored = [point for point in grid if point["miou"] is not None]
                if not scored:
                    continue
                best = max(scored, key=lambda point: point["miou"]["mean"])
                # points at the best mean (a flat map, e.g. runs too short to learn): none of them is "the best"
                tied = [point["camera"] for point in scored if point["miou"]["mean"] == best["miou"]["mean"]]
                tied = tied if len(tied) > 1 else []
                learned = []
                for camera in plan_spec.cameras:
                    config = configs.get(camera.name)
                    keys = learned_parameters(config, sweep.parameters) if config else []
                    if camera.name in swept or not keys or camera.name not in groups:
                        continue
                    runs = []
                    for cell in plan_spec.cells():
                        if cell.camera != camera.name or cell.light != light.name or cell.id not in finished:
                            continue
                        run = StudyDir(study_dir).run(cell)
                        path = trajectory(run.path, sweep.parameters, _read_config(run.config))
                        if path is not None:
                            runs.append({"cell": cell.id, "fold": cell.fold, "seed": cell.seed,
                                         "miou": finished[cell.id]["miou"].get(split), **path})
                    score = groups[camera.name]["miou"]
                    learned.append({"camera": camera.name, "learns": keys, "miou": score,
                                    "difference_to_best": score["mean"] - best["miou"]["mean"],
                                    "inside_best_interval": None if tied else _inside(best["miou"], score["mean"]),
                                    "runs": runs,
                                    "cost": _cost([groups[camera.name]])})
                maps.append({"split": split, "sweep": sweep.name, "light": light.name,
                             "parameters": list(sweep.parameters), "labels": list(sweep.labels),
                             "values": [list(v) for v in sweep.values], "grid": grid,
                             "best": {"camera": best["camera"], "values": best["values"], "miou": best["miou"],
                                      "tied": tied},
                             "learned": learned,
                             "cost": {"points": len(grid), **_cost([groups[p["camera"]] for p in scored])},
                             "folds": plan.get("folds", "none")})
    return maps


def _point(parameters, values) -> str:
    return ", ".join(f"{key} {value:g}" if isinstance(value, float) else f"{key} {value}"
                     for key, value in zip(parameters, values))


def _seconds(cost: dict) -> str:
    return "" if cost["run_s"] is None else f", {cost['run_s']:.0f} s"


def _runs(count: int) -> str:
    return f"{count} run" if count == 1 else f"{count} runs"


def _over(entry: dict) -> str:
    """What a map's means are over: (fold, seed) cells with sequence folds, seeds without."""
    return "(fold, seed)" if entry.get("folds", "none") != "none" else "seeds"


def _comparison(learned: dict, tied: list) -> str:
    """Where a learned design's mean lies against the best point's interval, in words."""
    if tied:
        return "no point is best: the grid ties"
    return {True: "inside the best point's interval", False: "outside the best point's interval",
            None: "the best point has no interval"}[learned["inside_best_interval"]]


def map_lines(maps: list[dict], level: str = "95%") -> list[str]:
    """The console text of the report's ``maps``: the grid (a table for two keys), the best point, each learned
    design's path (start -> end per run) and score beside the best point's, and what each cost."""
    lines = []
    for entry in maps:
        parameters, grid = entry["parameters"], entry["grid"]
        lines.append(f"\n[{entry['split']}] map of sweep {entry['sweep']!r} at {entry['light']}: mIoU mean over "
                     f"{_over(entry)} [{level} interval] per point of {' x '.join(parameters)}; * the best")
        tied = entry["best"].get("tied", [])
        cells = {tuple(map(repr, p["values"])): ("*" if p["camera"] == entry["best"]["camera"] and not tied else "") +
                 interval_text(p["miou"]) for p in grid}
        if len(parameters) == 2:
            rows, columns = entry["values"]
            heads = [f"{entry['labels'][1]}{c:g}" if isinstance(c, float) else f"{entry['labels'][1]}{c}"
                     for c in columns]
            names = [f"{entry['labels'][0]}{r:g}" if isinstance(r, float) else f"{entry['labels'][0]}{r}" for r in rows]
            table = [[cells[(repr(r), repr(c))] for c in columns] for r in rows]
            widths = [max(len(h), *(len(row[i]) for row in table)) for i, h in enumerate(heads)]
            name_width = max(len(n) for n in names)
            lines.append(f"  {'':<{name_width}s}  " + "  ".join(f"{h:>{w}s}" for h, w in zip(heads, widths)))
            lines += [f"  {n:<{name_width}s}  " + "  ".join(f"{c:>{w}s}" for c, w in zip(row, widths))
                      for n, row in zip(names, table)]
        else:
            width = max(len(p["camera"]) for p in grid)
            lines += [f"  {p['camera']:<{width}s}  {_point(parameters, p['values'])}: "
                      f"{cells[tuple(map(repr, p['values']))]}" for p in grid]
        best = entry["best"]
        if tied:
            lines.append(f"  best: none, {len(tied)} points tie at {best['miou']['mean']:.4f} ({', '.join(tied)}): "
                         "the map is flat (too few epochs to tell the points apart?)")
        else:
            lines.append(f"  best: {best['camera']} ({_point(parameters, best['values'])}): "
                         f"{interval_text(best['miou'])}")
        for learned in entry["learned"]:
            lines.append(f"  learned design {learned['camera']!r} (learns {', '.join(learned['learns'])}): "
                         f"{interval_text(learned['miou'])}, {learned['difference_to_best']:+.4f} to the "
                         f"{'tied points' if tied else 'best'}; {_comparison(learned, tied)}")
            for run in learned["runs"]:
                moves = ", ".join(f"{key} {start:.3g} -> {end:.3g}" for key, start, end in
                                  zip(parameters, run["path"][0], run["path"][-1]))
                score = "-" if run["miou"] is None else f"{run['miou']:.4f}"
                lines.append(f"    {run['cell']}: {moves} ({len(run['path']) - 1} epochs); mIoU {score}")
        cost = entry["cost"]
        learned_cost = "; ".join(f"learned design {x['camera']!r} {_runs(x['cost']['runs'])}{_seconds(x['cost'])}"
                                 for x in entry["learned"])
        lines.append(f"  cost: grid {cost['points']} points, {_runs(cost['runs'])}{_seconds(cost)}"
                     + (f"; {learned_cost}" if learned_cost else ""))
    return lines


def _positions(values: list):
    """A function from a parameter's value to its position on the map's axis (grid point i at i), interpolated
    between grid points on a log scale where every value is positive (linearly otherwise) and extrapolated past
    the ends; None where the values are not numbers (no path can be placed)."""
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return None
    log = all(v > 0 for v in values)
    scale = (lambda v: math.log(v)) if log else float
    points = sorted((scale(v), i) for i, v in enumerate(values))

    def position(value: float) -> float:
        if len(points) == 1 or (log and value <= 0):
            return float(points[0][1])
        x = scale(value)
        k = next((k for k in range(1, len(points) - 1) if x < points[k][0]), len(points) - 1)
        (x0, i0), (x1, i1) = points[k - 1], points[k]
        return i0 + (x - x0) / (x1 - x0) * (i1 - i0)

    return position


def _tick(label: str, value) -> str:
    return f"{label}{value:g}" if isinstance(value, float) else f"{label}{value}"


def plot_maps(record: dict, path: str | Path, split: str | None = None) -> bool:
    """Write `maps_figure` of ``split`` to ``path``. Returns False (nothing written) where no map has one or two
    keys."""
    import matplotlib.pyplot as plt

    figure = maps_figure(record, split)
    if figure is None:
        return False
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return True


SCORE_TEXT_OFFSET = 0.3
"""How far above its grid point (in cells) a heatmap cell's score is written: a learned path starts on a grid point
(its o) and often ends near one (its *); the score written on the point itself was covered by them."""


def maps_figure(record: dict, split: str | None = None):
    """The maps of ``split`` (default: the first split with one): per sweep and light, a heatmap (two swept keys) or
    a curve (one) of mean mIoU with its interval (within [0, 1]) per grid point, the best point outlined, and each
    learned run's path from start (o) to end (*); a heatmap cell's score is written above its grid point and over the
    paths (`SCORE_TEXT_OFFSET`). Returns the matplotlib figure (the caller closes it), None where no map has one or
    two keys."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = [m for m in record.get("maps", []) if len(m["parameters"]) in (1, 2)]
    split = split if split is not None else (maps[0]["split"] if maps else None)
    maps = [m for m in maps if m["split"] == split]
    if not maps:
        return None
    figure, axes = plt.subplots(1, len(maps), figsize=(6.5 * len(maps), 5.5), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for axis, entry in zip(axes[0], maps):
        values, labels, grid = entry["values"], entry["labels"], entry["grid"]
        places = [_positions(v) for v in values]
        tied = entry["best"].get("tied", [])
        best = None if tied else entry["best"]["camera"]  # a flat map outlines no point
        if len(values) == 2:
            means = np.full((len(values[1]), len(values[0])), np.nan)
            scores = [p["miou"]["mean"] for p in grid if p["miou"] is not None]
            middle = (min(scores) + max(scores)) / 2
            for point in grid:
                i, j = values[0].index(point["values"][0]), values[1].index(point["values"][1])
                if point["miou"] is not None:
                    means[j, i] = point["miou"]["mean"]
                    low, high = (None, None) if point["miou"]["low"] is None else bounded(point["miou"])
                    text = f"{point['miou']['mean']:.3f}" + ("" if low is None else f"\n[{low:.3f}, {high:.3f}]")
                    axis.text(i, j + SCORE_TEXT_OFFSET, text, ha="center", va="center", fontsize=7, zorder=4,
                              color="black" if point["miou"]["mean"] > middle else "white")  # dark on viridis' bright
                if point["camera"] == best:
                    axis.add_patch(plt.Rectangle((i - 0.5, j - 0.5), 1, 1, fill=False, edgecolor="red", linewidth=2.5))
            image = axis.imshow(means, origin="lower", cmap="viridis", aspect="auto")
            figure.colorbar(image, ax=axis, label=f"{entry['split']} mIoU (mean over {_over(entry)})")
            axis.set_xticks(range(len(values[0])), [_tick(labels[0], v) for v in values[0]])
            axis.set_yticks(range(len(values[1])), [_tick(labels[1], v) for v in values[1]])
            axis.set_ylabel(entry["parameters"][1])
        else:
            for i, point in enumerate(grid):
                if point["miou"] is None:
                    continue
                miou = point["miou"]
                low, high = (None, None) if miou["low"] is None else bounded(miou)
                error = None if low is None else [[miou["mean"] - low], [high - miou["mean"]]]
                axis.errorbar(i, miou["mean"], yerr=error, fmt="s", capsize=4,
                              color="red" if point["camera"] == best else "tab:blue")
            axis.set_xticks(range(len(values[0])), [_tick(labels[0], v) for v in values[0]])
            axis.set_ylabel(f"{entry['split']} mIoU (mean over {_over(entry)}, interval)")
            axis.grid(alpha=0.3)
        axis.set_xlabel(entry["parameters"][0])
        for n, learned in enumerate(entry["learned"]):
            colour = colours[n % len(colours)]
            label = f"{learned['camera']}: {learned['miou']['mean']:.3f} ({_comparison(learned, tied)})"
            for k, run in enumerate(learned["runs"]):
                if any(place is None for place in places):
                    continue
                xs = [places[0](p[0]) for p in run["path"]]
                ys = [places[1](p[1]) for p in run["path"]] if len(values) == 2 else [learned["miou"]["mean"]] * len(xs)
                axis.plot(xs, ys, "-", color=colour, linewidth=1.5, label=label if k == 0 else None)
                axis.plot(xs[0], ys[0], "o", color=colour, markerfacecolor="none", markersize=8)
                axis.plot(xs[-1], ys[-1], "*", color=colour, markersize=13, markeredgecolor="black")
        from warpsense.study.search_report import draw_proposals  # a [[search]] over the map's keys: its designs

        draw_proposals(axis, entry, record.get("search"), places)
        if entry["learned"]:
            axis.legend(fontsize=7, loc="best")
        mean = entry["best"]["miou"]["mean"]
        verdict = f"no best point, {len(tied)} points tie at {mean:.3f}" if tied else f"best {best} {mean:.3f}"
        axis.set_title(f"{entry['sweep']} at {entry['light']} ({entry['split']}): {verdict}", fontsize=9)
    figure.suptitle(f"study {record['study']}: design map (o start, * end of each learned run)", fontsize=10)
    figure.tight_layout()
    return figure


def map_path(plot_path: str | Path) -> Path:
    """Where ``--plot OUT.png`` puts the map: OUT_map.png."""
    plot_path = Path(plot_path)
    return plot_path.with_name(f"{plot_path.stem}_map{plot_path.suffix or '.png'}")
