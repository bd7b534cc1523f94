"""`warpsense convert`: raw captures (DNG, Bayer raws) to <stem>.safetensors mosaics, a batch at a time."""

from __future__ import annotations

from warpsense.data.raw import convert_files
from warpsense.files import check_output_folder


def run_convert(inputs: list[str], out_dir: str, progress: bool = True) -> int:
    """Convert every input into ``out_dir``; 1 when any failed (each failure reported on stderr), else 0."""
    check_output_folder(out_dir, "--out")
    return 1 if convert_files(inputs, out_dir, progress=progress) else 0
