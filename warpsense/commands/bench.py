"""`warpsense bench`: the benchmark suites (kernels, accuracy, train, time-to-accuracy, study) against the
plain-torch baseline and against themselves."""

from __future__ import annotations

import argparse
import sys

from warpsense.bench import BENCH_SUITES
from warpsense.choices import DEVICES, MPS_MODES
from warpsense.commands.options import count
from warpsense.files import check_output_file, check_plot_file

CAMVID_SUITES = ("accuracy", "time-to-accuracy", "all")  # the suites that read --camvid ("all": its accuracy suite)
STUDY_OPTIONS = ("plan", "out", "cells", "per_gpu", "gpus", "mps")
"""The study suite's own options (refused with another suite)."""
SET_SUITES = ("train", "study")
"""The suites ``--set`` configures: the train suite's preset (its network and codesign camera), the study's cells."""


def comma_separated(text: str, convert, example: str) -> tuple:
    """``text`` split at commas and each part converted; argparse turns the error into a one-line usage error."""
    try:
        return tuple(convert(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated {example}, got {text!r}") from None


def seed_list(text: str) -> tuple[int, ...]:
    """"0,1,2" -> (0, 1, 2), distinct and >= 0 (the range of run.seed, which each becomes)."""
    seeds = comma_separated(text, int, "integers such as 0,1,2")
    if any(seed < 0 for seed in seeds):
        raise argparse.ArgumentTypeError(f"seeds must be >= 0, got {text!r}")
    if len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"seeds must be distinct, got {text!r}")
    return seeds


def register(commands: argparse._SubParsersAction, name: str) -> None:
    """Add the command's parser to ``commands`` (the top-level subparsers) under ``name``."""
    parser = commands.add_parser(name, help="benchmarks: kernels, accuracy, training step, time to accuracy, "
                                 "study throughput",
                                 description="Benchmark warpsense, one suite at a time (--suite): the Warp kernels "
                                 "against their plain-torch references, their error against run time, the training "
                                 "step and latency against the plain-torch baseline, the wall time to mIoU levels, or "
                                 "a study's cells per GPU-hour. Measured figures: docs/benchmarks.md.")
    parser.add_argument("--device", default="cpu", choices=DEVICES[1:],
                        help="device to benchmark (default: %(default)s)")
    parser.add_argument("--suite", default="kernels", choices=BENCH_SUITES,
                        help="kernels: each op vs its reference; accuracy: error against run time (three error norms, "
                             "three scenes, the lens's discretisation against converged references); train: training "
                             "step, camera and latency vs the plain-torch baseline; time-to-accuracy: wall time to val "
                             "mIoU levels, the CamVid recipe vs the baseline (needs --camvid); study: cells per "
                             "GPU-hour of a plan's cells one per GPU against --per-gpu N, the same cells' scores side "
                             "by side (needs --plan and --out); all: kernels, accuracy and train "
                             "(default: %(default)s)")
    parser.add_argument("--quick", action="store_true",
                        help="small sizes and few repeats (< 2 min on 2 CPU cores)")
    parser.add_argument("--json", metavar="OUT", help="write the records as JSON")
    parser.add_argument("--plot", metavar="OUT.png",
                        help="write the error-against-run-time plot, one Pareto panel per kernel (accuracy suite), or "
                             "val mIoU against wall time (time-to-accuracy suite)")
    parser.add_argument("--camvid", metavar="ROOT", help="CamVid folder (with train.txt and val.txt): the accuracy "
                        "suite's real frames (without it that scene is left out); the time-to-accuracy suite's data")
    parser.add_argument("--seeds", type=seed_list, metavar="0,1,2",
                        help="time-to-accuracy: train both methods with each seed and add means with 95%% intervals "
                             "(default: 0)")
    study = parser.add_argument_group("study suite (--suite study)")
    study.add_argument("--plan", help="a study plan TOML file or a shipped plan name (configs/studies/)")
    study.add_argument("--out", help="the suite's folder: OUT/alone and OUT/shared study directories (kept: a "
                       "second call resumes)")
    study.add_argument("--cells", type=count(0), default=None, metavar="N",
                       help="the plan's first N cells (default: 0 = all)")
    study.add_argument("--per-gpu", type=count(2), default=None, metavar="N",
                       help="cells at once on each GPU in the shared invocation (default: 3)")
    study.add_argument("--gpus", default=None,
                       help="GPUs of the local pool: auto, none (this process), or ids 0,1 counted "
                            "within CUDA_VISIBLE_DEVICES as torch's cuda:N (default: auto)")
    study.add_argument("--mps", choices=MPS_MODES, default=None,
                       help="the shared invocation's CUDA MPS daemon (default: auto); the alone one runs without")
    parser.add_argument("--set", dest="overrides", action="append", default=None, metavar="SECTION.KEY=VALUE",
                        help="override one config key (repeatable): of the camvid_codesign preset the train suite "
                             "times (its network and codesign camera), e.g. model.squeeze=true; of every cell of the "
                             "study suite, e.g. train.epochs=30")


def run(args: argparse.Namespace) -> int:
    """Refuse --seeds for a suite that trains nothing, then `run_bench_command`; returns the exit code."""
    if args.seeds is not None and args.suite != "time-to-accuracy":
        raise ValueError(f"--seeds are the time-to-accuracy suite's training seeds: --suite {args.suite} trains none")
    if args.camvid is not None and args.suite not in CAMVID_SUITES:
        raise ValueError(f"--camvid is the CamVid folder of the {', '.join(CAMVID_SUITES)} suites: --suite "
                         f"{args.suite} reads none")
    if args.suite == "study":
        return run_study_suite_command(args.plan, args.out, args.cells or 0, args.per_gpu or 3, args.gpus or "auto",
                                       args.mps or "auto", tuple(args.overrides or ()), args.json)
    given = [name for name in STUDY_OPTIONS if getattr(args, name) is not None]
    if given:
        options = ", ".join("--" + name.replace("_", "-") for name in given)
        raise ValueError(f"{options}: options of the study suite (--suite study), not of --suite {args.suite}")
    if args.overrides and args.suite not in SET_SUITES:
        raise ValueError(f"--set configures the {' and '.join(SET_SUITES)} suites, not --suite {args.suite}")
    return run_bench_command(args.device, args.suite, args.quick, args.json, args.plot, args.camvid,
                             args.seeds or (0,), tuple(args.overrides or ()))


def run_bench_command(device: str, suite: str, quick: bool, json_out: str | None, plot_out: str | None,
                      camvid_root: str | None = None, seeds: tuple[int, ...] = (0,),
                      overrides: tuple[str, ...] = ()) -> int:
    """Run the suite (`warpsense.bench.runner.run_bench`) after checking its inputs and where its outputs go."""
    from warpsense.bench.runner import run_bench

    check_output_file(json_out, "--json")
    check_plot_file(plot_out, "--plot")
    if overrides:  # a bad key or value, before minutes of other suites
        from warpsense.bench.train_suite import PRESET
        from warpsense.config import load_config

        load_config(PRESET, list(overrides))
    if camvid_root is not None:  # the dataset's own checks, before minutes of other suites
        from warpsense.data.datasets import CamVid

        CamVid(camvid_root, "val", limit=1)
    run_bench(device=device, quick=quick, json_out=json_out, plot_out=plot_out, suite=suite, camvid_root=camvid_root,
              seeds=seeds, overrides=overrides)
    return 0


def run_study_suite_command(plan: str | None, out: str | None, cells: int, per_gpu: int, gpus: str, mps: str,
                            overrides: tuple[str, ...], json_out: str | None) -> int:
    """`warpsense.bench.study_suite.run_study_suite` after checking its options; prints the comparison."""
    from warpsense.bench.study_suite import SuiteStopped, format_study_suite, run_study_suite
    from warpsense.files import write_json
    from warpsense.study.launch import check_local_gpus, parse_gpus

    if not plan or not out:
        raise ValueError("--suite study needs --plan (a study plan) and --out (the suite's folder)")
    check_output_file(json_out, "--json")
    devices = parse_gpus(gpus)
    check_local_gpus(devices)
    try:
        record = run_study_suite(plan, out, cells, devices, per_gpu, mps, overrides)
    except SuiteStopped as stopped:  # a failed cell (1) or Ctrl-C / SIGTERM (130): one line, as `study run` ends
        print(f"warpsense bench: {stopped}", file=sys.stderr)
        return stopped.code
    print(format_study_suite(record))
    if json_out:
        write_json(json_out, record)
    return 0
