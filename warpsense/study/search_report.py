"""The report's ``search`` record of a plan with a ``[[search]]``: the designs in the order proposed with their
source, state, rung decisions and scores; the best complete design with its interval; the cells and run seconds the
search spent, beside those of the grid it replaces; its text and its figure (the designs over the two first searched
keys, or over the sweep's map where the plan has one of the same keys, `draw_proposals`).

The grid a search replaces is the plan's ``[[sweep]]`` where it has one (its points at the search's light x folds x
the study's seeds, and their measured run seconds), else the grid its bounds imply at ``grid_points`` values per key
(default 4, as camvid_photon_map's 4 x 4; evenly spaced, on a log scale for a log-scaled key) x folds x the study's
seeds, its run seconds estimated as that many cells at the search's mean seconds per cell. "gpu_seconds" are the
runs' wall seconds summed (each run holds one GPU; under MPS several runs share one, so that overstates its GPU time
alike for the search and a measured grid).
"""

from __future__ import annotations

import math
from pathlib import Path

from warpsense.study.plan import Plan
from warpsense.study.search import read_search
from warpsense.study.statistics import interval_text


def _split(parts: dict) -> str | None:
    return "heldout" if "heldout" in parts else "val" if "val" in parts else next(iter(parts), None)


def _seconds(cells: list[dict]) -> float | None:
    timed = [cell["run_s"] for cell in cells if cell.get("run_s") is not None]
    return float(sum(timed)) if timed else None


def search_record(study_dir: str | Path, plan: dict, cells: list[dict], parts: dict) -> dict | None:
    """The report's ``search`` (None for a plan without a [[search]]).

    Args:
        study_dir: the study directory (its search record, `warpsense.study.search.SEARCH_RECORD`).
        plan: the recorded plan (with or without the designs among its cameras).
        cells: the report's evaluated cells (each with camera, light, run_s).
        parts: the report's per-split records (their groups).

    Returns:
        {"name", "light", "split", "parameters", "low", "high", "log", "sampler", "reduction", "prune_margin",
        "budget", "best": {"camera", "values" (key -> value), "miou" (mean with its interval), "cells"} or None,
        "cells": the designs' cells trained, "grid_cells", "grid": {"source": "sweep" or "implied", "description",
        "points", "cells"}, "gpu_seconds": the designs' runs' wall seconds summed, "grid_gpu_seconds" (measured for a
        sweep, else estimated: "grid_seconds_estimated"), "warm_start": {"cameras", "cells", "gpu_seconds"} (the
        learned cameras it started from), "proposals": per design in order {"number", "camera", "values", "source",
        "state", "rungs", "cells" (trained by the search: 0 for a known camera's), "miou", "duplicate_of"}}.
    """
    if not plan.get("search"):
        return None
    spec = Plan.from_dict({**plan, "cameras": []}).search
    plan_spec = Plan.from_dict(plan)
    record = read_search(Path(study_dir))
    split = _split(parts)
    groups = {g["camera"]: g for g in parts[split]["groups"] if g["light"] == spec.light} if split else {}
    at_light = [cell for cell in cells if cell["light"] == spec.light]
    designs = {d["camera"] for d in record["designs"] if d["state"] != "duplicate" and not d.get("known")}
    design_cells = [cell for cell in at_light if cell["camera"] in designs]
    proposals = []
    for design in record["designs"]:
        group = groups.get(design["camera"])
        proposals.append({"number": design["number"], "camera": design["camera"],
                          "values": dict(zip(spec.parameters, design["values"])), "source": design["source"],
                          "state": design["state"], "rungs": design.get("rungs", []),
                          "cells": sum(cell["camera"] == design["camera"] for cell in design_cells),
                          "miou": group["miou"] if group and design["state"] != "duplicate" else None,
                          "duplicate_of": design.get("duplicate_of")})
    complete = [p for p in proposals if p["state"] == "complete" and p["miou"] is not None]
    best = max(complete, key=lambda p: p["miou"]["mean"], default=None)
    folds, seeds = len(plan_spec.fold_names()), len(plan_spec.seeds)
    sweeps = plan_spec.sweeps
    if sweeps:
        points = sum(len(sweep.points) for sweep in sweeps)
        swept = {camera for sweep in sweeps for camera, _ in sweep.points}
        grid = {"source": "sweep", "description": f"the plan's sweep {', '.join(s.name for s in sweeps)}: {points} "
                f"points x {folds} fold(s) x {seeds} seed(s)", "points": points, "cells": points * folds * seeds}
        grid_seconds, estimated = _seconds([cell for cell in at_light if cell["camera"] in swept]), False
    else:
        points = math.prod(spec.grid_points)
        shape = " x ".join(f"{n}" for n in spec.grid_points)
        grid = {"source": "implied", "description": f"implied by the bounds: {shape} points x {folds} fold(s) x "
                f"{seeds} seed(s)", "points": points, "cells": points * folds * seeds,
                "values": [[float(v) for v in values] for values in spec.grid_values()]}
        spent = _seconds(design_cells)
        grid_seconds = None if spent is None else spent / len(design_cells) * grid["cells"]
        estimated = True
    learned = [cell for cell in at_light if cell["camera"] in spec.learned]
    return {"name": spec.name, "light": spec.light, "split": split, "parameters": list(spec.parameters),
            "labels": list(spec.labels), "low": list(spec.low), "high": list(spec.high), "log": list(spec.log),
            "sampler": spec.sampler, "reduction": spec.reduction, "prune_margin": spec.prune_margin,
            "budget": spec.budget, "seeds_per_design": spec.seeds,
            "best": None if best is None else {"camera": best["camera"], "values": best["values"],
                                               "miou": best["miou"], "cells": best["cells"]},
            "cells": len(design_cells), "grid_cells": grid["cells"], "grid": grid,
            "gpu_seconds": _seconds(design_cells), "grid_gpu_seconds": grid_seconds,
            "grid_seconds_estimated": estimated,
            "warm_start": {"cameras": list(spec.learned), "cells": len(learned), "gpu_seconds": _seconds(learned)},
            "proposals": proposals}


