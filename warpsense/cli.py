"""The `warpsense` command line: thin argument parsing over importable functions."""

from __future__ import annotations

import argparse
import os
import sys

from warpsense import __version__
from warpsense.bench import BENCH_SUITES, parse_size
from warpsense.choices import DATASETS, DEVICES, MPS_MODES
from warpsense.config import preset_names
from warpsense.files import check_output_file


def _add_config_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE_OR_PRESET",
                        help="a TOML file or a preset name (configs/presets/); default: configs/default.toml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one config key (repeatable), e.g. --set train.epochs=5")


def _progress(args) -> bool:
    """Whether to draw progress bars: not with --no-progress, and only on a terminal (bars redrawn with carriage
    returns fill a log file with kilobytes of partial lines)."""
    return not args.no_progress and sys.stderr.isatty()


def _train(args) -> int:
    from warpsense.commands.train import run_train

    return run_train(args.config, args.overrides, args.resume, args.resume_dir, args.allow_config_change,
                     extend=args.extend,
                     progress=_progress(args), print_config=args.print_config)


def _eval(args) -> int:
    from warpsense.commands.eval import run_eval

    if args.plot and not args.sweep:
        raise ValueError("--plot draws the sweeps: add --sweep")
    check_output_file(args.json, "--json")
    check_output_file(args.plot, "--plot")
    height, width = parse_size(args.latency_size, "--latency-size", "192x640")
    run_eval(args.checkpoint, args.data, args.data_root, args.split, args.json, args.sweep, args.latency,
             (height, width), args.latency_batch, args.device, args.batch_size, args.limit, args.plot, args.flip_tta,
             progress=_progress(args))
    return 0


