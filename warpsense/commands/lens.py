"""`warpsense lens`: a lens's energy outside its PSF kernel per node and its pixel-integration error; with ``--plot``
its PSF grid per colour and its MTF."""

from __future__ import annotations

import argparse
import json

from warpsense.files import check_plot_file


def register(commands: argparse._SubParsersAction, name: str) -> None:
    """Add the command's parser to ``commands`` (the top-level subparsers) under ``name``."""
    parser = commands.add_parser(name, help="a lens's energy outside its PSF kernel and its sampling",
                                 description="Report, per PSF grid node, the energy the lens's K x K kernel leaves "
                                 "out (renormalised into the core) and the K a tolerance needs; whether its samples "
                                 "per pixel reach the Nyquist rate at which the pixel integration is exact; and how "
                                 "far its rendering moves at 15 samples per pixel (the pupil sampling's share).")
    parser.add_argument("lens", help="packaged lens name (configs/lenses/) or a lens JSON file")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--plot", metavar="OUT.png",
                        help="also draw the PSF grid per colour and the MTF of the on-axis and corner PSFs")


def run(args: argparse.Namespace) -> int:
    """Check where the plot goes, then `run_lens`; returns the exit code."""
    check_plot_file(args.plot, "--plot")
    return run_lens(args.lens, args.json, plot=args.plot)


def run_lens(name_or_path: str, as_json: bool = False, plot: str | None = None) -> int:
    """Print the report of `warpsense.optics.report.lens_report` (text, or JSON with ``as_json``); with ``plot``
    also write `warpsense.optics.mtf.plot_lens`'s figure there."""
    from warpsense.optics import report
    from warpsense.optics.lens import Lens

    lens = Lens.from_json(name_or_path)
    result = report.lens_report(lens)
    print(json.dumps(result, indent=1) if as_json else report.format_report(result))
    if plot:
        from warpsense.optics.mtf import plot_lens

        plot_lens(lens, plot)
        if not as_json:
            print(f"wrote {plot}")
    return 0
