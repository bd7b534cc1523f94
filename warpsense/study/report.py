"""The report of a study directory: per camera and light level, mean mIoU and per-class IoU, precision and recall
with 95% intervals over seeds; the paired difference to the reference camera (seed by seed) and an image-level
bootstrap interval; the learned camera and the wall time of every run. The console text and the JSON are rendered
from one record (`study_record`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from warpsense.study.plan import Plan, PlanError
from warpsense.study.runner import PLAN_RECORD, THROUGHPUT, evaluation_path, throughput_line
from warpsense.study.statistics import LEVEL, bootstrap_difference, distinguishable, paired_difference, t_interval
from warpsense.train.run_dir import METRICS, read_metrics

NOT_DISTINGUISHABLE = "not distinguishable"


def _read_plan(study_dir: Path) -> dict:
    path = study_dir / PLAN_RECORD
    if not study_dir.is_dir():
        raise PlanError(f"{study_dir}: no such study directory")
    if not path.is_file():
        raise PlanError(f"{study_dir}: not a study directory (no {PLAN_RECORD}); run `warpsense study run PLAN "
                        f"--out {study_dir}` first")
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise PlanError(f"{path}: unreadable: {error}") from None


def _sign_count(paired: dict) -> str:
    """", higher on 2 of 3 seeds" (the side most seeds took; nothing for reports written before the counts)."""
    if "higher" not in paired:
        return ""
    side, count = ("higher", paired["higher"]) if paired["higher"] >= paired["lower"] else ("lower", paired["lower"])
    return f", {side} on {count} of {len(paired['seeds'])} seeds"


def _verdict(paired: dict, bootstrap: dict | None) -> str:
    """"better" / "worse" when the seed-paired interval and the image bootstrap interval both exclude 0 on the
    same side; otherwise not distinguishable."""
    intervals = [paired] + ([bootstrap] if bootstrap is not None else [])
    if all(distinguishable(i) for i in intervals):
        sides = {i["low"] > 0 for i in intervals}
        if len(sides) == 1:
            return "better" if sides.pop() else "worse"
    return NOT_DISTINGUISHABLE


def precision_recall(image_counts) -> tuple[list[float | None], list[float | None]]:
    """Per-class pixel precision TP / (TP + FP) and recall TP / (TP + FN) over a split, from an evaluation's
    per-image counts [N, K, 3] (TP, FP, FN); None where a class was never predicted (precision) or is absent
    (recall)."""
    tp, fp, fn = np.asarray(image_counts, dtype=np.float64).sum(0).T
    precision = [float(t / (t + f)) if t + f > 0 else None for t, f in zip(tp, fp)]
    recall = [float(t / (t + f)) if t + f > 0 else None for t, f in zip(tp, fn)]
    return precision, recall


def run_seconds(metrics_path: Path) -> float | None:
    """A run's wall seconds from its ``metrics.jsonl``: each process's ``wall_s`` at its last epoch (setup,
    training and evaluation), summed over the processes of a resumed run (a record with ``setup_s`` starts one); None
    without records. The work an interrupted process did after its last epoch is not counted."""
    total, last = 0.0, None
    for record in read_metrics(metrics_path):
        if "setup_s" in record and last is not None:
            total += last
        last = record.get("wall_s", last)
    return None if last is None else total + last


def _per_class(per_seed: list[list[float | None]], classes: list[str]) -> dict:
    """Per class: the t interval over seeds of each seed's value ``per_seed[seed][k]`` (None left out)."""
    intervals = {}
    for k, name in enumerate(classes):
        present = [v[k] for v in per_seed if v[k] is not None]
        intervals[name] = t_interval(present) if present else None
    return intervals


