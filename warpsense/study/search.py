"""A Bayesian search over a plan's ``[[search]]`` design space: designs proposed by Optuna, trained as ordinary cells
by the study's runner, clearly losing designs stopped early by successive halving over their cells.

Round by round (`search_cells`, called by `warpsense.study.adaptive`):

1. Each design whose next rung of cells is finished is decided: a design's cells go in a fixed order (seed by seed,
   fold by fold: `warpsense.study.plan.Plan.design_cells`), its rungs are the first 1, r, r^2, ... of them (r =
   ``reduction``) and then all; at a rung it goes on only if its mean over the rung's cells is in the top 1/r of the
   designs that have reached that rung (asynchronous successive halving, Li et al. 2020, "A System for Massively
   Parallel Hyperparameter Tuning", MLSys), or within ``prune_margin`` of that rung's best; otherwise it is pruned and
   its other cells are never trained. Every design is judged on the same first cells (one fold of one seed), so the
   rung's means compare designs, not folds. A design with all its cells is complete: its score is their mean.
2. The search is warm-started once: the ``start`` designs, then each ``learned`` camera's learned design (the plan
   camera that learns the searched keys by gradient: the mean over its runs, geometric for a log-scaled key, of the
   learned values in each run's evaluation "camera" record; keys it does not learn at its config's value), rounded to
   the search's digits.
3. While fewer than ``batch`` designs are running and the budget holds another whole design (cells trained plus
   those reserved for the running designs' remaining rungs), the next design is proposed: a warm-start design not
   yet tried, else Optuna's sampler (`SAMPLERS`) fitted to every design so far: complete ones with their score,
   pruned ones with their rung's mean shifted by the mean gap between rung and final score of the complete designs
   (so the sampler learns where designs lose, which Optuna's GP sampler would otherwise not see), running ones as
   running (the GP's batch acquisition spreads a batch out).
4. The running designs' next rungs are the round's cells.

Why Optuna's GPSampler by default: a search here has 5-25 designs in 2-4 continuous keys, where a Gaussian process
with log expected improvement is the sample-efficient choice (TPE needs tens of trials before its densities say
much); Optuna 5's GPSampler is seeded, proposes batches with the running designs in view (qLogEI), and installs with
pip alone (Ax/BoTorch would add a heavier stack for the same model). ``sampler = "tpe"`` takes multivariate TPE.

Why rungs of cells rather than of epochs: stopping a run at an epoch needs the training loop to stop on request,
which it does not (a run trains its planned epochs); a design's cells (folds, seeds) are the units the runner, the
local pool and Slurm already train, resume and count, and the budget is in cells. docs/results.md measures how well a
design's first cell ranks designs, and how well early epochs would.

The search's state is the study directory: `SEARCH_RECORD` lists the designs in the order proposed, with their source,
state and rung decisions (written atomically whenever it changes), and the cells' run directories hold their scores.
The Optuna study is rebuilt from them at every proposal, its sampler seeded with ``seed`` + the designs so far, so an
interrupted search resumes where its directory stands and proposes what it would have proposed.
"""

from __future__ import annotations

import contextlib
import logging
import math
import warnings
from pathlib import Path

from warpsense.files import write_json
from warpsense.study.keys import LEARNED_KEYS
from warpsense.study.plan import Cell, Plan, PlanError
from warpsense.study.study_dir import StudyDir, cell_state, read_evaluation, read_record, run_dir
from warpsense.train.run_dir import RunDir

SEARCH_RECORD = StudyDir.SEARCH
"""The study directory's record of its search: the designs in the order proposed."""

SAMPLERS = ("gp", "tpe")

PROPOSAL_TRIES = 5
"""Proposals asked for a new design before the search stops for want of one (each rounded proposal that names a
design already tried is given to the sampler as that design and asked again)."""


def require_optuna() -> None:
    """A ValueError saying what to install where Optuna is missing (a plan with a [[search]] needs it)."""
    try:
        import optuna  # noqa: F401
    except ImportError:
        raise ValueError("a plan with a [[search]] proposes designs with Optuna, which is not installed: "
                         "pip install -e \".[search]\" (or pip install optuna)") from None


def judged_split(evaluation: dict) -> str:
    """The split a cell is judged on: "heldout" with folds, else "val" (else the first)."""
    splits = evaluation["splits"]
    return "heldout" if "heldout" in splits else "val" if "val" in splits else next(iter(splits))


def cell_score(out: Path, cell: Cell) -> float:
    """A finished cell's score: mIoU of its judged split."""
    evaluation = read_evaluation(out, cell)
    return float(evaluation["splits"][judged_split(evaluation)]["miou"])


