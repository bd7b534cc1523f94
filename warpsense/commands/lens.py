"""`warpsense lens`: a lens's energy outside its PSF kernel per node and its pixel-integration error."""

from __future__ import annotations

import json

from warpsense.optics import report
from warpsense.optics.lens import Lens


def run_lens(name_or_path: str, as_json: bool = False) -> int:
    """Print the report of `warpsense.optics.report.lens_report` (text, or JSON with ``as_json``)."""
    result = report.lens_report(Lens.from_json(name_or_path))
    print(json.dumps(result, indent=1) if as_json else report.format_report(result))
    return 0