def _comma_separated(text: str, convert, example: str) -> tuple:
    """``text`` split at commas and each part converted; argparse turns the error into a one-line usage error."""
    try:
        return tuple(convert(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated {example}, got {text!r}") from None


def _seed_list(text: str) -> tuple[int, ...]:
    """"0,1,2" -> (0, 1, 2), distinct and >= 0 (the range of run.seed, which each becomes)."""
    seeds = _comma_separated(text, int, "integers such as 0,1,2")
    if any(seed < 0 for seed in seeds):
        raise argparse.ArgumentTypeError(f"seeds must be >= 0, got {text!r}")
    if len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"seeds must be distinct, got {text!r}")
    return seeds


def _count(minimum: int):
    """An argparse ``type`` for an integer >= ``minimum``: a wrong value is a usage error naming the option, before
    any checkpoint or data is loaded."""
    def convert(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    convert.__name__ = "integer"  # argparse names the type in its "invalid ... value" message
    convert.minimum = minimum  # the least valid value, for the bad-input corpus (tests/reliability)
    return convert


def _bench(args) -> int:
    from warpsense.commands.bench import run_bench_command

    if args.seeds is not None and args.suite != "time-to-accuracy":
        raise ValueError(f"--seeds are the time-to-accuracy suite's training seeds: --suite {args.suite} trains none")
    return run_bench_command(args.device, args.suite, args.quick, args.json, args.plot, args.camvid,
                             args.seeds or (0,))


def _convert(args) -> int:
    from warpsense.commands.convert import run_convert

    return run_convert(args.inputs, args.out, progress=_progress(args))


def _predict(args) -> int:
    from warpsense.commands.predict import predict_raw

    check_output_file(args.out, "--out")
    predict_raw(args.checkpoint, args.input, args.out, device=args.device, overlay=args.overlay,
                legend=not args.no_legend)
    return 0


def _study(args) -> int:
    from warpsense.commands.study import report_study, run_study, status_study

    if args.study_command == "run":
        slurm = {"partition": args.slurm_partition, "time_minutes": args.slurm_time,
                 "gpus_per_cell": args.gpus_per_cell, "array_parallelism": args.array_parallelism,
                 "extra": args.slurm_option, "wait": args.wait}
        return run_study(args.plan, args.out, args.overrides, args.cell, args.plan_only, args.gpus, args.per_gpu,
                         progress=args.progress, worker=args.worker, reuse=args.reuse, mps=args.mps,
                         executor=args.executor, slurm=slurm)
    if args.study_command == "status":
        return status_study(args.study_dir)
    return report_study(args.study_dir, args.json, args.plot, args.split, args.resamples, args.block_frames)


def _lens(args) -> int:
    from warpsense.commands.lens import run_lens

    check_output_file(args.plot, "--plot")
    return run_lens(args.lens, args.json, plot=args.plot)


def _simulate(args) -> int:
    from warpsense.commands.simulate import run_simulate

    if args.checkpoint and (args.config or args.overrides):
        raise ValueError("--checkpoint brings its own camera: leave out --config and --set")
    if not args.checkpoint and not args.config:
        raise ValueError("give the camera: --config FILE_OR_PRESET (with --set) or --checkpoint CKPT")
    return run_simulate(args.images, args.out, args.config, args.overrides, args.checkpoint, args.linear, args.seed)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="warpsense", description="Camera co-design for driving perception: a "
                                     "differentiable camera (lens, exposure, colour filters, noise, ADC) in NVIDIA "
                                     "Warp, trained with a segmentation network; compare cameras with `warpsense "
                                     "study`.")
    parser.add_argument("--version", action="version", version=f"warpsense {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")

    train = commands.add_parser("train", help="train camera + network (default: built-in scenes on the CPU)",
                                description="Two-phase co-design training. With no arguments it trains on built-in "
                                "generated street scenes. Multi-GPU: torchrun --nproc_per_node N -m warpsense train ...",
                                epilog=f"presets: {', '.join(preset_names())}. Every key and its default: "
                                "configs/default.toml, or --print-config.")
    _add_config_options(train)
    train.add_argument("--resume", action="store_true", help="continue the run <output_dir>/<name> from its last checkpoint")
    train.add_argument("--resume-dir", metavar="RUN_DIR", help="continue the run in RUN_DIR from its last checkpoint")
    train.add_argument("--allow-config-change", action="store_true",
                       help="with --resume/--resume-dir: continue with the given --config/--set even where it differs "
                            "from the run's saved config (refused otherwise)")
    train.add_argument("--extend", type=_count(1), metavar="N",
                       help="with --resume/--resume-dir: train N more epochs after the last checkpoint, finished run or "
                            "not (train.epochs becomes the epochs trained + N, any time budget is dropped; the cosine "
                            "learning rate is laid over the new total, so it rises again and decays to 0 at the new "
                            "end; the previous config.json is kept as config.epoch<E>.json)")
    train.add_argument("--no-progress", action="store_true",
                       help="hide the progress bars (they are drawn only when stderr is a terminal)")
    train.add_argument("--print-config", action="store_true",
                       help="print the resolved config (after --config and --set) as JSON and exit")
    train.set_defaults(handler=_train)

    evaluate = commands.add_parser("eval", help="evaluate a checkpoint (mIoU, per-class IoU, sweeps, latency)",
                                   description="Evaluate a trained checkpoint on a dataset split.")
    evaluate.add_argument("--checkpoint", required=True,
                          help="a checkpoint .safetensors written by `warpsense train` (its config and classes are "
                               "inside it; the .json beside it is a readable copy, not needed)")
    evaluate.add_argument("--data", choices=DATASETS,
                          help="dataset kind (default: the one the checkpoint was trained on)")
    evaluate.add_argument("--data-root", help="dataset folder (not needed for scenes; default: the checkpoint's "
                          "data.root when --data is left out)")
    evaluate.add_argument("--split", default="val",
                          help="split name; heldout: a sequence-fold checkpoint's held-out sequence (default: "
                          "%(default)s)")
    evaluate.add_argument("--json", metavar="OUT", help="write metrics JSON (miou, per_class_iou, pixel_accuracy, num_images)")
    evaluate.add_argument("--sweep", action="store_true", help="robustness sweeps: extra blur, noise scale, bit depth")
    evaluate.add_argument("--flip-tta", action="store_true",
                          help="average with the prediction on the mirrored capture (keeps the CFA phase)")
    evaluate.add_argument("--plot", metavar="OUT.png", help="with --sweep: plot the sweeps")
    evaluate.add_argument("--latency", action="store_true", help="time sensor simulation + network (the camera cached: Camera.cached) and network alone (alone: no dataset, no mIoU; with --sweep: both)")
    evaluate.add_argument("--latency-size", default="192x640", metavar="HxW", help="input size for --latency (default: %(default)s)")
    evaluate.add_argument("--latency-batch", type=_count(1), default=1, metavar="N", help="batch size for --latency (default: %(default)s)")
    evaluate.add_argument("--batch-size", type=_count(1), default=4, metavar="N", help="evaluation batch size (default: %(default)s)")
    evaluate.add_argument("--limit", type=_count(0), default=0, metavar="N", help="evaluate only the first N images (default: %(default)s = all)")
    evaluate.add_argument("--device", default="auto", choices=DEVICES, help="device (default: %(default)s)")
    evaluate.add_argument("--no-progress", action="store_true",
                          help="hide the progress bars (they are drawn only when stderr is a terminal)")
    evaluate.set_defaults(handler=_eval)

    bench = commands.add_parser("bench", help="kernel microbenchmarks: error against run time",
                                description="Benchmark every Warp kernel against its plain-torch reference.")
    bench.add_argument("--device", default="cpu", choices=DEVICES[1:], help="device to benchmark (default: %(default)s)")
    bench.add_argument("--suite", default="kernels", choices=BENCH_SUITES,
                       help="kernels: each op vs its reference; accuracy: error against run time (three error norms, "
                            "three scenes, the lens's discretisation against converged references); train: training "
                            "step, camera and latency vs the plain-torch baseline; time-to-accuracy: wall time to val "
                            "mIoU levels, the CamVid recipe vs the baseline (needs --camvid); all: kernels, accuracy "
                            "and train (default: %(default)s)")
    bench.add_argument("--quick", action="store_true", help="small sizes and few repeats (< 2 min on 2 CPU cores)")
    bench.add_argument("--json", metavar="OUT", help="write the records as JSON")
    bench.add_argument("--plot", metavar="OUT.png",
                       help="write the error-against-run-time plot, one Pareto panel per kernel (accuracy suite), or "
                            "val mIoU against wall time (time-to-accuracy suite)")
    bench.add_argument("--camvid", metavar="ROOT", help="CamVid folder (with train.txt and val.txt): the accuracy "
                       "suite's real frames (without it that scene is left out); the time-to-accuracy suite's data")
    bench.add_argument("--seeds", type=_seed_list, metavar="0,1,2",
                       help="time-to-accuracy: train both methods with each seed and add means with 95%% intervals "
                            "(default: 0)")
    bench.set_defaults(handler=_bench)

    convert = commands.add_parser("convert", help="convert raw captures (DNG, Bayer raws) to RAW tensors",
                                  description="Convert raw files (files, folders or globs) into <stem>.safetensors "
                                  "mosaics with metadata, through rawpy/LibRaw.")
    convert.add_argument("inputs", nargs="+", help="raw files, folders or glob patterns")
    convert.add_argument("--out", required=True, help="output folder")
    convert.add_argument("--no-progress", action="store_true",
                         help="hide the progress bar (it is drawn only when stderr is a terminal)")
    convert.set_defaults(handler=_convert)

    predict = commands.add_parser("predict", help="segment a real raw capture with a fixed-Bayer checkpoint",
                                  description="Run a checkpoint trained with a fixed Bayer CFA on a DNG and write a "
                                  "colour-coded segmentation PNG.")
    predict.add_argument("checkpoint", help="checkpoint .safetensors")
    predict.add_argument("input", help="raw file (DNG, or another LibRaw raw) or a `warpsense convert` .safetensors")
    predict.add_argument("--out", required=True,
                         help="output image, as large as the capture; its type follows the suffix (.png, .jpg, ...)")
    predict.add_argument("--overlay", action="store_true", help="blend the class colours over the capture")
    predict.add_argument("--no-legend", action="store_true", help="leave out the strip naming the class colours")
    predict.add_argument("--device", default="auto", choices=DEVICES, help="device (default: %(default)s)")
    predict.set_defaults(handler=_predict)

    study = commands.add_parser("study", help="compare cameras: cameras x light levels x seeds, with intervals",
                                description="Run a study plan (one training run per camera, light level and seed, "
                                "judged at its final epoch) and report which camera wins, by how much, with what "
                                "confidence.")
    study_commands = study.add_subparsers(dest="study_command", metavar="run|status|report", required=True)
    study_run = study_commands.add_parser(
        "run", help="run the plan's cells (resumable; finished cells are never retrained)",
        description="Run every cell of a plan into OUT/runs/<camera>.<light>[.<fold>].seed<N>. Finished cells are skipped, "
        "interrupted ones resume, failed ones are reported and the others go on. With several GPUs the cells run "
        "on a local pool of worker processes (--per-gpu on each GPU), each taking the next cell.",
        epilog="shipped plans: configs/studies/")
    study_run.add_argument("plan", help="a study plan TOML file or a shipped plan name (configs/studies/)")
    study_run.add_argument("--out", required=True, help="the study directory")
    study_run.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                           help="override one config key of every cell (repeatable)")
    study_run.add_argument("--cell", metavar="CAMERA/LIGHT/[FOLD/]SEED",
                           help="run this cell only (what --plan-only prints)")
    study_run.add_argument("--plan-only", action="store_true",
                           help="print one command per cell, for a scheduler (a Slurm job array, ...), and exit")
    study_run.add_argument("--gpus", default="auto",
                           help="GPUs of the local pool: auto (all torch sees), none (this process), or ids 0,1 "
                                "(default: %(default)s)")
    study_run.add_argument("--per-gpu", type=_count(1), default=1, metavar="N",
                           help="cells at once on each GPU (default: %(default)s)")
    study_run.add_argument("--mps", choices=MPS_MODES, default="auto",
                           help="run the pool's workers under a CUDA MPS daemon of the study's own, so that cells "
                           "sharing a GPU run concurrently instead of time-sliced: auto (with --per-gpu > 1 where "
                           "nvidia-cuda-mps-control is on the PATH), on, off (default: %(default)s)")
    study_run.add_argument("--progress", action="store_true", help="show each cell's progress bars")
    study_run.add_argument("--reuse", action="append", default=[], metavar="STUDY_DIR",
                           help="copy in another study's finished runs for the cells whose config they trained "
                           "(all but run.name and run.output_dir equal; repeatable)")
    study_run.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)  # the local pool's processes
    study_run.add_argument("--executor", choices=("local", "slurm"), default="local",
                           help="local: the cells run here (this process, or the local pool over the GPUs); slurm: "
                           "submit the pending cells to Slurm through submitit as one job array, one cell per task, "
                           "and return once submitted (OUT must be on a file system the nodes share); "
                           "`warpsense study status OUT` follows them (default: %(default)s)")
    slurm = study_run.add_argument_group(
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
    study_status = study_commands.add_parser(
        "status", help="each cell pending, running, done or failed",
        description="One line per cell of a study directory: done (evaluated), running, pending (queued, or not "
        "submitted yet) or failed (its last Slurm task ended without finishing it: run the study again to resume "
        "it), from the directory and, for cells submitted with --executor slurm, from squeue.")
    study_status.add_argument("study_dir", metavar="DIR", help="a study directory (warpsense study run --out)")
    study_report = study_commands.add_parser(
        "report", help="per camera and light: mIoU with intervals, differences to the reference",
        description="Mean mIoU and per-class IoU with 95% t intervals over seeds (over the folds' means with "
        "sequence folds), the difference to the reference camera paired over seeds (or (fold, seed) pairs) with a "
        "bootstrap interval that draws blocks of consecutive frames within each sequence, a per-sequence table with "
        "folds, and the learned camera of every run.")
    study_report.add_argument("study_dir", metavar="DIR", help="a study directory (warpsense study run --out)")
    study_report.add_argument("--json", metavar="OUT", help="write the report's record as JSON")
    study_report.add_argument("--plot", metavar="OUT.png", help="scores with intervals and per-class differences")
    study_report.add_argument("--split", help="the split the plot shows (default: the first, val)")
    study_report.add_argument("--resamples", type=_count(1), default=2000, metavar="N",
                              help="bootstrap resamples (default: %(default)s)")
    study_report.add_argument("--block-frames", type=_count(1), default=10, metavar="N",
                              help="consecutive frames of one sequence drawn together by the bootstrap (default: "
                              "%(default)s)")
    study.set_defaults(handler=_study)

    lens = commands.add_parser("lens", help="a lens's energy outside its PSF kernel and its sampling",
                               description="Report, per PSF grid node, the energy the lens's K x K kernel leaves out "
                               "(renormalised into the core) and the K a tolerance needs; whether its samples per "
                               "pixel reach the Nyquist rate at which the pixel integration is exact; and how far "
                               "its rendering moves at 15 samples per pixel (the pupil sampling's share).")
    lens.add_argument("lens", help="packaged lens name (configs/lenses/) or a lens JSON file")
    lens.add_argument("--json", action="store_true", help="print the report as JSON")
    lens.add_argument("--plot", metavar="OUT.png",
                      help="also draw the PSF grid per colour and the MTF of the on-axis and corner PSFs")
    lens.set_defaults(handler=_lens)

    simulate = commands.add_parser(
        "simulate", help="your own images through a camera: RAW (.safetensors, DNG) and a preview",
        description="Take sRGB images (PNG/JPEG; linear TIFFs with --linear) through a configured or checkpointed "
        "camera in eval mode (fixed noise seed) and write per image <stem>.safetensors (the RAW mosaic, which "
        "`warpsense predict` reads), <stem>.dng (where the CFA is a 2x2 Bayer layout) and <stem>.preview.png. A bad "
        "file is reported and the others go on (exit 2 at the end).")
    simulate.add_argument("images", nargs="+", help="image files")
    _add_config_options(simulate)
    simulate.add_argument("--checkpoint", metavar="CKPT", help="use a trained checkpoint's camera instead of --config")
    simulate.add_argument("--out", required=True, help="output folder")
    simulate.add_argument("--linear", action="store_true",
                          help="the images hold linear radiance (16-bit or float TIFF) instead of sRGB")
    simulate.add_argument("--seed", type=_count(0), default=0, metavar="N",
                          help="noise seed offset (with the camera's eval seed and the file name; default: "
                          "%(default)s)")
    simulate.set_defaults(handler=_simulate)
    return parser


CPU_THREAD_DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE"}
"""Environment defaults for torch's OpenMP runtime that `main` sets before torch loads, where the caller has not set
them: an OpenMP thread waiting for work sleeps instead of spinning. libgomp's default spins at every barrier, which
takes the cores from the threads with work whenever another job shares them: beside another CPU job the quickstart's
training ran 14x slower, and on a loaded 2-core machine 5-10x slower than with PASSIVE (tools/bench_threads.py,
docs/benchmarks.md). OMP_WAIT_POLICY=ACTIVE in the environment keeps spinning on a machine of one's own."""


def _cpu_thread_defaults() -> None:
    """Set `CPU_THREAD_DEFAULTS` where the environment does not; child processes (a study's workers, torchrun's
    ranks) inherit them."""
    for key, value in CPU_THREAD_DEFAULTS.items():
        os.environ.setdefault(key, value)


def main(argv: list[str] | None = None) -> int:
    _cpu_thread_defaults()  # before anything imports torch, which loads the OpenMP runtime that reads them once
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    from warpsense.config import ConfigError
    from warpsense.data.datasets import DatasetError
    from warpsense.optics.lens import LensFileError
    from warpsense.study.plan import PlanError

    try:
        return args.handler(args)
    except (ConfigError, DatasetError, LensFileError, PlanError, OSError, KeyError, ValueError) as error:
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        print(f"warpsense {args.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
