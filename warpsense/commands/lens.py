"""`warpsense lens`: a lens's energy outside its PSF kernel per node and its pixel-integration error; with ``--plot``
its PSF grid per colour and its MTF."""

from __future__ import annotations

import json

from warpsense.optics import report
from warpsense.optics.lens import Lens


def run_lens(name_or_path: str, as_json: bool = False, plot: str | None = None) -> int:
    """Print the report of `warpsense.optics.report.lens_report` (text, or JSON with ``as_json``); with ``plot``
    also write `warpsense.optics.mtf.plot_lens`'s PNG there."""
    lens = Lens.from_json(name_or_path)
    result = report.lens_report(lens)
    print(json.dumps(result, indent=1) if as_json else report.format_report(result))
    if plot:
        from warpsense.optics.mtf import plot_lens

        plot_lens(lens, plot)
        if not as_json:
            print(f"wrote {plot}")
    return 0
