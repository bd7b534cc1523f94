"""The verdict rules' false-verdict rate with the same camera twice (A/A), from the measured seed variance of archived
studies (warpsense.study.false_verdicts): docs/results.md's table.

    python tools/aa_simulation.py                       # every docs/records/*/*_runs.tar.xz, 200,000 A/A studies a row
    python tools/aa_simulation.py ARCHIVE_OR_STUDY_DIR... --replicates 20000 --json aa.json

It prints the measured within-fold seed spread (which archives and study directories, how many runs), then per row
(A/A data: normal with the measured standard deviation, or the measured residuals resampled; 1, 3 or 5 folds) the
false-verdict rate of the fixed rule at min_seeds and max_seeds, of the fixed interval looked at after every seed, and
of the sequential rule, and the bound on it for any stopping time (its repeated interval excluding 0 at some look);
then the sequential rule's stopping times for 5 block folds with the resampled residuals.
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

from scipy import stats

from warpsense.study.false_verdicts import (
    archive_scores,
    normal_differences,
    resampled_by_fold,
    resampled_differences,
    seed_residuals,
    simulate,
    standard_error,
    table_lines,
    to_json,
)
from warpsense.study.sequential import SequentialRule

ROOT = Path(__file__).resolve().parents[1]

BY_FOLD_RUNS = 50
"""The folds whose residuals are resampled fold by fold: those measured on at least this many runs (the archived drive
folds 0001TP, 0006R0 and 0016E5; a block fold's few runs are pooled with the rest)."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("archives", nargs="*", help="study archives (.tar.xz) or study directories (default: "
                        "docs/records/*/*_runs.tar.xz)")
    parser.add_argument("--min-seeds", type=int, default=3)
    parser.add_argument("--max-seeds", type=int, default=8)
    parser.add_argument("--tolerance", type=float, default=0.01, help="the sequential rule's (mIoU)")
    parser.add_argument("--replicates", type=int, default=200_000, help="simulated A/A studies a row")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", metavar="OUT", help="write the measurements and every row's result")
    args = parser.parse_args(argv)
    archives = args.archives or sorted(glob.glob(str(ROOT / "docs" / "records" / "*" / "*_runs.tar.xz")))
    if not archives:
        print("aa_simulation: no archives", file=sys.stderr)
        return 2
    measured = seed_residuals(archive_scores(archives))
    residuals = measured["residuals"]
    print(f"within-fold seed spread of one camera's mIoU: sd {measured['sd']:.4f} over {measured['groups']} (camera, "
          f"fold) groups, {measured['runs']} runs; an A/A pair's difference: sd {measured['sd'] * 2 ** 0.5:.4f}")
    print(f"  residuals: excess kurtosis {stats.kurtosis(residuals):.2f}, skewness {stats.skew(residuals):+.2f}; by "
          "fold: " + ", ".join(f"{fold or '-'} {values.std(ddof=0):.4f} ({len(values)})"
                               for fold, values in sorted(measured["by_fold"].items())))
    if measured["paired_sd"] is not None:
        print(f"  two cameras of one study at the same seed: paired-difference sd {measured['paired_sd']:.4f} "
              f"({measured['paired_groups']} pairs of cameras)")
    print("  runs used: " + ", ".join(f"{name} {count}" for name, count in measured["directories"].items()))
    rule = SequentialRule(args.min_seeds, args.max_seeds, args.tolerance)
    wide = {fold: values for fold, values in measured["by_fold"].items() if len(values) >= BY_FOLD_RUNS}
    rows = []
    for label, draw, folds in (
            ("normal, measured sd", normal_differences(measured["sd"]), 1),
            ("normal, measured sd", normal_differences(measured["sd"]), 3),
            ("normal, measured sd", normal_differences(measured["sd"]), 5),
            ("measured residuals, resampled", resampled_differences(residuals), 1),
            ("measured residuals, resampled", resampled_differences(residuals), 3),
            ("measured residuals, resampled", resampled_differences(residuals), 5),
            *([("each drive fold's own residuals", resampled_by_fold(wide), len(wide))] if len(wide) > 1 else [])):
        rows.append((label, simulate(draw, folds, rule, args.replicates, args.seed)))
    print(f"\nrule: fixed 95% paired t interval; sequential {rule.min_seeds}..{rule.max_seeds} seeds, tolerance "
          f"+-{rule.tolerance:g}; {args.replicates} A/A studies a row (s.e. of a 5% rate "
          f"{standard_error(0.05, args.replicates):.4f})")
    print("\n".join(table_lines(rows)))
    headline = next(result for label, result in rows if label.startswith("measured") and result["folds"] == 5)
    print(f"\nsequential rule, 5 folds, resampled residuals (nominal level {headline['nominal_level']:.4f} a look): "
          "per stopping time")
    print("| seeds | stopped there | with a false verdict | false, among those stopped there | false up to here |")
    print("|---|---|---|---|---|")
    for look in headline["sequential"]:
        given = "-" if look["false_given_stop"] is None else f"{look['false_given_stop']:.3f}"
        print(f"| {look['seeds']} | {look['stopped']:.3f} | {look['false']:.4f} | {given} | {look['cumulative']:.4f} |")
    if args.json:
        Path(args.json).write_text(json.dumps(to_json({"measured": {k: v for k, v in measured.items()
                                                                    if k not in ("residuals", "by_fold")},
                                                       "rule": rule.to_dict(), "replicates": args.replicates,
                                                       "results": [{"data": label, **result}
                                                                   for label, result in rows]}), indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
