"""A study's folds cut from its data: the frames each fold trains on and is judged on (``folds = "blocks"``: a
block of every sequence held out, with a buffer; ``"sequence"``: one held-out sequence each; ``"none"``: the train
and val splits), said in words, and the held-out sequences a ``folds = "sequence"`` plan takes. Reads file lists
only; a fold that holds no frame is a `PlanError` naming it."""

from __future__ import annotations

import dataclasses

from warpsense.config import ConfigError, load_config, parse_override
from warpsense.data import DatasetError, sequence_names
from warpsense.study.plan_model import Cell, Plan, PlanError, cell_overrides, fill_placeholders, plain_name


def _base_data(plan: Plan):
    """The data section of the plan's base config with the study's and the command line's overrides (what the folds
    are cut from), any placeholder left empty; a PlanError naming the key or file where it does not resolve."""
    unfilled = Cell("", "", 0, "")
    overrides = [fill_placeholders(text, unfilled) for text in [*plan.set, *cell_overrides(plan.overrides)]]
    try:
        return load_config([plan.base] if plan.base else None, overrides).data
    except ConfigError as error:
        raise PlanError(f"{plan.source}: {error}") from None


def fold_sizes(plan: Plan) -> list[dict]:
    """Per fold of the plan: {"fold", "train" (frames it trains on), "judged" (frames it is judged on), "labelled"
    (frames of the labelled splits: train_split + val_split)}, from the base config's data (file lists only; before
    ``max_train_images`` and ``max_val_images``). Without folds, one row "" of the train and val splits. A fold that
    judges no frame or trains on none is a PlanError naming it."""
    from warpsense.data import build_dataset, fold_frames

    data = _base_data(plan)
    rows = []
    try:
        if plan.folds == "none":
            train = len(build_dataset(data, data.train_split, train=True, seed=0))
            judged = len(build_dataset(data, data.val_split, train=False, seed=0))
            return [{"fold": "", "train": train, "judged": judged, "labelled": train + judged}]
        for fold in plan.fold_names():
            keys = dict(_assignment(text) for text in plan.fold_overrides(fold))
            train, held = fold_frames(dataclasses.replace(data, **keys))
            rows.append({"fold": fold, "train": len(train), "judged": len(held),
                         "labelled": len(train.sources[0]) + len(train.sources[1])})
    except DatasetError as error:
        where = f"study.folds = {plan.folds!r}" + (f", fold {fold}" if plan.folds != "none" else "")
        raise PlanError(f"{plan.source}: {where}: data: {error}") from None
    return rows


def _assignment(text: str) -> tuple[str, object]:
    """"data.key=value" as (key, the parsed value)."""
    return next(iter(parse_override(text)["data"].items()))


def fold_lines(rows: list[dict]) -> list[str]:
    """`fold_sizes`' rows in words: "fold block1: train 372 frames (79% of the labelled frames), judge 93 frames"."""
    return [f"{'fold ' + row['fold'] if row['fold'] else 'no folds (the train split; judged on val)'}: train "
            f"{row['train']} frames ({row['train'] / max(row['labelled'], 1):.0%} of the labelled frames), judge "
            f"{row['judged']} frames" for row in rows]


def fold_sequences(plan: Plan, wanted: list) -> tuple[str, ...]:
    """The held-out sequences of a ``folds = "sequence"`` plan: ``wanted`` (study.sequences) or every sequence of
    the base config's labelled splits (train_split + val_split), checked against the frames."""
    where = f"{plan.source}: study.folds"
    data = _base_data(plan)  # the config's own errors (a bad --set, a missing data root) name their key or file
    try:
        names = sequence_names(data)
    except DatasetError as error:
        raise PlanError(f"{plan.source}: data: {error} (study.folds = \"sequence\" lists the labelled splits' "
                        "sequences)") from None
    if len(names) < 2:
        raise PlanError(f"{where}: the labelled splits ({data.train_split}, {data.val_split}) hold "
                        f"{len(names)} sequence(s) ({', '.join(names)}): a fold needs others to train on")
    if not all(isinstance(name, str) for name in wanted) or len(set(wanted)) != len(wanted):
        raise PlanError(f"{plan.source}: study.sequences: expected distinct sequence names, got {wanted!r}")
    for name in wanted:
        if name not in names:
            raise PlanError(f"{plan.source}: study.sequences: {name!r} holds no frame of the labelled splits "
                            f"({data.train_split}, {data.val_split}); sequences: {', '.join(names)}")
    chosen = tuple(wanted) or tuple(names)
    for name in chosen:
        if not name or not plain_name(name):
            raise PlanError(f"{where}: sequence {name!r} cannot name a cell (no '/', '.' or spaces at the ends)")
    return chosen
