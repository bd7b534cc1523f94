"""The examples run as a user runs them (a fresh process, warnings as errors) and show what they claim."""

import re
import subprocess
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_camera_gradients_example_reaches_every_parameter_and_recovers_the_exposure():
    """examples/camera_gradients.py: `Camera` alone, gradients with respect to each of its learnable parameters and
    the scene (finite, non-zero, no torch warning), and a gradient-descent calibration that recovers the reference
    camera's exposure gain of 1.5 from 1.0."""
    result = subprocess.run([sys.executable, "-W", "error::UserWarning", str(EXAMPLES / "camera_gradients.py"),
                             "--size", "32x48"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "Warning" not in result.stderr, result.stderr
    norms = dict(re.findall(r"^  (.+?)\s+\|grad\| = (\S+)$", result.stdout, flags=re.MULTILINE))
    assert {"exposure.gain_logit", "cfa.logits", "radiance (the scene)"} <= set(norms)
    assert any(name.startswith("optics.") for name in norms) and any(name.startswith("noise.") for name in norms)
    assert all(0 < float(value) < float("inf") for value in norms.values()), norms
    final = re.search(r"exposure calibration: gain 1\.0000 -> (\S+) in 20 steps", result.stdout)
    assert final and abs(float(final.group(1)) - 1.5) < 0.005, result.stdout


def test_camera_gradients_example_refuses_a_bad_size_or_step_count_as_a_usage_error():
    """`--size 32` was a ValueError traceback from unpacking, `--size 0x5` one from deep inside psf_conv, and
    `--steps -1` printed a calibration "in -1 steps": each is argparse's usage error naming the option."""
    for arguments, named in ((["--size", "32"], "--size"), (["--size", "0x5"], "--size"),
                             (["--steps", "-1"], "--steps")):
        result = subprocess.run([sys.executable, str(EXAMPLES / "camera_gradients.py"), *arguments],
                                capture_output=True, text=True, timeout=300)
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        assert named in result.stderr.strip().splitlines()[-1], result.stderr
