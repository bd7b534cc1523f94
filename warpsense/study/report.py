"""The report of a study directory: per camera and light level, mean mIoU and per-class IoU, precision and recall
with 95% intervals over seeds (clustered by fold with sequence folds); the paired difference to the reference camera
(over seeds, or (fold, seed) pairs) and a bootstrap interval that resamples blocks of frames within their sequences;
with folds, a per-sequence table; the learned camera and the wall time of every run, in total and steady (without
the one-off kernel compilation of a process's first epoch: `warpsense.study.run_times`). The console text and the
JSON are rendered from one record (`study_record`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from warpsense.study.adaptive import expected_cells, plan_view
from warpsense.study.maps import design_maps, map_lines
from warpsense.study.plan import PlanError
from warpsense.study.report_checks import cell_name, check_evaluation
from warpsense.study.run_times import run_times
from warpsense.study.search_report import search_lines, search_record
from warpsense.study.sequential_report import judged_comparison, sequential_lines
from warpsense.study.statistics import (
    LEVEL,
    block_bootstrap_difference,
    bounded,
    distinguishable,
    few_values_note,
    fold_interval,
    interval_text,
    paired_difference,
    t_interval,
)
from warpsense.study.study_dir import StudyDir, read_record, throughput_line

NOT_DISTINGUISHABLE = "not distinguishable"

MISSING_SHOWN = 12
"""Missing cells the console report names (a study run in parts misses hundreds; --json lists them all)."""


def _sign_count(paired: dict, folds: bool = False) -> str:
    """", higher on 2 of 3 seeds" (or "of 9 (fold, seed) pairs"; the side most pairs took)."""
    if "higher" not in paired:
        return ""
    side, count = ("higher", paired["higher"]) if paired["higher"] >= paired["lower"] else ("lower", paired["lower"])
    return f", {side} on {count} of {len(paired['seeds'])} {'(fold, seed) pairs' if folds else 'seeds'}"


def _verdict(paired: dict, bootstrap: dict | None) -> str:
    """"better" / "worse" when every interval the report prints for the comparison, the paired one (over seeds, or
    (fold, seed) pairs) and the clustered bootstrap's, excludes 0 on the same side; otherwise not distinguishable."""
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


def _per_class(per_seed: list[list[float | None]], classes: list[str]) -> dict:
    """Per class: the t interval over seeds of each seed's value ``per_seed[seed][k]`` (None left out)."""
    intervals = {}
    for k, name in enumerate(classes):
        present = [v[k] for v in per_seed if v[k] is not None]
        intervals[name] = t_interval(present) if present else None
    return intervals


def _runs(evaluations: dict, camera: str, light: str, split: str) -> dict:
    """A camera's evaluations of ``split`` at ``light``, by (fold, seed)."""
    return {(fold, seed): evaluation["splits"][split] for (c, x, fold, seed), evaluation in evaluations.items()
            if c == camera and x == light and split in evaluation["splits"]}


def _group(camera: str, light: str, runs: dict, classes: list[str], run_s: dict, steady_s: dict) -> dict:
    iou = [[run["per_class_iou"][name] for name in classes] for run in runs.values()]
    precision, recall = zip(*(precision_recall(run["image_counts"]) for run in runs.values()))
    seconds = [s for s in (run_s[(camera, light, *key)] for key in runs) if s is not None]
    steady = [s for s in (steady_s[(camera, light, *key)] for key in runs) if s is not None]
    return {"camera": camera, "light": light, "seeds": sorted({seed for _, seed in runs}),
            "folds": sorted({fold for fold, _ in runs if fold}), "cells": len(runs),
            "run_s": float(np.mean(seconds)) if seconds else None, "timed_runs": len(seconds),
            "steady_run_s": float(np.mean(steady)) if steady else None,
            "miou": fold_interval({key: run["miou"] for key, run in runs.items()}),
            "per_class_iou": _per_class(iou, classes),
            "per_class_precision": _per_class(precision, classes),
            "per_class_recall": _per_class(recall, classes)}


def _frames(run: dict) -> list:
    """The sequence of each frame a run was judged on (one unnamed sequence where the evaluation has none)."""
    return run.get("image_sequences") or [""] * len(run["image_counts"])


