"""`warpsense calibrate` against two published noise estimators on the same captures (docs/guide/calibrate.md, the
comparison table).

- scikit-image's `skimage.restoration.estimate_sigma` (Donoho's wavelet MAD): one Gaussian standard deviation per
  image. Scored against the noise standard deviation the capture holds on average, sqrt(mean(shot * y + read^2))
  over its pixels: it has no shot/read split.
- the `ponomarenko` package (M. Colom's IPOL code of Colom & Buades 2013, after Ponomarenko et al.): a noise curve
  (bin means and standard deviations, from the lowest-variance DCT blocks); shot and read here are the weighted line
  variance = shot * mean + read^2 through its bins (its default 3 bins, and 8).

Each runs on every CFA channel plane of the capture (the pixels of one filter), as warpsense does. The captures:
`warpsense simulate` of scenes with known noise (a textured synthetic scene with black patches, as in
tests/test_calibrate.py, and CamVid val frames when ../shared/data is present) and the real DNGs.

The anchors are not warpsense dependencies: install them beside it (ponomarenko builds against FFTW:
`apt-get install libfftw3-dev`), e.g. in a separate environment that sees the project's packages:

    python3 -m venv /tmp/anchors && /tmp/anchors/bin/pip install scikit-image PyWavelets ponomarenko
    python tools/calibrate_anchors.py --anchors /tmp/anchors/lib/python3.11/site-packages --out table.md

(--anchors is appended to the import path after the project's packages, so its numpy does not shadow theirs).

An anchor that does not import is reported as missing in the table.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

LEVELS = [(0.015, 0.002, 10), (0.004, 0.001, 12), (0.0005, 0.0005, 14), (0.02, 0.01, 10)]
CAMERA = ["--config", str(ROOT / "configs" / "default.toml"), "--set", "exposure.enabled=false", "--set",
          "cfa.mode=\"fixed\""]


def _quiet(function, *args):
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return function(*args)


def simulate(image: Path, out: Path, shot: float, read: float, bits: int, linear: bool) -> Path:
    from warpsense.cli import main

    arguments = ["simulate", str(image), *CAMERA, "--set", f"noise.shot={shot}", "--set", f"noise.read={read}",
                 "--set", f"quantize.bits={bits}", "--out", str(out)] + (["--linear"] if linear else [])
    assert _quiet(main, arguments) == 0
    return out / f"{image.stem}.dng"


def ours(capture: Path, folder: Path) -> dict:
    from warpsense.cli import main

    out = folder / f"{capture.stem}.calibration.json"
    _quiet(main, ["calibrate", str(capture), "--json", str(out)])
    return json.loads(out.read_text())["noise"]


def planes(capture: Path) -> list:
    from warpsense.calibration.captures import read_calibration_capture

    return [site.plane for site in read_calibration_capture(capture).sites]


def skimage_sigma(capture: Path) -> float | None:
    """estimate_sigma over the CFA planes: the root mean square of the planes' sigmas."""
    try:
        from skimage.restoration import estimate_sigma
    except ImportError:
        return None
    return float(np.sqrt(np.mean([estimate_sigma(plane) ** 2 for plane in planes(capture)])))


def ponomarenko_curve(capture: Path, bins: int) -> tuple[float, float] | None:
    """(shot, read) of the weighted line through ponomarenko's noise curve of every CFA plane."""
    try:
        import ponomarenko
    except ImportError:
        return None
    means, variances = [], []
    for plane in planes(capture):
        mean, std = ponomarenko.estimate_noise(np.ascontiguousarray(plane, dtype=np.float64), num_bins=bins)
        means += list(np.asarray(mean, dtype=float))
        variances += list(np.asarray(std, dtype=float) ** 2)
    means, variances = np.array(means), np.array(variances)
    keep = np.isfinite(means) & np.isfinite(variances) & (variances > 0)
    if keep.sum() < 2:
        return None
    weights = 1 / variances[keep]
    design = np.stack([means[keep], np.ones(keep.sum())], axis=1) * weights[:, None]
    (shot, read_variance), *_ = np.linalg.lstsq(design, variances[keep] * weights, rcond=None)
    return float(shot), float(np.sqrt(max(read_variance, 0.0)))


