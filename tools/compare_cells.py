"""Per-cell results of two study directories side by side (issue 32: one plan run on one GPU and on several must
give the same cells; with `run.deterministic = true`, identical ones).

    python tools/compare_cells.py STUDY_A STUDY_B [--split val] [--json OUT]

For every cell finished in both (`runs/<cell>/evaluation.json`), its mIoU on the split in each and the difference,
then the largest |difference| and whether every cell is identical. Cells finished in only one are listed apart. A
directory without runs/, or an evaluation without the split, is a one-line error.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def cell_scores(study_dir: Path, split: str) -> dict[str, float]:
    """mIoU on ``split`` of every finished cell of a study directory, by run directory name."""
    runs = Path(study_dir) / "runs"
    if not runs.is_dir():
        raise ValueError(f"{study_dir}: no runs/ folder (not a study directory)")
    scores = {}
    for evaluation in sorted(runs.glob("*/evaluation.json")):
        splits = json.loads(evaluation.read_text()).get("splits", {})
        if split not in splits:
            raise ValueError(f"{evaluation}: no split {split!r} (it has {', '.join(splits) or 'none'})")
        scores[evaluation.parent.name] = float(splits[split]["miou"])
    return scores


def compare(first: dict[str, float], second: dict[str, float]) -> dict:
    """The cells of both with their difference (second - first), the largest |difference|, and the cells of one."""
    both = sorted(set(first) & set(second))
    cells = [{"cell": name, "a": first[name], "b": second[name], "difference": second[name] - first[name]}
             for name in both]
    largest = max((abs(cell["difference"]) for cell in cells), default=0.0)
    return {"cells": cells, "max_abs_difference": largest, "identical": bool(cells) and largest == 0.0,
            "only_a": sorted(set(first) - set(second)), "only_b": sorted(set(second) - set(first))}


def render(record: dict, a: str, b: str, split: str) -> str:
    lines = [f"{split} mIoU per cell: A = {a}, B = {b}", f"{'cell':<34} {'A':>8} {'B':>8} {'B - A':>9}"]
    lines += [f"{c['cell']:<34} {c['a']:>8.4f} {c['b']:>8.4f} {c['difference']:>+9.4f}" for c in record["cells"]]
    verdict = "identical" if record["identical"] else f"largest |B - A| {record['max_abs_difference']:.4f}"
    lines.append(f"{len(record['cells'])} cell(s) in both: {verdict}")
    for side in ("a", "b"):
        if record[f"only_{side}"]:
            lines.append(f"only in {side.upper()}: {', '.join(record[f'only_{side}'])}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("study_a", type=Path)
    parser.add_argument("study_b", type=Path)
    parser.add_argument("--split", default="val", help="the split compared (default: %(default)s)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the comparison as JSON")
    args = parser.parse_args(argv)
    try:
        record = compare(cell_scores(args.study_a, args.split), cell_scores(args.study_b, args.split))
    except (ValueError, json.JSONDecodeError) as error:
        print(f"compare_cells: {error}".splitlines()[0], file=sys.stderr)
        return 2
    print(render(record, str(args.study_a), str(args.study_b), args.split))
    if args.json:
        args.json.write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