def _values(values: dict) -> str:
    return ", ".join(f"{key} {value:g}" for key, value in values.items())


def _state(proposal: dict) -> str:
    if proposal["state"] == "pruned":
        last = proposal["rungs"][-1]
        return f"pruned after {last['cells']} cell(s), rank {last['rank']} of {last['of']}"
    if proposal["state"] == "duplicate":
        return f"the same design as {proposal['duplicate_of']} (not trained)"
    return proposal["state"]


def search_lines(search: dict | None, level: str = "95%") -> list[str]:
    """The console text of the report's ``search``."""
    if not search:
        return []
    keys = " x ".join(f"{label} {low:g}..{high:g}{' (log)' if log else ''}" for label, low, high, log in
                      zip(search["labels"], search["low"], search["high"], search["log"]))
    states = {}
    for proposal in search["proposals"]:
        if proposal["state"] != "duplicate":
            states[proposal["state"]] = states.get(proposal["state"], 0) + 1
    seconds = "" if search["gpu_seconds"] is None else f", {search['gpu_seconds']:.0f} s of runs"
    grid_seconds = "" if search["grid_gpu_seconds"] is None else (
        f", {'~' if search['grid_seconds_estimated'] else ''}{search['grid_gpu_seconds']:.0f} s"
        + (" (estimated at the search's seconds per cell)" if search["grid_seconds_estimated"] else ""))
    halving = f"successive halving 1/{search['reduction']}" if search["reduction"] >= 2 else "no pruning"
    lines = [f"\n[{search['split']}] search {search['name']!r} at {search['light']} over {keys} ({search['sampler']} "
             f"sampler, {halving}, margin {search['prune_margin']:g}; {search['seeds_per_design']} seed(s) a design): "
             f"{sum(states.values())} designs ({', '.join(f'{n} {s}' for s, n in states.items())}), "
             f"{search['cells']} cells of a budget of {search['budget']}{seconds}; the grid it replaces "
             f"({search['grid']['description']}): {search['grid_cells']} cells{grid_seconds}"]
    warm = search["warm_start"]
    if warm["cameras"]:
        lines.append(f"  started from the learned design(s) of {', '.join(warm['cameras'])}: {warm['cells']} cells"
                     + ("" if warm["gpu_seconds"] is None else f", {warm['gpu_seconds']:.0f} s"))
    best = search["best"]
    lines.append(f"  best: {best['camera']} ({_values(best['values'])}): {interval_text(best['miou'])} over "
                 f"{best['cells']} cells" if best else "  best: none yet (no design complete)")
    width = max((len(p["camera"]) for p in search["proposals"]), default=0)
    for proposal in search["proposals"]:
        score = "-" if proposal["miou"] is None else interval_text(proposal["miou"])
        lines.append(f"  {proposal['number']:>3d} {proposal['camera']:<{width}s}  {proposal['source']:<16s} "
                     f"{_state(proposal)}: {score} ({proposal['cells']} cells)")
    return lines