def average_sigma(capture: Path, shot: float, read: float) -> float:
    """The noise standard deviation the capture holds on average (its pixels' signal taken as their reading)."""
    values = np.concatenate([plane.ravel() for plane in planes(capture)])
    return float(np.sqrt(np.mean(shot * np.clip(values, 0, None) + read**2)))


def scenes(folder: Path) -> list[tuple[str, Path, bool]]:
    """(name, file, linear) of the scenes to simulate: the tests' textured scene, and 2 CamVid val frames."""
    import tifffile

    sys.path.insert(0, str(ROOT / "tests"))
    from test_calibrate import scene

    path = folder / "textured.tif"
    tifffile.imwrite(path, np.round(scene() * 65535).astype(np.uint16))
    found = [("textured synthetic", path, True)]
    camvid = ROOT.parent / "shared" / "data" / "camvid" / "val"
    found += [(f"CamVid {p.stem}", p, False) for p in sorted(camvid.glob("*.png"))[:2]]
    return found


def relative(value, truth) -> str:
    return "n/a" if value is None else f"{value / truth - 1:+.0%}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", help="write the markdown tables here (default: print them)")
    parser.add_argument("--anchors", help="a site-packages folder holding scikit-image and ponomarenko")
    args = parser.parse_args()
    if args.anchors:
        sys.path.append(args.anchors)
    lines = ["| capture | true shot / read | ours: shot, read | ponomarenko (3 bins): shot, read | ponomarenko (8 "
             "bins): shot, read | estimate_sigma vs the average sigma |", "|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        for name, image, linear in scenes(folder):
            for shot, read, bits in LEVELS:
                capture = simulate(image, folder / f"{image.stem}_{bits}_{shot}", shot, read, bits, linear)
                mine = ours(capture, folder)
                curves = [ponomarenko_curve(capture, bins) for bins in (3, 8)]
                sigma = skimage_sigma(capture)
                cells = [f"{relative(mine['shot'], shot)}, {relative(mine['read'], read)}"]
                cells += ["not installed" if c is None else f"{relative(c[0], shot)}, {relative(c[1], read)}"
                          for c in curves]
                cells.append("not installed" if sigma is None else relative(sigma, average_sigma(capture, shot, read)))
                lines.append(f"| {name}, {bits}-bit | {shot:g} / {read:g} | " + " | ".join(cells) + " |")
                print(lines[-1], flush=True)
        lines += ["", "| real capture | ours: shot, read (95% interval) | ponomarenko (3 bins): shot, read | "
                  "ponomarenko (8 bins): shot, read | estimate_sigma |", "|---|---|---|---|---|"]
        dngs = ROOT.parent / "shared" / "data" / "dng"
        for capture in sorted(dngs.glob("*.dng")):
            mine = ours(capture, folder)
            curves = [ponomarenko_curve(capture, bins) for bins in (3, 8)]
            sigma = skimage_sigma(capture)
            cells = [f"{mine['shot']:.3g} [{mine['shot_interval'][0]:.3g}, {mine['shot_interval'][1]:.3g}], "
                     f"{mine['read']:.3g} [{mine['read_interval'][0]:.3g}, {mine['read_interval'][1]:.3g}]"]
            cells += ["not installed" if c is None else f"{c[0]:.3g}, {c[1]:.3g}" for c in curves]
            cells.append("not installed" if sigma is None else f"{sigma:.3g}")
            lines.append(f"| {capture.name} | " + " | ".join(cells) + " |")
            print(lines[-1], flush=True)
    if args.out:
        Path(args.out).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