def read_search(out: Path) -> dict:
    """The study directory's `SEARCH_RECORD` ({"designs": [], "warm_started": false} before the first round); a one-line
    PlanError naming the file where it is damaged."""
    path = StudyDir(out).search
    if not path.is_file():
        return {"designs": [], "warm_started": False}
    record = read_record(path, dict)
    designs = record.get("designs")
    if not isinstance(designs, list) or not all(isinstance(d, dict) and isinstance(d.get("camera"), str)
                                                 and isinstance(d.get("values"), list) for d in designs):
        raise PlanError(f"{path}: designs: expected a list of designs (camera, values, ...); delete the file to start "
                        "the search again (its trained cells are kept)")
    return record


def _write(out: Path, record: dict) -> None:
    write_json(StudyDir(out).search, record)


def _done(plan: Plan, out: Path, design: dict) -> int:
    """How many of a design's cells, in rung order, are finished without a gap."""
    count = 0
    for cell in plan.design_cells(design["camera"]):
        if cell_state(out, cell) != "done":
            break
        count += 1
    return count


def _rung_mean(plan: Plan, out: Path, design: dict, size: int) -> float:
    return sum(cell_score(out, cell) for cell in plan.design_cells(design["camera"])[:size]) / size


def _decide(plan: Plan, out: Path, record: dict, say) -> bool:
    """Decide every running design whose next rung is finished (prune, go on, or complete); True where any changed."""
    spec, folds = plan.search, len(plan.fold_names())
    rungs, cost = spec.rungs(folds), spec.design_cost(folds)
    changed = False
    for design in record["designs"]:
        if design["state"] != "running":
            continue
        done = _done(plan, out, design)
        decided = {rung["cells"] for rung in design["rungs"]}
        for size in rungs:
            if size > done or size in decided:
                continue
            mean = _rung_mean(plan, out, design, size)
            changed = True
            if size == cost:
                design["value"], design["state"] = mean, "complete"
                design["rungs"].append({"cells": size, "mean": mean})
                _announce(say, design, f"complete: {mean:.4f} over {size} cell(s)")
                break
            rivals = [other for other in record["designs"] if other is not design
                      and other["state"] != "duplicate" and _done(plan, out, other) >= size]
            means = sorted([mean, *(_rung_mean(plan, out, other, size) for other in rivals)], reverse=True)
            rank = means.index(mean) + 1
            kept = rank <= max(1, math.ceil(len(means) / spec.reduction)) or means[0] - mean <= spec.prune_margin
            design["rungs"].append({"cells": size, "mean": mean, "rank": rank, "of": len(means), "best": means[0],
                                    "kept": kept})
            if not kept:
                design["state"] = "pruned"
                _announce(say, design, f"pruned after {size} cell(s): {mean:.4f}, rank {rank} of {len(means)} "
                                       f"(best {means[0]:.4f})")
                break
    return changed


def _committed(plan: Plan, out: Path, record: dict) -> int:
    """Cells the search has spent or holds: a complete or pruned design's cells up to its last rung, a running one's
    whole cost (every started design can complete within the budget)."""
    cost = plan.search.design_cost(len(plan.fold_names()))
    return sum(cost if design["state"] == "running" else design["rungs"][-1]["cells"]
               for design in record["designs"] if design["state"] not in ("duplicate", "waiting")
               and not design.get("known"))


