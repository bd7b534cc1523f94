"""`warpsense convert`: raw captures (DNG, Bayer raws) to <stem>.safetensors mosaics, a batch at a time."""

from __future__ import annotations

from warpsense.data.raw import convert_files
from warpsense.files import check_output_folder


def run_convert(inputs: list[str], out_dir: str, progress: bool = True) -> int:
    """Convert every input into ``out_dir``.

    Returns:
        The exit status: 2 when any input failed (each failure reported on stderr, the others converted), as every
        command's errors exit; else 0.
    """
    check_output_folder(out_dir, "--out")
    return 2 if convert_files(inputs, out_dir, progress=progress) else 0