def _split_record(plan: dict, evaluations: dict, run_s: dict, split: str, resamples: int) -> dict:
    classes = next(iter(evaluations.values()))["class_names"]
    groups, comparisons = [], []
    for light in plan["lights"]:
        by_camera = {}
        for camera in plan["cameras"]:
            runs = {seed: evaluations[(camera["name"], light["name"], seed)]["splits"][split]
                    for seed in plan["seeds"] if (camera["name"], light["name"], seed) in evaluations
                    and split in evaluations[(camera["name"], light["name"], seed)]["splits"]}
            if not runs:
                continue
            by_camera[camera["name"]] = runs
            iou = [[run["per_class_iou"][name] for name in classes] for run in runs.values()]
            precision, recall = zip(*(precision_recall(run["image_counts"]) for run in runs.values()))
            seconds = [s for s in (run_s[(camera["name"], light["name"], seed)] for seed in runs) if s is not None]
            groups.append({"camera": camera["name"], "light": light["name"], "seeds": sorted(runs),
                           "run_s": float(np.mean(seconds)) if seconds else None, "timed_runs": len(seconds),
                           "miou": t_interval([run["miou"] for run in runs.values()]),
                           "per_class_iou": _per_class(iou, classes),
                           "per_class_precision": _per_class(precision, classes),
                           "per_class_recall": _per_class(recall, classes)})
        reference = by_camera.get(plan["reference"])
        if reference is None:
            continue
        for camera, runs in by_camera.items():
            if camera == plan["reference"] or not set(runs) & set(reference):
                continue
            seeds = sorted(set(runs) & set(reference))
            paired = paired_difference({s: runs[s]["miou"] for s in seeds}, {s: reference[s]["miou"] for s in seeds})
            counts = np.array([runs[s]["image_counts"] for s in seeds])
            reference_counts = np.array([reference[s]["image_counts"] for s in seeds])
            bootstrap = bootstrap_difference(counts, reference_counts, resamples) \
                if counts.shape == reference_counts.shape and counts.size else None
            deltas = {}
            for name in classes:
                pairs = [(runs[s]["per_class_iou"][name], reference[s]["per_class_iou"][name]) for s in seeds]
                pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
                deltas[name] = float(np.mean([a - b for a, b in pairs])) if pairs else None
            comparisons.append({"camera": camera, "light": light["name"], "reference": plan["reference"],
                                "paired": paired, "bootstrap": bootstrap, "verdict": _verdict(paired, bootstrap),
                                "per_class_delta": deltas})
    return {"groups": groups, "comparisons": comparisons}


def study_record(study_dir: str | Path, resamples: int = 2000) -> dict:
    """Everything the report says, as JSON-ready data: the plan, each cell (its scores and learned camera, or
    that it is missing), and per split the groups and comparisons."""
    study_dir = Path(study_dir)
    plan = _read_plan(study_dir)
    evaluations, run_s, cells, missing = {}, {}, [], []
    for cell in Plan.from_dict(plan).cells():
        path = evaluation_path(study_dir, cell)
        if not path.is_file():
            missing.append(cell.id)
            continue
        try:
            evaluation = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise PlanError(f"{path}: unreadable: {error}") from None
        evaluations[(cell.camera, cell.light, cell.seed)] = evaluation
        run_s[(cell.camera, cell.light, cell.seed)] = run_seconds(path.parent / METRICS)
        cells.append({"cell": cell.id, "camera": cell.camera, "light": cell.light, "seed": cell.seed,
                      "epoch": evaluation["epoch"], "network_parameters": evaluation["network_parameters"],
                      "run_s": run_s[(cell.camera, cell.light, cell.seed)],
                      "miou": {split: m["miou"] for split, m in evaluation["splits"].items()},
                      "learned_camera": evaluation["camera"]})
    if not evaluations:
        raise PlanError(f"{study_dir}: no finished cell yet ({len(missing)} cells planned, none evaluated)")
    splits = list(dict.fromkeys(split for e in evaluations.values() for split in e["splits"]))
    throughput_path = study_dir / THROUGHPUT
    throughput = json.loads(throughput_path.read_text()) if throughput_path.is_file() else []
    return {"study": plan["name"], "directory": str(study_dir), "reference": plan["reference"], "level": LEVEL,
            "plan": plan, "cells": cells, "missing": missing, "throughput": throughput,
            "splits": {split: _split_record(plan, evaluations, run_s, split, resamples) for split in splits}}


