"""Studies that choose their next cells from their finished ones: sequential verdicts (``study.sequential``: seeds
added to the comparisons that are unsettled) and a Bayesian search (``[[search]]``: designs proposed and trained
rung by rung, `warpsense.study.search`).

`run_adaptive` is a thin loop over the study's runner: each round is a list of cells that the command's runner
trains (this process, the local pool over the GPUs, or Slurm through ``--executor slurm --wait``), then the study
directory is read again to choose the next round. Nothing is kept in memory between rounds: the finished cells (and
the search's record) are the state, so an interrupted study, or one whose Slurm tasks were submitted without
``--wait``, goes on where its directory stands when the same command runs again.

For the report (`warpsense.study.report.study_record`): `plan_view` adds the search's designs to a recorded plan's
cameras, and `expected_cells` lists the cells a study needs so far (a sequential study's later seeds only where a
comparison went on; a search's designs only up to their rungs), so that a cell never needed is not "missing".
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from warpsense.study.plan import Cell, Plan
from warpsense.study.search import cell_score, read_search, search_cells, search_summary
from warpsense.study.sequential import judge, stop_text
from warpsense.study.study_dir import cell_state


def plan_only_notes(plan: Plan) -> list[str]:
    """What `--plan-only` says of an adaptive plan: which of its cells a scheduler of one's own cannot choose."""
    if plan.sequential is not None:
        rule = plan.sequential
        return [f"study.sequential: every cell's first {rule.min_seeds} seed(s) are needed; seeds "
                f"{', '.join(map(str, plan.seeds[rule.min_seeds:]))} only for comparisons still unsettled (interval "
                f"holding 0 and wider than +-{rule.tolerance:g}): `warpsense study run` chooses them"]
    if plan.search is not None:
        return [f"[[search]] {plan.search.name!r}: its designs are proposed from the finished cells by "
                "`warpsense study run` (budget "
                f"{plan.search.budget} cells); the commands below are the plan's own cells"]
    return []


def first_cells(plan: Plan) -> list[Cell]:
    """The cells every adaptive study trains first: a sequential plan's first ``min_seeds`` seeds of every cell; a
    search plan's own cells (its reference, the learned cameras the search starts from, any sweep)."""
    if plan.sequential is not None:
        seeds = set(plan.seeds[:plan.sequential.min_seeds])
        return [cell for cell in plan.cells() if cell.seed in seeds]
    return plan.cells()


def _scores(plan: Plan, out: Path, camera: str, light: str) -> dict:
    """A camera's finished cells' scores at ``light``, by (fold, seed)."""
    return {(cell.fold, cell.seed): cell_score(out, cell) for cell in plan.cells()
            if cell.camera == camera and cell.light == light and cell_state(out, cell) == "done"}


def sequential_judgements(plan: Plan, out: Path) -> list[dict]:
    """Each comparison of a sequential plan with its reference camera, judged from the finished cells
    (`warpsense.study.sequential.judge`, without the bootstrap: where a comparison stops depends on its paired
    interval alone): {"camera", "light", ...judge's record}."""
    judgements = []
    for light in plan.lights:
        cameras = [camera.name for camera in plan.cameras if not light.cameras or camera.name in light.cameras]
        reference = _scores(plan, out, plan.reference, light.name)
        for camera in cameras:
            if camera != plan.reference:
                scores = _scores(plan, out, camera, light.name)
                judgement = judge(plan.sequential, plan.seeds, plan.fold_names(), scores, reference)
                judgements.append({"camera": camera, "light": light.name, **judgement})
    return judgements


def _seed_cells(plan: Plan, camera: str, light: str, seeds) -> list[Cell]:
    return [Cell(camera, light, seed, fold) for seed in seeds for fold in plan.fold_names()]


def sequential_cells(plan: Plan, out: Path, say=None) -> list[Cell]:
    """The cells the unsettled comparisons need next (the camera's and the reference's of the next look's seeds),
    not finished, in plan order; none once every comparison has stopped."""
    wanted = set()
    unsettled = []
    for judgement in sequential_judgements(plan, out):
        if judgement["state"] == "unsettled":
            unsettled.append(judgement)
            for camera in (judgement["camera"], plan.reference):
                wanted.update(_seed_cells(plan, camera, judgement["light"], judgement["needs_seeds"]))
    cells = [cell for cell in plan.cells() if cell in wanted and cell_state(out, cell) != "done"]
    if cells and say is not None:
        stops = "; ".join(f"{j['camera']} at {j['light']}: {stop_text(j)}" for j in unsettled)
        say(f"study: sequential: {len(unsettled)} comparison(s) unsettled ({stops}): {len(cells)} cell(s)")
    return cells


