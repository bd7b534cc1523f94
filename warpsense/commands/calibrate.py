"""`warpsense calibrate`: a sensor's noise (noise.shot, noise.read, electrons) from its raw captures, as JSON, a
preset and a plot."""

from __future__ import annotations

import argparse

from warpsense.commands.options import show_progress
from warpsense.files import check_output_file, check_plot_file


def register(commands: argparse._SubParsersAction, name: str) -> None:
    """Add the command's parser to ``commands`` (the top-level subparsers) under ``name``."""
    parser = commands.add_parser(
        name, help="estimate a sensor's noise from raw captures: a preset of your sensor",
        description="Estimate the Poisson-Gaussian noise (noise.shot: variance coefficient, noise.read: standard "
        "deviation, in units of the white level; and in electrons) per CFA channel with 95%% intervals, from "
        "raw captures (DNG and other raws LibRaw reads, or .safetensors from `warpsense convert` / `simulate`): "
        "each capture a scene (smooth regions, a clipping-aware fit), or with --series flat-field pairs and dark "
        "frames (photon transfer). A bad capture is reported and the others go on (exit 2 at the end). See "
        "docs/guide/calibrate.md.")
    parser.add_argument("captures", nargs="+", metavar="CAPTURES",
                        help="raw captures of one sensor at one setting (files, folders of raws, glob patterns)")
    parser.add_argument("--json", metavar="OUT", help="write the estimate, its intervals, files and regions as JSON")
    parser.add_argument("--out", metavar="PRESET.toml",
                        help="write a preset of this sensor (inherits --base), for train/simulate --config and "
                        "study cameras")
    parser.add_argument("--base", metavar="PRESET", default=None,
                        help="the preset (name or TOML file) the --out preset inherits (default: camvid_raw_fixed; "
                        "one with the photon budget, e.g. camvid_photons, gets [photons] in electrons)")
    parser.add_argument("--plot", metavar="OUT.png", help="draw the mean-variance points and fits per channel")
    parser.add_argument("--series", action="store_true",
                        help="the captures are flat fields, two at each exposure (paired by mean level): the "
                        "photon-transfer method; dark frames go to --dark")
    parser.add_argument("--dark", nargs="+", metavar="DARK", default=[],
                        help="dark frames of the --series (lens capped): the read noise directly")
    parser.add_argument("--no-progress", action="store_true",
                        help="hide the progress bar (it is drawn only when stderr is a terminal)")


def run(args: argparse.Namespace) -> int:
    """Check the options, then `run_calibrate`; returns the exit code."""
    if args.base is not None and not args.out:
        raise ValueError("--base names the preset --out inherits: give --out PRESET.toml")
    if args.dark and not args.series:
        raise ValueError("--dark frames belong to a photon-transfer series: add --series")
    return run_calibrate(args.captures, args.json, args.out, args.plot, args.base, args.series, args.dark,
                         show_progress(args))


def run_calibrate(captures: list[str], json_path: str | None = None, preset_path: str | None = None,
                  plot_path: str | None = None, base: str | None = None, series: bool = False,
                  darks: list[str] = (), progress: bool = False) -> int:
    """Calibrate ``captures`` (`warpsense.calibration.batch.calibrate_files`), outputs checked first.

    Returns:
        The exit status: 2 when any capture failed (each reported on stderr, the others used), else 0.
    """
    from warpsense.calibration.batch import DEFAULT_BASE, calibrate_files, check_base

    check_output_file(json_path, "--json")
    check_output_file(preset_path, "--out")
    check_plot_file(plot_path, "--plot")
    if preset_path and not str(preset_path).endswith(".toml"):
        raise ValueError(f"--out {preset_path}: a preset is a .toml file")
    base = base or DEFAULT_BASE
    if preset_path:
        check_base(base)
    failures = calibrate_files(captures, json_path, preset_path, plot_path, base, series, list(darks), progress)
    return 2 if failures else 0