def learned_design(plan: Plan, out: Path, camera: str) -> tuple[float, ...]:
    """A learned camera's design in the search's keys: per key the mean over its finished runs at the search's
    light (geometric for a log-scaled key) of the learned value its evaluation records, or of its config's value for
    a key it does not learn; a PlanError naming the camera where none of its runs is finished."""
    spec = plan.search
    cells = [cell for cell in plan.cells() if cell.camera == camera and cell.light == spec.light
             and cell_state(out, cell) == "done"]
    if not cells:
        raise PlanError(f"{plan.source}: search[0].learned: {camera!r} has no finished run at {spec.light!r} to "
                        "start the search from")
    values = []
    for key, log in zip(spec.parameters, spec.log):
        section, name = key.split(".", 1)
        samples = []
        for cell in cells:
            config = read_record(StudyDir(out).run(cell).config, dict)
            learned = read_evaluation(out, cell).get("camera", {})
            flag, field = LEARNED_KEYS.get(key, (None, None))
            learns = flag is not None and config.get(flag.split(".")[0], {}).get(flag.split(".")[1]) is True
            value = learned.get(field) if learns else config.get(section, {}).get(name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                where = f"{RunDir.EVALUATION} camera.{field}" if learns else f"{RunDir.CONFIG} {key}"
                raise PlanError(f"{run_dir(out, cell)}: {where}: expected a number to start the search from, got "
                                f"{value!r}")
            samples.append(float(value))
        if log:
            values.append(math.exp(sum(math.log(max(v, 1e-12)) for v in samples) / len(samples)))
        else:
            values.append(sum(samples) / len(samples))
    return spec.rounded(values)


def known_design(plan: Plan, out: Path, camera: str) -> tuple[float, ...]:
    """A plan camera's design in the search's keys: its config's values (as its first finished run resolved them)."""
    spec = plan.search
    cell = next((cell for cell in plan.design_cells(camera) if cell_state(out, cell) == "done"), None)
    if cell is None:
        raise PlanError(f"{plan.source}: search[0].known: {camera!r} has no finished run at {spec.light!r} to start "
                        "the search from")
    config = read_record(StudyDir(out).run(cell).config, dict)
    values = []
    for key in spec.parameters:
        section, name = key.split(".", 1)
        value = config.get(section, {}).get(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise PlanError(f"{StudyDir(out).run(cell).config}: {key}: expected a number, got {value!r}")
        values.append(float(value))
    return tuple(values)


def _warm_start(plan: Plan, out: Path, record: dict) -> None:
    """Once: the known cameras as designs already trained (their own cells: no cell of the budget), then the start
    designs and the learned cameras' designs queued ("waiting"), skipping any already listed."""
    spec = plan.search
    for camera in spec.known:
        if not any(design["camera"] == camera for design in record["designs"]):
            record["designs"].append({"number": len(record["designs"]) + 1, "camera": camera,
                                      "values": list(known_design(plan, out, camera)), "source": f"camera:{camera}",
                                      "state": "running", "rungs": [], "value": None, "known": True})
    wanted = [(tuple(point), "start") for point in spec.start]
    wanted += [(learned_design(plan, out, camera), f"learned:{camera}") for camera in spec.learned]
    for values, source in wanted:
        values = spec.rounded(values)
        camera = spec.camera(values)
        if any(design["camera"] == camera for design in record["designs"]):
            continue
        record["designs"].append({"number": len(record["designs"]) + 1, "camera": camera, "values": list(values),
                                  "source": source, "state": "waiting", "rungs": [], "value": None})
    record["warm_started"] = True


def _estimated_values(plan: Plan, out: Path, record: dict) -> dict[str, float]:
    """Each decided design's value for the sampler: a complete design's score; a pruned one's last rung mean plus
    the mean gap (final score minus that rung's mean) of the complete designs (0 before any completes)."""
    complete = [design for design in record["designs"] if design["state"] == "complete"]
    values = {design["camera"]: design["value"] for design in complete}
    for design in record["designs"]:
        if design["state"] != "pruned":
            continue
        last = design["rungs"][-1]
        gaps = [other["value"] - _rung_mean(plan, out, other, last["cells"]) for other in complete]
        values[design["camera"]] = last["mean"] + (sum(gaps) / len(gaps) if gaps else 0.0)
    return values


@contextlib.contextmanager
def _quiet_optuna():
    """Optuna's info logs and experimental warnings off while it proposes (the study's lines say what happened)."""
    import optuna

    verbosity = optuna.logging.get_verbosity()
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    logger = logging.getLogger("optuna")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield optuna
    finally:
        optuna.logging.set_verbosity(verbosity)
        logger.setLevel(level)


def propose(plan: Plan, out: Path, record: dict, extra: list[tuple[float, ...]] = ()) -> tuple[float, ...]:
    """The sampler's next design (not rounded), given every design of ``record`` (complete and pruned ones with
    their value, `_estimated_values`; the others as running) and ``extra`` designs proposed already in this round
    (running)."""
    spec = plan.search
    values = _estimated_values(plan, out, record)
    with _quiet_optuna() as optuna:
        from optuna.distributions import FloatDistribution
        from optuna.trial import TrialState, create_trial

        distributions = {key: FloatDistribution(low, high, log=log)
                         for key, low, high, log in zip(spec.parameters, spec.low, spec.high, spec.log)}
        seed = spec.seed + len(record["designs"]) + len(extra)
        if spec.sampler == "tpe":
            sampler = optuna.samplers.TPESampler(seed=seed, multivariate=True, n_startup_trials=3,
                                                 constant_liar=True)
        else:
            sampler = optuna.samplers.GPSampler(seed=seed, n_startup_trials=2)
        study = optuna.create_study(direction="maximize", sampler=sampler)
        seen = set()
        for design in record["designs"]:
            if design["camera"] in seen:
                continue
            seen.add(design["camera"])
            params = dict(zip(spec.parameters, design["values"]))
            if design["camera"] in values:
                study.add_trial(create_trial(params=params, distributions=distributions,
                                             value=values[design["camera"]]))
            else:
                study.add_trial(create_trial(params=params, distributions=distributions, state=TrialState.RUNNING))
        for point in extra:
            study.add_trial(create_trial(params=dict(zip(spec.parameters, point)), distributions=distributions,
                                         state=TrialState.RUNNING))
        trial = study.ask(distributions)
        return tuple(float(trial.params[key]) for key in spec.parameters)


def _announce(say, design: dict, how: str) -> None:
    values = ", ".join(f"{v:g}" for v in design["values"])
    say(f"study: search: design {design['number']} {design['camera']} ({values}) {how}")


def search_cells(plan: Plan, out: Path, say=None) -> list[Cell]:
    """One round of the search: decide the designs whose rungs finished, warm-start once, start designs up to
    ``batch`` running within the budget, record it all (`SEARCH_RECORD`), and return the cells to train next (the
    running designs' next rungs); none when the search is over.

    A design's states: "waiting" (a warm-start design not started yet), "running" (its rungs are being trained),
    "complete", "pruned", "duplicate" (a proposal that rounded to a design tried already: recorded, not trained)."""
    say = say or (lambda text: print(text, flush=True))
    out = Path(out)
    spec = plan.search
    folds = len(plan.fold_names())
    cost, rungs = spec.design_cost(folds), spec.rungs(folds)
    record = read_search(out)
    while True:
        changed = _decide(plan, out, record, say)
        if not record.get("warm_started"):
            _warm_start(plan, out, record)
            changed = True
        if changed:  # a known camera decided above may complete at once: decide before starting others
            changed = _decide(plan, out, record, say) or True
        running = [design for design in record["designs"] if design["state"] == "running"
                   and not design.get("known")]
        while len(running) < spec.batch and _committed(plan, out, record) + cost <= spec.budget:
            waiting = [design for design in record["designs"] if design["state"] == "waiting"]
            if waiting:
                design = waiting[0]
                design["state"] = "running"
                _announce(say, design, f"started ({design['source']})")
            else:
                design = _proposed(plan, out, record, say)
                if design is None:
                    break
            running.append(design)
            changed = True
        if changed:
            _write(out, record)
        cells = [cell for design in record["designs"]  # a decided design's lost cell (deleted to retrain it)
                 if design["state"] in ("complete", "pruned") and not design.get("known")
                 for cell in plan.design_cells(design["camera"])[:design["rungs"][-1]["cells"]]
                 if cell_state(out, cell) != "done"]
        for design in running:
            done = _done(plan, out, design)
            target = next((size for size in rungs if size > done), cost)
            cells += [cell for cell in plan.design_cells(design["camera"])[:target] if cell_state(out, cell) != "done"]
        if cells or not running:
            return cells
        # every running design's next rung is finished already (copied in, or an interrupted round): decide again


def _proposed(plan: Plan, out: Path, record: dict, say) -> dict | None:
    """A new running design from the sampler (appended to ``record``); None where the sampler proposes only
    designs tried already (`PROPOSAL_TRIES` times)."""
    spec = plan.search
    for _ in range(PROPOSAL_TRIES):
        values = spec.rounded(propose(plan, out, record))
        camera = spec.camera(values)
        earlier = next((d for d in record["designs"] if d["camera"] == camera), None)
        entry = {"number": len(record["designs"]) + 1, "camera": camera, "values": list(values),
                 "source": "sampler", "state": "running", "rungs": [], "value": None}
        if earlier is None:
            record["designs"].append(entry)
            _announce(say, entry, f"proposed by the {spec.sampler} sampler")
            return entry
        # the rounded proposal is a design tried already: recorded as asked (the sampler sees that design once)
        record["designs"].append({**entry, "state": "duplicate", "duplicate_of": earlier["number"]})
    say(f"study: search: the sampler proposed only designs tried already ({PROPOSAL_TRIES} times, at "
        f"{spec.digits} significant digits); no new design")
    return None


def search_summary(plan: Plan, out: Path) -> str:
    """One line: designs by state, cells trained, the best complete design."""
    record = read_search(out)
    designs = [d for d in record["designs"] if d["state"] != "duplicate"]
    states = {state: sum(d["state"] == state for d in designs) for state in ("complete", "pruned", "running",
                                                                            "waiting")}
    trained = sum(_done(plan, out, d) for d in designs if not d.get("known"))
    complete = [d for d in designs if d["state"] == "complete"]
    best = max(complete, key=lambda d: d["value"], default=None)
    said = ", ".join(f"{count} {state}" for state, count in states.items() if count)
    line = f"search: {len(designs)} designs ({said}), {trained} cells of a budget of {plan.search.budget}"
    if best is not None:
        line += f"; best {best['camera']} {best['value']:.4f}"
    return line
