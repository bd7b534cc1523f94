"""`warpsense study run | status | report`: run a study plan's cells, follow them, and report what they say (which
path a run takes, and the rest of the work: `warpsense.study.launch`)."""

from __future__ import annotations

import argparse

from warpsense.choices import MPS_MODES
from warpsense.commands.options import count
from warpsense.resources import shipped_studies


def register(commands: argparse._SubParsersAction, name: str) -> None:
    """Add the command's parser, with its subcommands run, status and report, to ``commands`` (the top-level
    subparsers) under ``name``."""
    study = commands.add_parser(name, help="compare cameras: cameras x light levels x seeds, with intervals",
                                description="Run a study plan (one training run per camera, light level and seed, "
                                "judged at its final epoch) and report which camera wins, by how much, with what "
                                "confidence.")
    subcommands = study.add_subparsers(dest="study_command", metavar="run|status|report", required=True)
    _add_run(subcommands)
    status = subcommands.add_parser(
        "status", help="each cell pending, running, done or failed",
        description="One line per cell of a study directory: done (evaluated), running, pending (queued, or not "
        "submitted yet) or failed (its last Slurm task ended without finishing it, or a local run failed it, with "
        "the reason: run the study again to resume it), from the directory and, for cells submitted with "
        "--executor slurm, from squeue.")
    status.add_argument("study_dir", metavar="DIR", help="a study directory (warpsense study run --out)")
    report = subcommands.add_parser(
        "report", help="per camera and light: mIoU with intervals, differences to the reference",
        description="Mean mIoU and per-class IoU with 95% t intervals over seeds (over the folds' means with "
        "sequence folds), the difference to the reference camera paired over seeds (or (fold, seed) pairs) with a "
        "bootstrap interval that draws blocks of consecutive frames within each sequence, a per-sequence table with "
        "folds, and the learned camera of every run.")
    report.add_argument("study_dir", metavar="DIR", help="a study directory (warpsense study run --out)")
    report.add_argument("--json", metavar="OUT", help="write the report's record as JSON")
    report.add_argument("--plot", metavar="OUT.png", help="scores with intervals and per-class differences")
    report.add_argument("--split", help="with --plot: the split it draws (default: the first the runs were judged "
                        "on: val, or heldout with sequence folds; the text and --json hold every split)")
    report.add_argument("--resamples", type=count(1), default=2000, metavar="N",
                        help="bootstrap resamples (default: %(default)s)")
    report.add_argument("--block-frames", type=count(1), default=10, metavar="N",
                        help="consecutive frames of one sequence drawn together by the bootstrap (default: "
                        "%(default)s)")


def per_gpu_count(text: str) -> int | str:
    """``--per-gpu``: "auto" or an integer >= 1 (argparse type; a wrong value is a usage error naming the option)."""
    if text == "auto":
        return text
    if not text.lstrip("-").isdigit():
        raise argparse.ArgumentTypeError(f"expected auto or an integer, got {text!r}")
    return count(1)(text)


per_gpu_count.__name__ = "integer"  # argparse and the bad-input corpus (tests/reliability) read it as a count
per_gpu_count.minimum = 1  # the least valid number


