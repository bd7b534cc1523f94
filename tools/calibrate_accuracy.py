"""How well `warpsense calibrate`'s single-capture estimate recovers known noise (docs/guide/calibrate.md, the
accuracy table): captures simulated by `warpsense simulate`'s Python API at known (shot, read, bits), several noise
draws each, from several kinds of scene:

- ``textured``: the tests' textured scene (tests/test_calibrate.py `scene`: a lit gradient, discs, a faint texture,
  grey patches from black to near white), linear;
- ``no-black``: the same scene with its darkest patches lifted to 2% of white (no black region to read the read
  noise from);
- ``camvid``: CamVid train frames (../shared/data/camvid/train, sRGB 8-bit PNGs decoded to linear radiance; skipped
  with a message where the data is absent). The frames carry their own camera's noise, demosaicked and compressed:
  to the simulated sensor it is scene texture;
- ``street``: the project's generated street scenes (`warpsense.data.scenes.render_scene`, quantized to 8-bit sRGB
  as the scenes dataset serves them). Their surfaces are painted with independent per-pixel shading (6-20%), which
  no single-image estimate can tell from sensor noise: reported apart, not in the totals.

The camera is the tests' (configs/default.toml with a fixed RGGB mosaic, no exposure gain, no lens); each capture is
calibrated in memory exactly as a `.safetensors` capture of it is (the mosaic split into CFA site planes with the ADC's
bounds), by `warpsense.calibration.single.estimate_capture`. The report gives, per scene kind and level, the median
and worst relative errors of shot and read, and the captures whose read noise was not resolved (interval from 0).

    python tools/calibrate_accuracy.py --frames 8 --seeds 3  # the guide's CamVid column (about 5 minutes on 2 cores)
    python tools/calibrate_accuracy.py --seeds 10 --kinds textured,no-black  # its synthetic columns
    python tools/calibrate_accuracy.py --frames 2 --seeds 2  # a quick look
    python tools/calibrate_accuracy.py --json all.json       # every capture's estimate
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

LEVELS = [(0.015, 0.002, 10), (0.004, 0.001, 12), (0.001, 0.0005, 12), (0.0005, 0.0005, 14), (0.03, 0.004, 10)]
"""(shot, read, bits) simulated."""
CAMERA = ["exposure.enabled=false", "cfa.mode=\"fixed\"", "optics.enabled=false"]
CAMVID = ROOT.parent / "shared" / "data" / "camvid" / "train"


@dataclass
class Scene:
    kind: str
    name: str
    radiance: object  # torch [1, 3, H, W] linear


def _textured(black: bool):
    import torch

    sys.path.insert(0, str(ROOT / "tests"))
    from test_calibrate import scene

    image = scene()
    if not black:  # lift every patch darker than 2% of white to 2%: no region near black is left
        image = np.where(image < 0.02, 0.02, image)
    return torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]


def _street(index: int):
    import torch

    from warpsense.data.color import srgb_to_linear
    from warpsense.data.scenes import render_scene

    image, _ = render_scene(360, 480, np.random.default_rng([7, index]))
    srgb = torch.from_numpy((image * 255 + 0.5).astype(np.uint8)).permute(2, 0, 1)[None]
    return srgb_to_linear(srgb)


def scenes(frames: int, streets: int) -> list[Scene]:
    """The scenes measured (see the module docstring); CamVid frames spread over its sequences."""
    from warpsense.simulate import read_image

    found = [Scene("textured", "textured", _textured(True)), Scene("no-black", "textured, no black",
                                                                    _textured(False))]
    paths = sorted(CAMVID.glob("*.png"))
    if not paths:
        print(f"calibrate_accuracy: no CamVid frames in {CAMVID}: CamVid skipped", file=sys.stderr)
    elif frames:
        picks = np.linspace(0, len(paths) - 1, frames).round().astype(int)
        found += [Scene("camvid", paths[i].stem, read_image(paths[i])) for i in picks]
    found += [Scene("street", f"street {i}", _street(i)) for i in range(streets)]
    return found


def capture_of(mosaic: np.ndarray, bits: int, name: str):
    """The Capture `read_calibration_capture` makes of a simulated .safetensors mosaic (RGGB, black 0)."""
    from warpsense.calibration.captures import Capture, Site

    white = float(2**bits - 1)
    plane = np.asarray(mosaic, dtype=np.float64)
    sites = [Site(letter, row, col, plane[row::2, col::2], 0.0, 1.0, 1.0 / white)
             for letter, (row, col) in zip("RGGB", [(0, 0), (0, 1), (1, 0), (1, 1)])]
    return Capture(Path(name), sites, "RGGB", white, dict.fromkeys("RGB", 0.0), bits, "warpsense simulated",
                   height=plane.shape[0], width=plane.shape[1])


def measure(scene_list: list[Scene], levels, seeds: int) -> list[dict]:
    """Every (scene, level, seed)'s estimate against the truth."""
    from warpsense.calibration.captures import CalibrateError
    from warpsense.calibration.single import estimate_capture
    from warpsense.simulate import load_camera, simulate_image

    rows = []
    for shot, read, bits in levels:
        with contextlib.redirect_stdout(io.StringIO()):
            sim = load_camera(str(ROOT / "configs" / "default.toml"),
                              CAMERA + [f"noise.shot={shot}", f"noise.read={read}", f"quantize.bits={bits}"])
        for scene in scene_list:
            for seed in range(seeds):
                mosaic = simulate_image(sim, scene.radiance, 1000 * seed + 17)
                start = time.perf_counter()
                row = {"kind": scene.kind, "scene": scene.name, "shot": shot, "read": read, "bits": bits,
                       "seed": seed}
                try:
                    estimate = estimate_capture(capture_of(mosaic, bits, scene.name))
                except CalibrateError as error:
                    row["error"] = str(error)
                else:
                    fit = estimate.fit
                    row.update(shot_estimate=fit.shot, read_estimate=fit.read, shot_error=fit.shot / shot - 1,
                               read_error=fit.read / read - 1, read_interval=list(fit.read_interval),
                               shot_interval=list(fit.shot_interval), resolved=fit.read_interval[0] > 0)
                row["seconds"] = time.perf_counter() - start
                rows.append(row)
                shown = row.get("error") or (f"shot {row['shot_error']:+.1%} read {row['read_error']:+.1%}"
                                             + ("" if row["resolved"] else " (read not resolved)"))
                print(f"{scene.name:>22s} {shot:g}/{read:g}/{bits}b seed {seed}: {shown} "
                      f"[{row['seconds']:.1f} s]", flush=True)
    return rows


