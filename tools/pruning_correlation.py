"""How early archived studies rank their cameras as their final scores do (warpsense.study.early_ranks): the
measurement behind pruning designs early in a search, docs/results.md's table.

    python tools/pruning_correlation.py                 # every docs/records/*/*_runs.tar.xz
    python tools/pruning_correlation.py ARCHIVE_OR_STUDY_DIR... --margin 0.02 --json ranks.json

Prints, per early point of a run (10% .. 75% of its epochs), the median (and lowest) Spearman rank correlation
between the validation mIoU there and the final score, across a study fold's cells and across its cameras' means;
then per study the correlation between each camera's first cell (the first rung of a search's successive halving)
and its mean over all cells, and whether the camera that ends best passes that first rung.
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

from warpsense.study.archives import archive_cells
from warpsense.study.early_ranks import cell_ranks, epoch_ranks

ROOT = Path(__file__).resolve().parents[1]


def _value(summary: dict) -> str:
    if summary["median"] is None:
        return "-"
    return f"{summary['median']:+.2f} (lowest {summary['min']:+.2f}, {summary['groups']} groups)"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("archives", nargs="*", help="study archives (.tar.xz) or study directories (default: "
                        "docs/records/*/*_runs.tar.xz)")
    parser.add_argument("--reduction", type=int, default=3, help="the first rung keeps the top 1/N (default 3)")
    parser.add_argument("--margin", type=float, default=0.0, help="... or those within this of its best")
    parser.add_argument("--json", metavar="OUT")
    args = parser.parse_args(argv)
    archives = args.archives or sorted(glob.glob(str(ROOT / "docs" / "records" / "*" / "*_runs.tar.xz")))
    if not archives:
        print("pruning_correlation: no archives", file=sys.stderr)
        return 2
    rows = archive_cells(archives, metrics=True)
    epochs = epoch_ranks(rows)
    cells = cell_ranks(rows, reduction=args.reduction, margin=args.margin)
    print(f"{len(rows)} cells of {len({(r['archive'], r['directory']) for r in rows})} study directories")
    print("\n| point of the run | epochs used (0-based) | Spearman, cells vs final "
          "| Spearman, cameras' means vs final |")
    print("|---|---|---|---|")
    for row in epochs:
        print(f"| {row['fraction']:.0%} | {', '.join(map(str, row['epochs_at']))} | {_value(row['cells'])} | "
              f"{_value(row['cameras'])} |")
    print(f"\nfirst cell vs the camera's mean over all its cells: {_value(cells['first_cell'])}; first fold's mean "
          f"vs all folds': {_value(cells['first_fold'])}; the best camera passes a first rung keeping the top "
          f"1/{args.reduction} (or within {args.margin:g}) in {cells['best_kept']} of {len(cells['studies'])} studies")
    print("| study | cameras | folds | first cell | first fold | best camera's rank at the first cell |")
    print("|---|---|---|---|---|---|")
    for study in cells["studies"]:
        fold = "-" if study["first_fold"] is None else f"{study['first_fold']:+.2f}"
        cell = "-" if study["first_cell"] is None else f"{study['first_cell']:+.2f}"
        print(f"| {study['study']} | {study['cameras']} | {study['folds']} | {cell} | {fold} | {study['best_rank']}"
              f"{' (kept)' if study['best_kept'] else ' (pruned)'} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"epochs": epochs, "cells": cells}, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