def _paired_frames(camera: str, light: str, runs: dict, reference: dict, name: str, keys: list) -> dict:
    """Per fold, the sequence of each frame its pairs were judged on (`_frames`), checked: a camera's cell and the
    reference's of the same (fold, seed) were judged on the same frames (counts [N, K, 3] of one shape, the same
    sequence names), and every pair of a fold on frames of the same sequences, as the bootstrap draws them together;
    else a one-line PlanError naming both cells and their files. A pair is never left out of the bootstrap."""
    sequences, first = {}, {}
    for fold, seed in keys:
        cell, base = cell_name(camera, light, fold, seed), cell_name(name, light, fold, seed)
        frames, judged = _frames(runs[fold, seed]), _frames(reference[fold, seed])
        shapes = [list(np.shape(run["image_counts"])) for run in (runs[fold, seed], reference[fold, seed])]
        if shapes[0] != shapes[1] or frames != judged:
            raise PlanError(f"{cell}: image_counts {shapes[0]} / image_sequences: judged on other frames than the "
                            f"reference {base} ({shapes[1]}); the pair cannot be compared frame by frame")
        if sequences.setdefault(fold, judged) != judged:
            other = cell_name(name, light, fold, first[fold])
            raise PlanError(f"{base}: image_sequences: judged on other frames than {other} of the same fold "
                            f"({len(judged)} against {len(sequences[fold])} frames, or other sequences)")
        first.setdefault(fold, seed)
    return sequences


def _comparison(camera: str, light: str, runs: dict, reference: dict, plan: dict, classes: list[str],
                resamples: int, block: int) -> dict:
    keys = sorted(set(runs) & set(reference))
    label = (lambda key: key) if any(fold for fold, _ in keys) else (lambda key: key[1])  # no folds: the seed
    paired = paired_difference({label(k): runs[k]["miou"] for k in keys},
                               {label(k): reference[k]["miou"] for k in keys})
    sequences = _paired_frames(camera, light, runs, reference, plan["reference"], keys)
    pairs = [(runs[k]["image_counts"], reference[k]["image_counts"], k[0]) for k in keys]
    bootstrap = block_bootstrap_difference(pairs, sequences, block, resamples)
    deltas = {}
    for name in classes:
        both = [(runs[k]["per_class_iou"][name], reference[k]["per_class_iou"][name]) for k in keys]
        both = [(a, b) for a, b in both if a is not None and b is not None]
        deltas[name] = float(np.mean([a - b for a, b in both])) if both else None
    record = {"camera": camera, "light": light, "reference": plan["reference"], "paired": paired,
              "bootstrap": bootstrap, "verdict": _verdict(paired, bootstrap), "per_class_delta": deltas}
    # study.sequential: judged at the look where the sequential rule stopped, its repeated interval
    record.update(judged_comparison(plan, runs, reference, sequences, block, resamples) or {})
    return record


def _per_sequence(light: str, by_camera: dict, reference: str) -> list[dict]:
    """Per held-out sequence (fold): each camera's mean over seeds with its t interval, and the mean paired
    difference to the reference over the fold's seeds (no interval: the pooled one judges)."""
    rows = []
    folds = sorted({fold for runs in by_camera.values() for fold, _ in runs if fold})
    for fold in folds:
        cameras = {}
        for camera, runs in by_camera.items():
            scores = {seed: run["miou"] for (f, seed), run in runs.items() if f == fold}
            if not scores:
                continue
            base = {seed: run["miou"] for (f, seed), run in by_camera.get(reference, {}).items() if f == fold}
            common = sorted(set(scores) & set(base))
            cameras[camera] = {"miou": t_interval(list(scores.values())), "seeds": sorted(scores),
                               "difference": float(np.mean([scores[s] - base[s] for s in common]))
                               if common and camera != reference else None}
        rows.append({"light": light, "sequence": fold, "cameras": cameras})
    return rows


def _shared_sequences(evaluations: dict, split: str) -> list[str]:
    """Sequences of ``split``'s frames that some run also trained on (CamVid's val: drive 0016E5)."""
    shared = set()
    for evaluation in evaluations.values():
        judged = set(evaluation["splits"].get(split, {}).get("image_sequences") or ())
        shared |= judged & set(evaluation.get("train_sequences") or ())
    return sorted(shared)


def _split_record(plan: dict, evaluations: dict, run_s: dict, steady_s: dict, split: str, resamples: int,
                  block: int) -> dict:
    classes = next(iter(evaluations.values()))["class_names"]
    groups, comparisons, per_sequence = [], [], []
    for light in plan["lights"]:
        by_camera = {}
        for camera in plan["cameras"]:
            runs = _runs(evaluations, camera["name"], light["name"], split)
            if runs:
                by_camera[camera["name"]] = runs
                groups.append(_group(camera["name"], light["name"], runs, classes, run_s, steady_s))
        if plan.get("folds", "none") != "none":
            per_sequence += _per_sequence(light["name"], by_camera, plan["reference"])
        reference = by_camera.get(plan["reference"])
        if reference is None:
            continue
        for camera, runs in by_camera.items():
            if camera != plan["reference"] and set(runs) & set(reference):
                comparisons.append(_comparison(camera, light["name"], runs, reference, plan, classes, resamples,
                                               block))
    return {"groups": groups, "comparisons": comparisons, "per_sequence": per_sequence,
            "shared_sequences": [] if plan.get("folds") == "blocks" else _shared_sequences(evaluations, split)}


