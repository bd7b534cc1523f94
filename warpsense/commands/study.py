"""`warpsense study run | report`: run a study plan's cells, and report what they say."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from warpsense.choices import MPS_MODES
from warpsense.commands.options import check_local_gpus, count, parse_gpus
from warpsense.files import check_output_file, check_output_folder, check_plot_file, write_json


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
        epilog="shipped plans: configs/studies/")
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
    parser.add_argument("--progress", action="store_true", help="show each cell's progress bars (with a local pool: in its log, "
                        "OUT/logs/<cell>.log)")
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
    """Run the parsed subcommand (`run_study`, `status_study` or `report_study`); returns the exit code."""
    if args.study_command == "run":
        slurm = {"partition": args.slurm_partition, "time_minutes": args.slurm_time,
                 "gpus_per_cell": args.gpus_per_cell, "array_parallelism": args.array_parallelism,
                 "extra": args.slurm_option, "wait": args.wait}
        return run_study(args.plan, args.out, args.overrides, args.cell, args.plan_only, args.gpus, args.per_gpu,
                         progress=args.progress, worker=args.worker, reuse=args.reuse, mps=args.mps,
                         executor=args.executor, slurm=slurm, patterns=args.cells)
    if args.study_command == "status":
        return status_study(args.study_dir)
    return report_study(args.study_dir, args.json, args.plot, args.split, args.resamples, args.block_frames)


def run_study(plan_name: str, out: str, overrides: list[str], cell: str | None = None, plan_only: bool = False,
              gpus: str = "auto", per_gpu: int | str = "auto", progress: bool = False, worker: bool = False,
              reuse: list[str] | None = None, executor: str = "local", slurm: dict | None = None,
              mps: str = "auto", patterns: list[str] | None = None) -> int:
    """The `warpsense study run` command; returns the exit code. ``worker``: be one of the local pool's worker
    processes (`warpsense.study.runner.cell_worker`, cell ids on stdin). ``executor`` "slurm": submit the cells to
    Slurm (`warpsense.study.slurm.submit_study`) with ``slurm``, the keyword arguments of
    `warpsense.study.slurm.slurm_options` (None: not given). ``patterns``: shell patterns of the cell ids to run
    (`warpsense.study.plan.Plan.select`; none: every cell)."""
    from warpsense.study.mps import MPSError
    from warpsense.study.mps import check_mode as check_mps_mode
    from warpsense.study.plan import fold_lines, fold_sizes, load_plan
    from warpsense.study.runner import (
        cell_state,
        cell_worker,
        check_reuse_dirs,
        check_runnable,
        plan_commands,
        run_cells,
    )
    from warpsense.study.slurm import check_not_queued, slurm_options, submit_study

    # every option is checked here, whichever path follows (worker, plan-only, one cell, pool, Slurm)
    if per_gpu != "auto" and (not isinstance(per_gpu, int) or per_gpu < 1):
        raise ValueError(f"--per-gpu must be auto or a number >= 1, got {per_gpu!r}")
    check_mps_mode(mps)
    devices = parse_gpus(gpus)
    cluster = slurm_options(executor, **(slurm or {}))  # before the plan loads: nothing is read or written
    if cluster is not None and plan_only:
        raise ValueError("--plan-only prints the commands for a scheduler of your own: leave out --executor slurm")
    if cluster is None and not (plan_only or worker or cell is not None):
        check_local_gpus(devices)  # the local pool's workers take these GPUs
    check_output_folder(out, "--out")
    check_reuse_dirs(reuse or [])  # here, not only when the cells run: --plan-only and --cell too
    plan = load_plan(plan_name, overrides)
    if cell is not None and patterns:
        raise ValueError("--cell runs one cell, --cells those matching patterns: give one of them")
    if cell is not None:
        plan.cell(cell)  # an unknown --cell is refused on every path, --plan-only and --worker included
    if worker:
        return cell_worker(plan, Path(out), progress)
    chosen_cells = [plan.cell(cell)] if cell is not None else plan.select(patterns or [])
    reuse_dirs = [Path(path) for path in reuse or []]
    folds = fold_lines(fold_sizes(plan))
    if plan_only:
        from warpsense.study.adaptive import plan_only_notes

        print("\n".join([*(f"# {line}" for line in folds), *(f"# {line}" for line in plan_only_notes(plan)),
                         *plan_commands(plan, Path(out), reuse_dirs, chosen_cells)]))
        return 0
    if plan.search is not None and cell is None and not patterns:
        from warpsense.study.search import require_optuna

        require_optuna()  # before anything is written
    check_runnable(plan, chosen_cells, local=cluster is None)  # a device it cannot have: before anything is written
    print("\n".join(f"study: {line}" for line in folds), flush=True)
    # study.sequential and [[search]] choose their rounds of cells (warpsense.study.adaptive); --cell and --cells
    # run the cells named, as in any plan
    adaptive = (plan.sequential is not None or plan.search is not None) and cell is None and not patterns
    if adaptive:
        from warpsense.study.adaptive import run_adaptive
    if cluster is not None and adaptive:
        return run_adaptive(plan, Path(out), lambda round_plan, cells: submit_study(round_plan, Path(out), cluster,
                                                                                    cells, reuse_dirs),
                            wait=cluster.wait)
    if cluster is not None:
        return submit_study(plan, Path(out), cluster, None if cell is None and not patterns else chosen_cells,
                            reuse_dirs)
    local = chosen_cells
    check_not_queued(Path(out), [each for each in local if cell_state(Path(out), each) != "done"])
    if cell is not None:  # here, on this process's cuda:0 or the CPU; GPUs named without 0: a worker on the first
        elsewhere = devices[:1] if devices and "0" not in devices else None
        if elsewhere:
            check_local_gpus(devices)
        return run_cells(plan, Path(out), cells=local, gpus=elsewhere, mps="off",
                         progress=progress, record=False, reuse=reuse_dirs)
    def run_pool(per_gpu: int, mps: str, round_plan=plan, cells=None) -> int:
        # in this process where that is one cell at a time on its own cuda:0 (or the CPU); one worker process
        # for another single GPU (--gpus 1): this process's training would take cuda:0 whatever --gpus says
        here = not devices or (devices == ["0"] and per_gpu == 1)
        return run_cells(round_plan, Path(out), cells=local if cells is None else cells, gpus=None if here else devices,
                         per_gpu=per_gpu, progress=progress, sample_gpus=devices, reuse=reuse_dirs, mps=mps)

    chosen = per_gpu == "auto"
    if not devices and (mps == "on" or per_gpu not in ("auto", 1)):  # a GPU machine's command line, run on a CPU
        print(f"study: no pool of GPUs (--gpus {gpus}): the cells run one at a time in this process; --per-gpu and "
              "--mps apply to the pool", flush=True)

    def run_local(round_plan=plan, cells=None) -> int:
        try:
            return run_pool(pool_cells_per_gpu(plan, devices, mps) if chosen else per_gpu, mps, round_plan, cells)
        except MPSError as error:
            if not (chosen and mps == "auto"):
                raise
            # a choice of ours, not the user's: one cell a GPU without MPS rather than no study
            print(f"study: {error}; one cell at once on each GPU instead", file=sys.stderr, flush=True)
            return run_pool(1, "off", round_plan, cells)

    code = run_adaptive(plan, Path(out), run_local) if adaptive else run_local()
    if code == 0:
        print(f"study finished; report: warpsense study report {out}")
    return code


def pool_cells_per_gpu(plan, devices: list[str], mps: str) -> int:
    """``--per-gpu auto`` for a local pool on ``devices`` (`warpsense.study.mps.auto_cells_per_gpu`), said in one
    line; 1 without GPUs."""
    from warpsense.study.mps import auto_cells_per_gpu
    from warpsense.study.runner import gpu_memory_gib, step_pixels

    if not devices:
        return 1
    count, why = auto_cells_per_gpu(mps, gpu_memory_gib(devices), step_pixels(plan))
    print(f"study: {count} cell(s) at once on each GPU (--per-gpu auto: {why}; --per-gpu N sets it)", flush=True)
    return count


def status_study(study_dir: str) -> int:
    """The `warpsense study status` command: each cell pending, running, done or failed."""
    from warpsense.study.slurm import print_status

    return print_status(study_dir)


def report_study(study_dir: str, json_out: str | None = None, plot_out: str | None = None,
                 split: str | None = None, resamples: int = 2000, block_frames: int = 10) -> int:
    """The `warpsense study report` command: console text, and the same record as JSON and a plot (with sweeps, and
    the design map beside it: OUT_map.png for ``--plot OUT.png``; with a search, its designs: OUT_search.png)."""
    from warpsense.study.report import plot_study, render_text, study_record

    if split is not None and not plot_out:
        raise ValueError(f"--split {split} picks the split --plot draws (the text and --json hold every split): "
                         "add --plot OUT.png")
    check_output_file(json_out, "--json")
    check_plot_file(plot_out, "--plot")
    record = study_record(study_dir, resamples, block_frames)
    if split is not None and split not in record["splits"]:
        raise ValueError(f"--split {split!r}: the study's runs were judged on {', '.join(record['splits'])}")
    print(render_text(record))
    if json_out:
        write_json(json_out, record)
        print(f"wrote {json_out}")
    if plot_out:
        plot_study(record, plot_out, split)
        print(f"wrote {plot_out}")
        if record["maps"]:  # a plan with sweeps: the design map beside the plot
            from warpsense.study.maps import map_path, plot_maps

            if plot_maps(record, map_path(plot_out), split):
                print(f"wrote {map_path(plot_out)}")
        if record.get("search"):  # a plan with a [[search]]: its designs over the searched keys beside it
            from warpsense.study.search_report import plot_search, search_path

            if plot_search(record, search_path(plot_out)):
                print(f"wrote {search_path(plot_out)}")
    return 0