def _interval(record: dict | None, signed: bool = False) -> str:
    if record is None:
        return "-"
    sign = "+" if signed else ""
    if record["low"] is None:
        return f"{record['mean']:{sign}.4f} [n=1, no interval]"
    return f"{record['mean']:{sign}.4f} [{record['low']:{sign}.4f}, {record['high']:{sign}.4f}]"


def _learned(camera: dict) -> str:
    parts = []
    if "cfa_layout" in camera:
        parts.append(f"CFA {camera['cfa_layout']}")
    if "exposure_gain" in camera:
        parts.append(f"gain {camera['exposure_gain']:.3f}")
    for key, label, unit in (("f_number", "f/", ""), ("exposure_ms", "exposure ", " ms"),
                             ("analog_gain", "analog gain ", "")):
        if key in camera:
            parts.append(f"{label}{camera[key]:.3g}{unit}")
    if "zernike_waves" in camera:
        on_axis = [row[0] if isinstance(row, list) else row for row in camera["zernike_waves"]]  # [J, 3]: constant term
        parts.append("lens Zernike on axis [" + ", ".join(f"{w:+.3f}" for w in on_axis) + "] waves")
    return "; ".join(parts) or "fixed"


def _percent(interval: dict | None) -> str:
    return "-" if interval is None else f"{100 * interval['mean']:.1f}"


def _per_class_lines(split: str, part: dict) -> list[str]:
    """One row per class, one column per light/camera group: IoU (precision / recall), % means over seeds."""
    groups = part["groups"]
    classes = list(groups[0]["per_class_iou"])
    cells = [[f"{_percent(g['per_class_iou'][name])} ({_percent(g['per_class_precision'][name])}/"
              f"{_percent(g['per_class_recall'][name])})" for g in groups] for name in classes]
    heads = [f"{g['light']}/{g['camera']}" for g in groups]
    widths = [max(len(head), *(len(row[i]) for row in cells)) for i, head in enumerate(heads)]
    name_width = max(len(name) for name in classes)
    lines = [f"[{split}] per class, % means over seeds: IoU (precision/recall)",
             f"  {'':<{name_width}s}  " + "  ".join(f"{h:>{w}s}" for h, w in zip(heads, widths))]
    lines += [f"  {name:<{name_width}s}  " + "  ".join(f"{c:>{w}s}" for c, w in zip(row, widths))
              for name, row in zip(classes, cells)]
    return lines


def render_text(record: dict) -> str:
    """The console report (every number comes from ``record``)."""
    level = f"{record['level']:.0%}"
    lines = [f"study {record['study']} ({record['directory']}): {len(record['cells'])} cells evaluated, "
             f"{len(record['missing'])} missing; judged at the final epoch; intervals {level}"]
    if record["missing"]:
        lines.append(f"  missing: {', '.join(record['missing'])}")
    for split, part in record["splits"].items():
        lines.append(f"\n[{split}] mIoU, mean over seeds [{level} t interval]")
        width = max(len(g["camera"]) for g in part["groups"])
        for group in part["groups"]:
            seconds = "" if group["run_s"] is None else f"  {group['run_s']:.0f} s/run" + (
                "" if group["timed_runs"] == len(group["seeds"]) else f" ({group['timed_runs']} timed)")
            lines.append(f"  {group['light']:>8s}  {group['camera']:<{width}s}  {_interval(group['miou'])}  "
                         f"seeds {','.join(map(str, group['seeds']))}{seconds}")
        if part["comparisons"]:
            lines.append(f"[{split}] difference to the reference camera {record['reference']!r}: paired over seeds "
                         f"[{level} t] | image bootstrap [{level}]")
        for comparison in part["comparisons"]:
            bootstrap = comparison["bootstrap"]
            boot = f"[{bootstrap['low']:+.4f}, {bootstrap['high']:+.4f}]" if bootstrap else "-"
            lines.append(f"  {comparison['light']:>8s}  {comparison['camera']:<{width}s}  "
                         f"{_interval(comparison['paired'], signed=True)} | {boot}  {comparison['verdict']}"
                         f"{_sign_count(comparison['paired'])}")
        lines += _per_class_lines(split, part)
    if record.get("throughput"):
        lines.append("\nthroughput (each `study run`)")
        lines += [f"  {throughput_line(entry)}" for entry in record["throughput"]]
    lines.append("\nlearned cameras (final epoch)")
    for cell in record["cells"]:
        scores = ", ".join(f"{split} {value:.4f}" for split, value in cell["miou"].items())
        lines.append(f"  {cell['cell']}: {scores}; {_learned(cell['learned_camera'])}")
    return "\n".join(lines)