def study_record(study_dir: str | Path, resamples: int = 2000, block: int = 10) -> dict:
    """Everything the report says, as JSON-ready data: the plan, each cell (its scores and learned camera, or
    that it is missing), and per split the groups, comparisons and, with sequence folds, the per-sequence table;
    ``maps``: per sweep of the plan, light and split, the design map (`warpsense.study.maps.design_maps`).
    ``block``: frames per block of the clustered bootstrap."""
    if resamples < 1 or block < 1:
        raise ValueError(f"{'--resamples' if resamples < 1 else '--block-frames'} must be >= 1")
    study_dir = Path(study_dir)
    study = StudyDir(study_dir)
    plan = plan_view(study_dir, study.read_plan())  # with a [[search]]'s designs among the cameras
    evaluations, run_s, steady_s, cells, missing = {}, {}, {}, [], []
    for cell in expected_cells(study_dir, plan):  # study.sequential, [[search]]: the cells needed so far
        run = study.run(cell)
        if not run.finished():
            missing.append(cell.id)
            continue
        evaluation = read_record(run.evaluation)
        check_evaluation(evaluation, cell.id, run.evaluation, evaluations)
        key = (cell.camera, cell.light, cell.fold, cell.seed)
        evaluations[key] = evaluation
        run_s[key], steady_s[key] = run_times(run.read_metrics())
        cells.append({"cell": cell.id, "camera": cell.camera, "light": cell.light, "fold": cell.fold,
                      "seed": cell.seed, "epoch": evaluation["epoch"],
                      "network_parameters": evaluation["network_parameters"], "run_s": run_s[key],
                      "steady_run_s": steady_s[key],
                      "miou": {split: m["miou"] for split, m in evaluation["splits"].items()},
                      "learned_camera": evaluation["camera"]})
    if not evaluations:
        raise PlanError(f"{study_dir}: no finished cell yet ({len(missing)} cells planned, none evaluated)")
    splits = list(dict.fromkeys(split for e in evaluations.values() for split in e["splits"]))
    throughput = study.read_throughput()
    parts = {split: _split_record(plan, evaluations, run_s, steady_s, split, resamples, block) for split in splits}
    for part in parts.values():
        for comparison in part["comparisons"]:
            comparison["detectable"] = detectable_difference(comparison)
    return {"study": plan["name"], "directory": str(study_dir), "reference": plan["reference"], "level": LEVEL,
            "folds": plan.get("folds", "none"), "sequences": plan.get("sequences", []), "block_frames": block,
            "fold_sizes": _fold_sizes(evaluations),
            "plan": plan, "cells": cells, "missing": missing, "throughput": throughput, "splits": parts,
            "maps": design_maps(study_dir, plan, cells, parts),
            "search": search_record(study_dir, plan, cells, parts)}


def detectable_difference(comparison: dict) -> float | None:
    """The smallest difference a comparison could have called: the larger half-width of the intervals its verdict
    needs to exclude 0 (the paired one and the bootstrap's); None where an interval is unknown (one pair)."""
    widths = [(interval["high"] - interval["low"]) / 2 for interval in (comparison["paired"], comparison["bootstrap"])
              if interval is not None and interval.get("low") is not None]
    return max(widths) if len(widths) == 2 or (widths and comparison["bootstrap"] is None) else None


def _fold_sizes(evaluations: dict) -> list[dict]:
    """Per fold the cells were judged on: {"fold", "train" (frames trained on), "judged", "labelled" (frames of the
    labelled splits the fold was cut from; None where unknown)}, from the first evaluation of each fold that records
    them (evaluations written before the counts were recorded give none)."""
    rows = {}
    for (_, _, fold, _), evaluation in evaluations.items():
        if fold in rows or "train_frames" not in evaluation:
            continue
        judged = next(iter(evaluation["splits"].values()))
        rows[fold] = {"fold": fold, "train": evaluation["train_frames"], "judged": len(judged["image_counts"]),
                      "labelled": evaluation.get("labelled_frames")}
    return sorted(rows.values(), key=lambda row: (len(row["fold"]), row["fold"]))


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