def _spread(values: list[float]) -> str:
    if not values:
        return "-"
    values = np.asarray(values)
    worst = values[np.argmax(np.abs(values))]
    return f"{np.median(values):+.1%} (worst {worst:+.1%})"


def table(rows: list[dict]) -> str:
    """Markdown: per scene kind and level, the median and worst errors, the captures outside 15% / 30% and the
    unresolved read noises."""
    lines = ["| scene | shot / read, ADC | captures | shot error: median (worst) | read error: median (worst) | "
             "outside 15% shot / 30% read | read not resolved |", "|---|---|---|---|---|---|---|"]
    kinds = list(dict.fromkeys(row["kind"] for row in rows))
    levels = list(dict.fromkeys((row["shot"], row["read"], row["bits"]) for row in rows))
    for kind in kinds + ["all but street"]:
        for level in levels + [None]:
            mine = [row for row in rows if (row["kind"] == kind or (kind == "all but street" and row["kind"] !=
                                                                    "street"))
                    and (level is None or (row["shot"], row["read"], row["bits"]) == level)]
            if not mine or (kind == "all but street" and level is not None):
                continue
            fitted = [row for row in mine if "error" not in row]
            outside = sum(abs(row["shot_error"]) > 0.15 or abs(row["read_error"]) > 0.30 for row in fitted)
            label = "all" if level is None else f"{level[0]:g} / {level[1]:g}, {level[2]}-bit"
            lines.append(f"| {kind} | {label} | {len(mine)} ({len(mine) - len(fitted)} refused) | "
                         f"{_spread([row['shot_error'] for row in fitted])} | "
                         f"{_spread([row['read_error'] for row in fitted])} | {outside} | "
                         f"{sum(not row['resolved'] for row in fitted)} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=6, help="CamVid train frames (spread over its sequences)")
    parser.add_argument("--streets", type=int, default=2, help="generated street scenes")
    parser.add_argument("--seeds", type=int, default=3, help="noise draws per scene and level")
    parser.add_argument("--kinds", default="textured,no-black,camvid,street", help="scene kinds to measure")
    parser.add_argument("--levels", help="shot/read/bits,... (default: the guide's five)")
    parser.add_argument("--json", help="write every capture's estimate here")
    parser.add_argument("--out", help="write the markdown table here (default: print it)")
    args = parser.parse_args()
    levels = LEVELS if not args.levels else [
        (float(s), float(r), int(b)) for s, r, b in (item.split("/") for item in args.levels.split(","))]
    kinds = set(args.kinds.split(","))
    chosen = [s for s in scenes(args.frames, args.streets) if s.kind in kinds]
    rows = measure(chosen, levels, args.seeds)
    text = table(rows)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