def plot_study(record: dict, path: str | Path, split: str | None = None) -> None:
    """One row per light level: mIoU with intervals per camera (reference marked) and per-class IoU differences to
    the reference camera (mean over paired seeds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    split = split or next(iter(record["splits"]))
    part = record["splits"][split]
    lights = list(dict.fromkeys(g["light"] for g in part["groups"]))
    classes = list(part["groups"][0]["per_class_iou"])
    figure, axes = plt.subplots(len(lights), 2, figsize=(14, 0.5 + 0.45 * len(record["plan"]["cameras"]) *
                                                          len(lights) + 1.5 * len(lights)), squeeze=False,
                                gridspec_kw={"width_ratios": [1, 1.4]})
    for row, light in enumerate(lights):
        groups = [g for g in part["groups"] if g["light"] == light]
        score_axis, delta_axis = axes[row]
        for y, group in enumerate(groups):
            miou = group["miou"]
            error = None if miou["low"] is None else [[miou["mean"] - miou["low"]], [miou["high"] - miou["mean"]]]
            colour = "tab:red" if group["camera"] == record["reference"] else "tab:blue"
            score_axis.errorbar(miou["mean"], y, xerr=error, fmt="o", color=colour, capsize=4)
        score_axis.set_yticks(range(len(groups)), [g["camera"] for g in groups])
        score_axis.invert_yaxis()
        score_axis.set_xlabel(f"{split} mIoU (mean over seeds, {record['level']:.0%} interval)")
        score_axis.set_title(f"{light}: score per camera (red: reference {record['reference']})", fontsize=10)
        score_axis.grid(axis="x", alpha=0.3)
        comparisons = [c for c in part["comparisons"] if c["light"] == light]
        if comparisons:
            deltas = np.array([[np.nan if c["per_class_delta"][k] is None else c["per_class_delta"][k]
                                for k in classes] for c in comparisons])
            limit = max(np.nanmax(np.abs(deltas)) if np.isfinite(deltas).any() else 0.01, 0.01)
            image = delta_axis.imshow(deltas, cmap="RdBu", vmin=-limit, vmax=limit, aspect="auto")
            for i in range(deltas.shape[0]):
                for j in range(deltas.shape[1]):
                    if np.isfinite(deltas[i, j]):
                        delta_axis.text(j, i, f"{deltas[i, j] * 100:+.1f}", ha="center", va="center", fontsize=7)
            delta_axis.set_yticks(range(len(comparisons)),
                                  [f"{c['camera']} ({c['verdict']})" for c in comparisons], fontsize=8)
            delta_axis.set_xticks(range(len(classes)), classes, rotation=45, ha="right", fontsize=8)
            figure.colorbar(image, ax=delta_axis, label="IoU difference to the reference")
            delta_axis.set_title(f"{light}: per-class IoU minus {record['reference']} (points x100)", fontsize=10)
        else:
            delta_axis.axis("off")
    figure.suptitle(f"study {record['study']}: {len(record['cells'])} runs, judged at the final epoch", fontsize=11)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