def _per_sequence_lines(split: str, part: dict, reference: str) -> list[str]:
    rows = part.get("per_sequence") or []
    if not rows:
        return []
    cameras = list(dict.fromkeys(camera for row in rows for camera in row["cameras"]))
    cells = [[(f"{interval_text(row['cameras'][c]['miou'])}" + ("" if row["cameras"][c]["difference"] is None else
              f" {row['cameras'][c]['difference']:+.4f}")) if c in row["cameras"] else "-" for c in cameras]
             for row in rows]
    heads = [f"{row['light']}/{row['sequence']}" for row in rows]
    head_width = max(len(h) for h in heads)
    widths = [max(len(c), *(len(line[i]) for line in cells)) for i, c in enumerate(cameras)]
    lines = [f"[{split}] per fold (held-out block or sequence): mIoU mean over seeds [t interval], then the mean "
             f"paired difference "
             f"to {reference!r}",
             f"  {'':<{head_width}s}  " + "  ".join(f"{c:>{w}s}" for c, w in zip(cameras, widths))]
    lines += [f"  {head:<{head_width}s}  " + "  ".join(f"{c:>{w}s}" for c, w in zip(line, widths))
              for head, line in zip(heads, cells)]
    return lines


def _protocol_text(record: dict) -> str:
    """How the study's cells were trained and judged, in words."""
    if record.get("folds") == "sequence":
        return (f"sequence folds (held out: {', '.join(record['sequences'])}): each cell trains on the other "
                "sequences' frames and is judged on its own")
    if record.get("folds") == "blocks":
        plan = record.get("plan", {})
        return (f"block folds ({plan.get('blocks')} blocks of every sequence, buffer {plan.get('block_buffer')} frame "
                f"numbers): each cell is judged on one block of every sequence and trains on the rest, less the buffer "
                f"around it")
    return "no folds: trained on train, judged on val"


def render_text(record: dict) -> str:
    """The console report (every number comes from ``record``)."""
    level = f"{record['level']:.0%}"
    folds = record.get("folds") in ("sequence", "blocks")
    protocol = _protocol_text(record)
    lines = [f"study {record['study']} ({record['directory']}): {len(record['cells'])} cells evaluated, "
             f"{len(record['missing'])} missing; judged at the final epoch; {protocol}; intervals {level}"]
    for row in record.get("fold_sizes") or []:
        share = f" ({row['train'] / row['labelled']:.0%} of the labelled frames)" if row.get("labelled") else ""
        lines.append(f"  fold {row['fold'] or '-'}: train {row['train']} frames{share}, judge {row['judged']} frames")
    if record["missing"]:
        shown = record["missing"][:MISSING_SHOWN]
        more = len(record["missing"]) - len(shown)
        rest = f" and {more} more (`warpsense study status {record['directory']}` lists every cell)" if more else ""
        lines.append(f"  missing: {', '.join(shown)}{rest}")
    lines += few_values_note(record, record["level"])
    over = "(fold, seed)" if folds else "seeds"
    for split, part in record["splits"].items():
        if part.get("shared_sequences"):
            lines.append(f"\nnote: [{split}] frames come from sequences the runs also trained on "
                         f"({', '.join(part['shared_sequences'])}): this measures more frames of known drives, not new "
                         f"streets; judge by study.folds = \"sequence\"")
        interval = "t interval over the folds' means" if folds else "t interval"
        lines.append(f"\n[{split}] mIoU, mean over {over} [{level} {interval}]; s/run: wall time (setup, training, "
                     f"evaluation), steady: each process's first epoch (its one-off Warp kernel compilation) counted "
                     f"at the median of its other epochs")
        width = max(len(g["camera"]) for g in part["groups"])
        for group in part["groups"]:
            steady = group.get("steady_run_s")
            seconds = "" if group["run_s"] is None else f"  {group['run_s']:.0f} s/run" + (
                "" if steady is None else f" ({steady:.0f} steady)") + (
                "" if group["timed_runs"] == group.get("cells", len(group["seeds"])) else
                f" ({group['timed_runs']} timed)")
            where = f"folds {','.join(group['folds'])} x " if group.get("folds") else ""
            lines.append(f"  {group['light']:>8s}  {group['camera']:<{width}s}  {interval_text(group['miou'])}  "
                         f"{where}seeds {','.join(map(str, group['seeds']))}{seconds}")
        if part["comparisons"]:
            block = record.get("block_frames")
            boot = f"bootstrap of frames in blocks of {block} within sequences" if block else "image bootstrap"
            lines.append(f"[{split}] difference to the reference camera {record['reference']!r}: paired over {over} "
                         f"[{level} t] | {boot} [{level}]; verdict; the smallest difference it could have called "
                         f"(the wider interval's half-width)")
        for comparison in part["comparisons"]:
            bootstrap = comparison["bootstrap"]
            boot = f"[{bootstrap['low']:+.4f}, {bootstrap['high']:+.4f}]" if bootstrap else "-"
            lines.append(f"  {comparison['light']:>8s}  {comparison['camera']:<{width}s}  "
                         f"{interval_text(comparison['paired'], signed=True)} | {boot}  {comparison['verdict']}"
                         f"{_sign_count(comparison['paired'], folds)}"
                         + ("" if comparison.get("detectable") is None else
                            f"; detects +-{comparison['detectable']:.4f}"))
        lines += sequential_lines(split, part, record["level"])
        lines += _per_sequence_lines(split, part, record["reference"])
        lines += _per_class_lines(split, part)
    lines += map_lines(record.get("maps", []), level)
    lines += search_lines(record.get("search"), level)
    if record.get("throughput"):
        lines.append("\nthroughput (each `study run`)")
        lines += [f"  {throughput_line(entry)}" for entry in record["throughput"]]
    lines.append("\nlearned cameras (final epoch)")
    for cell in record["cells"]:
        scores = ", ".join(f"{split} {value:.4f}" for split, value in cell["miou"].items())
        lines.append(f"  {cell['cell']}: {scores}; {_learned(cell['learned_camera'])}")
    return "\n".join(lines)