def _add_run(subcommands: argparse._SubParsersAction) -> None:
    """``study run``'s parser: the plan, the local pool and the Slurm executor."""
    parser = subcommands.add_parser(
        "run", help="run the plan's cells (resumable; finished cells are never retrained)",
        description="Run every cell of a plan into OUT/runs/<camera>.<light>[.<fold>].seed<N>. Finished cells are "
        "skipped, interrupted ones resume, failed ones are reported and the others go on. With GPUs the cells run "
        "on a local pool of worker processes (--per-gpu on each GPU), each taking the next cell; the first GPU "
        "(id 0) at one cell a GPU, and a CPU, run them in this process. A plan with study.sequential (seeds added "
        "to unsettled comparisons) or a [[search]] (designs proposed by Bayesian optimisation, losers stopped early) "
        "chooses its next cells from the finished ones, round after round, on the same runner.",
        epilog=f"shipped plans (configs/studies/): {', '.join(shipped_studies())}")
    parser.add_argument("plan", help="a study plan TOML file or a shipped plan name (configs/studies/)")
    parser.add_argument("--out", required=True, help="the study directory")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one config key of every cell (repeatable)")
    parser.add_argument("--cell", metavar="CAMERA/LIGHT/[FOLD/]SEED",
                        help="run this cell only (what --plan-only prints), in this process; where --gpus names "
                        "GPUs but not 0, in a worker process given the first it names")
    parser.add_argument("--cells", action="append", default=[], metavar="PATTERN",
                        help="run only the cells whose id matches this shell pattern, e.g. 'fixed_isp/*' or "
                        "'*/night/block1/*' (repeatable: any pattern; the study directory records the whole plan, so "
                        "runs of other cells, here or on other machines, complete the same study)")
    parser.add_argument("--plan-only", action="store_true",
                        help="print each fold's size (lines starting with '#': what each fold trains on and is judged "
                        "on) and one command per cell, for a scheduler (a Slurm job array, ...), and exit")
    parser.add_argument("--gpus", default="auto",
                        help="GPUs of the local pool: auto (all torch sees), none (this process), or ids 0,1 "
                             "counted within CUDA_VISIBLE_DEVICES as torch's cuda:N (default: %(default)s)")
    parser.add_argument("--per-gpu", type=per_gpu_count, default="auto", metavar="N|auto",
                        help="cells at once on each GPU: auto (3 under CUDA MPS where each GPU's free memory holds "
                        "them, fewer where it holds fewer, 1 without MPS) or a number (default: %(default)s)")
    parser.add_argument("--mps", choices=MPS_MODES, default="auto",
                        help="run the pool's workers under a CUDA MPS daemon of the study's own, so that cells "
                        "sharing a GPU run concurrently instead of time-sliced: auto (with --per-gpu > 1 where "
                        "nvidia-cuda-mps-control is on the PATH), on, off (default: %(default)s)")
    parser.add_argument("--progress", action="store_true",
                        help="show each cell's progress bars (with a local pool: in its log, OUT/logs/<cell>.log)")
    parser.add_argument("--reuse", action="append", default=[], metavar="STUDY_DIR",
                        help="copy in another study's finished runs for the cells whose config they trained "
                        "(all but run.name and run.output_dir equal; repeatable)")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)  # the local pool's processes
    parser.add_argument("--executor", choices=("local", "slurm"), default="local",
                        help="local: the cells run here (this process, or the local pool over the GPUs); slurm: "
                        "submit the pending cells to Slurm through submitit as one job array, one cell per task, "
                        "and return once submitted (OUT must be on a file system the nodes share); "
                        "`warpsense study status OUT` follows them (default: %(default)s)")
    slurm = parser.add_argument_group(
        "Slurm executor (--executor slurm)",
        "A finished cell is never submitted again, nor one still queued; a cancelled, killed or failed task's cell "
        "resumes from its last checkpoint when the same command runs again; a preempted task, or one whose time "
        "runs out, is checkpointed and requeued by submitit. The options are checked with sbatch --test-only "
        "before anything is written or submitted.")
    slurm.add_argument("--slurm-partition", metavar="NAME", help="the partition (default: the cluster's default)")
    slurm.add_argument("--slurm-time", type=int, metavar="MINUTES",
                       help="time limit of each task; a cell that needs longer is requeued and resumes, up to 3 times "
                       "(default: 60)")
    slurm.add_argument("--gpus-per-cell", type=int, metavar="N",
                       help="GPUs of each task (default: 0 where every cell's config runs on the CPU, else 1)")
    slurm.add_argument("--array-parallelism", type=int, metavar="N",
                       help="tasks of the array running at once (default: 256)")
    slurm.add_argument("--slurm-option", action="append", default=[], metavar="KEY=VALUE",
                       help="a further sbatch option without its dashes, e.g. qos=high, account=vision, "
                       "cpus-per-task=8, or KEY alone for a flag (repeatable)")
    slurm.add_argument("--wait", action="store_true",
                       help="follow the tasks until every cell has finished or failed, a line per cell as it ends")


def run(args: argparse.Namespace) -> int:
    """Run the parsed subcommand (`warpsense.study.launch`'s `run_study`, `study_status` or `study_report`); returns
    the exit code."""
    from warpsense.study.launch import run_study, study_report, study_status

    if args.study_command == "run":
        slurm = {"partition": args.slurm_partition, "time_minutes": args.slurm_time,
                 "gpus_per_cell": args.gpus_per_cell, "array_parallelism": args.array_parallelism,
                 "extra": args.slurm_option, "wait": args.wait}
        return run_study(args.plan, args.out, args.overrides, args.cell, args.plan_only, args.gpus, args.per_gpu,
                         progress=args.progress, worker=args.worker, reuse=args.reuse, mps=args.mps,
                         executor=args.executor, slurm=slurm, patterns=args.cells)
    if args.study_command == "status":
        return study_status(args.study_dir)
    return study_report(args.study_dir, args.json, args.plot, args.split, args.resamples, args.block_frames)