def next_cells(plan: Plan, out: Path, say=None) -> tuple[Plan, list[Cell]]:
    """The next round: (the plan with the search's running designs, the cells to train); no cells when the study
    is complete."""
    first = [cell for cell in first_cells(plan) if cell_state(out, cell) != "done"]
    if first:
        return plan, first
    if plan.sequential is not None:
        return plan, sequential_cells(plan, out, say)
    if plan.search is not None:
        cells = search_cells(plan, out, say)
        return plan.with_designs(dict.fromkeys(cell.camera for cell in cells)), cells
    return plan, []


def run_adaptive(plan: Plan, out: Path, train: Callable[[Plan, list[Cell]], int], wait: bool = True,
                 say: Callable[[str], None] | None = None) -> int:
    """Train round after round until the study needs no more cells.

    Args:
        plan: a plan with ``study.sequential`` or a ``[[search]]``.
        out: the study directory.
        train: trains a round's cells of a plan (the command's runner: `warpsense.study.runner.run_cells`, or the
            Slurm executor) and returns its exit code.
        wait: go on after a round (False: one round, for Slurm without --wait: the command submits it and returns;
            run it again once the cells finish).
        say: a line of progress (default: print).

    Returns:
        0 when complete (or, without ``wait``, once a round is handed over), else the first round's non-zero code
        (a failed cell: the same command resumes it).
    """
    say = say or (lambda text: print(text, flush=True))
    out = Path(out)
    previous = None
    while True:
        round_plan, cells = next_cells(plan, out, say)
        if not cells:
            if plan.sequential is not None:
                stops = "; ".join(f"{j['camera']} at {j['light']}: {stop_text(j)}"
                                  for j in sequential_judgements(plan, out))
                say(f"study: sequential: every comparison has stopped ({stops})")
            elif plan.search is not None and (out / "search.json").is_file():
                say(f"study: {search_summary(plan, out)}")
            return 0
        if previous == set(cells):  # trained, yet not finished: the runner's answer was wrong
            say(f"study: the cells {', '.join(cell.id for cell in cells)} were trained but are not finished")
            return 1
        code = train(round_plan, cells)
        if code != 0:
            return code
        if not wait:
            say("study: this round is handed over; its later cells depend on these: run the same command again once "
                "they finish")
            return 0
        previous = set(cells)


def plan_view(study_dir: str | Path, plan: dict) -> dict:
    """A recorded plan (plan.json) with the search's designs that have cells among its cameras (as the report
    groups and compares cameras); the plan itself without a search."""
    if not plan.get("search"):
        return plan
    record = read_search(Path(study_dir))
    spec = Plan.from_dict(plan).search
    names = {camera["name"] for camera in plan["cameras"]}
    designs = []
    for design in record["designs"]:
        if design["state"] in ("duplicate", "waiting") or design["camera"] in names:
            continue
        names.add(design["camera"])
        values = spec.design_values(design["camera"])
        if values is None:
            continue
        designs.append({"name": design["camera"], "preset": spec.preset, "set": spec.overrides(values)})
    return {**plan, "cameras": [*plan["cameras"], *designs]}


def expected_cells(study_dir: str | Path, plan: dict) -> list[Cell]:
    """The cells a study needs so far, in plan order: every cell of a plain plan; a sequential plan's cells up to
    each comparison's current look (and any other cell begun); a search plan's own cells and each design's cells up
    to its rung. ``plan``: a recorded plan, with or without `plan_view`'s designs."""
    study_dir = Path(study_dir)
    spec = Plan.from_dict(plan)
    if spec.search is not None:  # the recorded plan's own cameras (plan_view adds the designs)
        own = tuple(camera for camera in spec.cameras if spec.search.design_values(camera.name) is None)
        spec = Plan.from_dict({**plan, "cameras": [c for c in plan["cameras"] if c["name"] in {x.name for x in own}]})
    if spec.sequential is not None:
        wanted = set(first_cells(spec))
        for judgement in sequential_judgements(spec, study_dir):
            seeds = judgement["needs_seeds"] if judgement["state"] == "unsettled" else judgement["seeds"]
            for camera in (judgement["camera"], spec.reference):
                wanted.update(_seed_cells(spec, camera, judgement["light"], seeds))
        return [cell for cell in spec.cells() if cell in wanted or cell_state(study_dir, cell) != "new"]
    if spec.search is None:
        return spec.cells()
    cells = spec.cells()
    rungs = spec.search.rungs(len(spec.fold_names()))
    for design in read_search(study_dir)["designs"]:
        if design["state"] in ("duplicate", "waiting"):
            continue
        decided = [rung["cells"] for rung in design.get("rungs", [])]
        size = decided[-1] if design["state"] in ("complete", "pruned") and decided else next(
            (rung for rung in rungs if rung not in decided), rungs[-1])
        cells += [cell for cell in spec.design_cells(design["camera"])[:size] if cell not in cells]
    return cells