def plot_study(record: dict, path: str | Path, split: str | None = None) -> None:
    """Write `study_figure` of ``split`` (default: the first) to ``path``."""
    import matplotlib.pyplot as plt

    figure = study_figure(record, split)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def study_figure(record: dict, split: str | None = None):
    """One row per light level: mIoU with intervals per camera (reference marked; each interval within [0, 1],
    `warpsense.study.statistics.bounded`) and per-class IoU differences to the reference camera (mean over paired
    seeds). Every label lies within the figure. Returns the matplotlib figure (the caller closes it)."""
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
            low, high = (None, None) if miou["low"] is None else bounded(miou)
            error = None if low is None else [[miou["mean"] - low], [high - miou["mean"]]]
            colour = "tab:red" if group["camera"] == record["reference"] else "tab:blue"
            score_axis.errorbar(miou["mean"], y, xerr=error, fmt="o", color=colour, capsize=4)
        score_axis.set_yticks(range(len(groups)), [g["camera"] for g in groups])
        score_axis.invert_yaxis()
        over = "(fold, seed)" if record.get("folds", "none") != "none" else "seeds"
        score_axis.set_xlabel(f"{split} mIoU (mean over {over}, {record['level']:.0%} interval)")
        score_axis.set_title(f"{light}: score per camera (red: reference {record['reference']})", fontsize=10)
        score_axis.grid(axis="x", alpha=0.3)
        comparisons = [c for c in part["comparisons"] if c["light"] == light]
        if comparisons:
            deltas = 100 * np.array([[np.nan if c["per_class_delta"][k] is None else c["per_class_delta"][k]
                                      for k in classes] for c in comparisons])  # IoU points, as the labels
            limit = max(np.nanmax(np.abs(deltas)) if np.isfinite(deltas).any() else 1.0, 1.0)
            image = delta_axis.imshow(deltas, cmap="RdBu", vmin=-limit, vmax=limit, aspect="auto")
            for i in range(deltas.shape[0]):
                for j in range(deltas.shape[1]):
                    if np.isfinite(deltas[i, j]):  # white text on the dark ends of the colour map
                        colour = "white" if abs(deltas[i, j]) > 0.6 * limit else "black"
                        delta_axis.text(j, i, f"{deltas[i, j]:+.1f}", ha="center", va="center", fontsize=7,
                                        color=colour)
            delta_axis.set_yticks(range(len(comparisons)),
                                  [f"{c['camera']} ({c['verdict']})" for c in comparisons], fontsize=8)
            delta_axis.set_xticks(range(len(classes)), classes, rotation=45, ha="right", fontsize=8)
            # short: a longer label ran past the height of a row of one comparison and was cut off
            figure.colorbar(image, ax=delta_axis, label="IoU points x100")
            delta_axis.set_title(f"{light}: per-class IoU minus {record['reference']} (points x100)", fontsize=10)
        else:
            delta_axis.axis("off")
    figure.suptitle(f"study {record['study']}: {len(record['cells'])} runs, judged at the final epoch", fontsize=11)
    figure.tight_layout()
    return figure
