"""The report's side of sequential verdicts (`warpsense.study.sequential`): a comparison judged at the look where
the rule stopped, and the report's lines on where each stopped."""

from __future__ import annotations

from warpsense.study.plan import Plan
from warpsense.study.sequential import NOT_DISTINGUISHABLE, SequentialRule, judge, stop_text
from warpsense.study.statistics import LEVEL, block_bootstrap_difference


def judged_comparison(plan: dict, runs: dict, reference: dict, sequences: dict, block: int,
                      resamples: int) -> dict | None:
    """A report's comparison under ``study.sequential`` (None for a plan without): the camera's and the reference's
    runs of one split, by (fold, seed), judged where the rule stopped (`judge`), the bootstrap over that look's
    pairs (`warpsense.study.statistics.block_bootstrap_difference`, frames drawn in blocks within ``sequences``).

    Returns the fields that replace the fixed rule's: {"paired" (the repeated interval), "bootstrap", "verdict",
    "sequential": the judgement's state, stop, look, pairs, seeds, nominal level, looks, tolerance and history}; the
    fixed rule's intervals are kept (and the verdict is "not distinguishable") before the first look is complete."""
    if not plan.get("sequential"):
        return None

    def bootstrap(keys: list) -> dict:
        pairs = [(runs[key]["image_counts"], reference[key]["image_counts"], key[0]) for key in keys]
        return block_bootstrap_difference(pairs, sequences, block, resamples)

    judgement = judge(SequentialRule.from_dict(plan["sequential"]), tuple(plan["seeds"]),
                      Plan.from_dict(plan).fold_names(), {key: run["miou"] for key, run in runs.items()},
                      {key: run["miou"] for key, run in reference.items()}, bootstrap)
    summary = {key: judgement[key] for key in ("state", "stop", "look", "pairs", "seeds", "needs_seeds",
                                                "nominal_level", "looks", "tolerance", "min_seeds", "max_seeds",
                                                "history")}
    summary["text"] = stop_text(judgement)
    if not judgement["look"]:
        return {"verdict": NOT_DISTINGUISHABLE, "sequential": summary}
    return {"paired": judgement["paired"], "bootstrap": judgement["bootstrap"], "verdict": judgement["verdict"],
            "sequential": summary}


def sequential_lines(split: str, part: dict, level: float = LEVEL) -> list[str]:
    """The report's lines on where each comparison of ``part`` stopped (none without study.sequential)."""
    comparisons = [c for c in part["comparisons"] if c.get("sequential")]
    if not comparisons:
        return []
    first = comparisons[0]["sequential"]
    lines = [f"[{split}] sequential verdicts: {first['min_seeds']}..{first['max_seeds']} seeds, another seed while the "
             f"interval holds 0 and is wider than +-{first['tolerance']:g}; the paired interval above is the "
             f"repeated {level:.0%} interval of the look where it stopped (Pocock-type, t at nominal level "
             f"{first['nominal_level']:.4f} at each of {len(first['looks'])} looks)"]
    width = max(len(c["camera"]) for c in comparisons)
    lines += [f"  {c['light']:>8s}  {c['camera']:<{width}s}  {c['sequential']['text']}" for c in comparisons]
    return lines