def draw_proposals(axis, entry: dict, search: dict | None, places) -> bool:
    """Draw the search's designs on a sweep map's ``axis`` (`warpsense.study.maps.maps_figure`'s ``entry`` and its
    grid-position functions ``places``) where the map's keys are the search's first two and its light and split
    the search's: each design at its values, numbered, o complete, x pruned, the best starred. Returns whether it
    drew."""
    if not search or entry["parameters"] != search["parameters"][:2] or len(entry["parameters"]) != 2 \
            or entry["light"] != search["light"] or entry["split"] != search["split"] or None in places:
        return False
    for proposal in search["proposals"]:
        if proposal["state"] == "duplicate":
            continue
        x, y = (places[i](proposal["values"][key]) for i, key in enumerate(entry["parameters"]))
        best = search["best"] is not None and proposal["camera"] == search["best"]["camera"]
        marker = "*" if best else "x" if proposal["state"] == "pruned" else "o"
        axis.plot(x, y, marker, color="red" if best else "white", markeredgecolor="black",
                  markersize=14 if best else 8, zorder=5)
        axis.annotate(str(proposal["number"]), (x, y), textcoords="offset points", xytext=(5, 5), fontsize=7,
                      color="red", zorder=6)
    return True


def plot_search(record: dict, path: str | Path) -> bool:
    """Write the search's figure to ``path``: its designs over the first two searched keys (one key: score against
    the key), coloured by score, o complete, x pruned (at its last rung's mean), numbered in the order proposed, the
    best starred, the implied grid's points as small dots where it has no sweep. Returns False (nothing written)
    without a search or a scored design."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    search = record.get("search")
    if not search:
        return False
    shown = [p for p in search["proposals"] if p["state"] != "duplicate" and (p["miou"] is not None or p["rungs"])]
    if not shown:
        return False
    keys = search["parameters"][:2]
    score = {p["number"]: p["miou"]["mean"] if p["miou"] is not None else p["rungs"][-1]["mean"] for p in shown}
    figure, axis = plt.subplots(figsize=(6.5, 5.2))
    colours = plt.get_cmap("viridis")
    low, high = min(score.values()), max(score.values())
    span = (high - low) or 1.0
    if len(keys) == 2 and search["grid"]["source"] == "implied":
        grid = search["grid"]["values"]
        axis.scatter([a for a in grid[0] for _ in grid[1]], [b for _ in grid[0] for b in grid[1]], s=6,
                     color="lightgrey", label=f"grid it replaces ({search['grid_cells']} cells)")
    for proposal in shown:
        x = proposal["values"][keys[0]]
        y = proposal["values"][keys[1]] if len(keys) == 2 else score[proposal["number"]]
        best = search["best"] is not None and proposal["camera"] == search["best"]["camera"]
        marker = "*" if best else "x" if proposal["state"] == "pruned" else "o"
        axis.scatter([x], [y], marker=marker, s=220 if best else 60, color=colours((score[proposal["number"]] - low)
                                                                                   / span),
                     edgecolors="black" if marker != "x" else None, zorder=3)
        axis.annotate(str(proposal["number"]), (x, y), textcoords="offset points", xytext=(5, 5), fontsize=8)
    from matplotlib.ticker import FuncFormatter, NullFormatter

    for i in range(len(keys)):
        if search["log"][i]:
            scale = axis.xaxis if i == 0 else axis.yaxis
            (axis.set_xscale if i == 0 else axis.set_yscale)("log")
            scale.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))  # 2, not 2 x 10^0
            scale.set_minor_formatter(NullFormatter())
            if search["grid"]["source"] == "implied":
                (axis.set_xticks if i == 0 else axis.set_yticks)([float(f"{v:.3g}") for v in
                                                                  search["grid"]["values"][i]])
    axis.set_xlabel(keys[0])
    axis.set_ylabel(keys[1] if len(keys) == 2 else f"{search['split']} mIoU")
    mappable = plt.cm.ScalarMappable(cmap=colours, norm=plt.Normalize(low, high))
    figure.colorbar(mappable, ax=axis, label=f"{search['split']} mIoU (pruned: at its last rung)")
    best = search["best"]
    axis.set_title(f"search {search['name']} at {search['light']}: {search['cells']} cells (grid "
                   f"{search['grid_cells']})" + (f"; best {best['camera']} {best['miou']['mean']:.3f}" if best else ""),
                   fontsize=9)
    if len(keys) == 2 and search["grid"]["source"] == "implied":
        axis.legend(fontsize=7, loc="upper right")
    figure.suptitle("o complete, x pruned, * best; numbers: the order proposed", fontsize=9)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return True


def search_path(plot_path: str | Path) -> Path:
    """Where ``--plot OUT.png`` puts the search's figure: OUT_search.png."""
    plot_path = Path(plot_path)
    return plot_path.with_name(f"{plot_path.stem}_search{plot_path.suffix or '.png'}")
