"""`warpsense simulate`: sRGB (or linear) images through a configured or checkpointed camera to RAW files."""

from __future__ import annotations

from warpsense.files import check_output_folder
from warpsense.simulate import load_camera, simulate_files


def run_simulate(inputs: list[str], out_dir: str, config: str | None = None, overrides: list[str] = (),
                 checkpoint: str | None = None, linear: bool = False, seed: int = 0) -> int:
    """Simulate every input into ``out_dir`` (`warpsense.simulate`).

    Returns:
        The exit status: 2 when any input failed (each reported on stderr, the others written), else 0.
    """
    check_output_folder(out_dir, "--out")
    camera = load_camera(config, overrides, checkpoint)
    return 2 if simulate_files(inputs, out_dir, camera, linear=linear, seed=seed) else 0
