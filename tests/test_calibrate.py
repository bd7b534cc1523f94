"""`warpsense calibrate` (warpsense/calibration/): the noise of captures made by `warpsense simulate` with known
shot and read is recovered (single captures of a textured scene, and a photon-transfer series); the clipped,
quantized reading's moments match a Monte Carlo draw; bad captures are one-line errors with nothing written and a
batch goes on past them; the preset it writes loads, trains, simulates and serves as a study's camera; the real
DNGs give finite positive estimates."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from warpsense.cli import main

tifffile = pytest.importorskip("tifffile")

# a camera with a fixed RGGB mosaic, no exposure gain and no lens: the radiance reaches the noise as it is
CAMERA = ["--config", "configs/default.toml", "--set", "exposure.enabled=false", "--set", "cfa.mode=\"fixed\""]
LEVELS = [(0.015, 0.002, 10), (0.004, 0.001, 12), (0.0005, 0.0005, 14)]


def scene(height=256, width=384, seed=0) -> np.ndarray:
    """Linear radiance [H, W, 3] in [0, 1]: a lit gradient, coloured discs with sharp edges, a faint texture over
    everything, and grey patches from black to near white (the black ones give the read noise)."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[:height, :width].astype(np.float64)
    image = (0.05 + 0.5 * cols / width + 0.2 * rows / height)[..., None] * np.array([1.0, 0.8, 0.6])
    for _ in range(10):
        cy, cx, radius = rng.uniform(0, height), rng.uniform(0, width), rng.uniform(10, 40)
        image[(rows - cy) ** 2 + (cols - cx) ** 2 < radius**2] = rng.uniform(0.0, 0.8, 3) ** 1.5
    image *= (1 + 0.03 * np.sin(cols * 0.07 + rng.uniform(0, 6)) * np.sin(rows * 0.05))[..., None]
    side = 40
    for i, level in enumerate([0.0, 0.0, 0.0005, 0.002, 0.006, 0.02, 0.05, 0.1, 0.2, 0.35, 0.6, 0.9]):
        top, left = 16 + (i // 6) * (height - 32 - side), 8 + (i % 6) * (side + 22)
        image[top:top + side, left:left + side] = level
    return np.clip(image, 0, 1)


def _tiff(path, image):
    tifffile.imwrite(path, np.round(np.clip(image, 0, 1) * 65535).astype(np.uint16))
    return path


def _simulate(inputs, out, shot, read, bits):
    assert main(["simulate", *map(str, inputs), "--linear", *CAMERA, "--set", f"noise.shot={shot}", "--set",
                 f"noise.read={read}", "--set", f"quantize.bits={bits}", "--out", str(out)]) == 0


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """{(shot, read, bits): the simulated DNG} of the textured scene at each of LEVELS."""
    folder = tmp_path_factory.mktemp("captures")
    source = _tiff(folder / "scene.tif", scene())
    made = {}
    for shot, read, bits in LEVELS:
        _simulate([source], folder / f"b{bits}", shot, read, bits)
        made[(shot, read, bits)] = folder / f"b{bits}" / "scene.dng"
    return made


def _calibrate(tmp_path, *arguments):
    out = tmp_path / "calibration.json"
    code = main(["calibrate", *map(str, arguments), "--json", str(out)])
    return code, json.loads(out.read_text()) if out.exists() else None


# --------------------------------------------------------------------------------------------------------------------
# the model against a Monte Carlo draw


@pytest.mark.parametrize("y, shot, read, bits", [(0.0, 0.015, 0.002, 10), (0.0005, 0.015, 0.002, 10),
                                                 (0.3, 0.004, 0.001, 12), (0.995, 0.01, 0.002, 10),
                                                 (0.002, 0.0005, 0.0005, 14)])
def test_clipped_moments_match_a_monte_carlo_draw(y, shot, read, bits):
    """The reading's mean and variance (clip at 0 and 1, rounding to 2^bits - 1 codes) against 4M draws of exactly
    what the simulator does, and the signal whose clipped mean that is comes back."""
    from warpsense.calibration.model import clipped_moments, noise_variance, signal_from_mean

    step = 1 / (2**bits - 1)
    draws = y + math.sqrt(shot * y + read**2) * np.random.default_rng(0).standard_normal(4_000_000)
    readings = np.round(np.clip(draws, 0, 1) / step) * step
    mean, variance = clipped_moments(np.array([y]), noise_variance(np.array([y]), shot, read**2), 0.0, 1.0, step)
    assert mean[0] == pytest.approx(readings.mean(), abs=4 * readings.std() / 2000)
    assert variance[0] == pytest.approx(readings.var(), rel=0.01)
    assert signal_from_mean(mean, shot, read**2, 0.0, 1.0, step)[0] == pytest.approx(y, abs=1e-9)


# --------------------------------------------------------------------------------------------------------------------
# recovery of known noise


@pytest.mark.parametrize("level", LEVELS, ids=[f"shot{s}-read{r}-{b}bit" for s, r, b in LEVELS])
def test_single_capture_recovers_the_simulated_noise(captures, level, tmp_path):
    """A simulated capture of a textured scene: shot within 10%, read within 25%, and the intervals cover both."""
    shot, read, bits = level
    code, record = _calibrate(tmp_path, captures[level])
    assert code == 0
    noise = record["noise"]
    assert noise["shot"] == pytest.approx(shot, rel=0.10)
    assert noise["read"] == pytest.approx(read, rel=0.25)
    assert noise["shot_interval"][0] < noise["shot"] < noise["shot_interval"][1]
    assert noise["read_interval"][0] <= read * 1.1 and noise["read_interval"][1] >= read * 0.9
    for letter in "RGB":  # every channel has the same noise in the simulator
        assert noise["per_channel"][letter]["shot"] == pytest.approx(shot, rel=0.2)


def no_black(image: np.ndarray) -> np.ndarray:
    """``image`` with everything darker than 2% of white lifted to 2%: no region where the read noise shows."""
    return np.maximum(image, 0.02)


# (scene, shot, read, bits, the camera's noise key): the tests' scene with its black patches and without them.
# Before the fit started from a line through the sets clear of the clips, the 14-bit capture with black patches
# started at a quarter of the shot (a line weighted by each set's own variance, led by a set of two samples drawn
# low) and stayed there, with an interval of [0, inf] (shot -75%, read -46%, and a ZeroDivisionError in the
# electrons); before black patches read all eight zero-sum filters, the 10-bit one's read noise was not resolved.
RECOVERY = [("black", 0.015, 0.002, 10, 17), ("black", 0.0005, 0.0005, 14, 17),
            ("no black", 0.015, 0.002, 10, 17), ("no black", 0.0005, 0.0005, 14, 17)]


@pytest.mark.parametrize("kind, shot, read, bits, key", RECOVERY,
                         ids=[f"{k.replace(' ', '-')}-shot{s}-{b}bit" for k, s, _, b, _ in RECOVERY])
def test_recovery_with_and_without_black_regions(kind, shot, read, bits, key, tmp_path):
    """Captures of the tests' scene drawn with fixed noise keys through `warpsense.simulate`'s API: shot within
    10% either way. With black patches the read noise within 25%; without them it cannot be read (at 2% of white
    its variance is 1-3% of the shot noise's), and the estimate says so: its interval starts at 0, holds the truth,
    and a note names the darkest smooth level. (Over ten noise draws of each, docs/guide/calibrate.md: shot within
    6%, read within 16% with black patches.)"""
    import torch

    from warpsense.simulate import load_camera, simulate_image, write_outputs

    image = scene() if kind == "black" else no_black(scene())
    source = _tiff(tmp_path / "scene.tif", image)
    sim = load_camera("configs/default.toml", [item for item in CAMERA[2:] if item != "--set"]
                      + [f"noise.shot={shot}", f"noise.read={read}", f"quantize.bits={bits}"])
    radiance = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    (tmp_path / "sim").mkdir()
    write_outputs(sim, simulate_image(sim, radiance, key), source, tmp_path / "sim")
    code, record = _calibrate(tmp_path, tmp_path / "sim" / "scene.dng")
    assert code == 0
    noise = record["noise"]
    assert noise["shot"] == pytest.approx(shot, rel=0.10)
    if kind == "black":
        assert noise["read"] == pytest.approx(read, rel=0.25)
        assert noise["read_interval"][0] > 0
    else:
        assert noise["read_interval"][0] == 0 and noise["read_interval"][1] > read
        assert any("not resolved" in note for note in record["notes"])


def test_safetensors_capture_gives_the_dng_estimate(captures, tmp_path):
    """`warpsense simulate`'s .safetensors RAW and its DNG are the same capture: the same estimate."""
    dng = captures[LEVELS[0]]
    _, from_dng = _calibrate(tmp_path, dng)
    _, from_raw = _calibrate(tmp_path, dng.with_suffix(".safetensors"))
    assert from_raw["noise"]["shot"] == pytest.approx(from_dng["noise"]["shot"], rel=1e-6)
    assert from_raw["noise"]["read"] == pytest.approx(from_dng["noise"]["read"], rel=1e-6)


def test_series_recovers_the_simulated_noise(tmp_path):
    """Flat fields two at a time at six exposures and two dark frames (photon transfer): shot within 5%, read
    within 10%; without the dark frames the shot still within 5%."""
    shot, read, bits = 0.004, 0.001, 12
    names = []
    for level in (0.02, 0.05, 0.1, 0.2, 0.4, 0.6):
        for copy in "ab":
            names.append(_tiff(tmp_path / f"flat_{level}_{copy}.tif", np.full((96, 128, 3), level)))
    darks = [_tiff(tmp_path / f"dark_{copy}.tif", np.zeros((96, 128, 3))) for copy in "ab"]
    _simulate(names + darks, tmp_path / "sim", shot, read, bits)
    flats = [tmp_path / "sim" / f"{path.stem}.dng" for path in names]
    code, record = _calibrate(tmp_path, "--series", *flats, "--dark", *[tmp_path / "sim" / f"{p.stem}.dng"
                                                                          for p in darks])
    assert code == 0 and record["method"].startswith("photon transfer")
    assert record["noise"]["shot"] == pytest.approx(shot, rel=0.05)
    assert record["noise"]["read"] == pytest.approx(read, rel=0.10)
    assert len(record["series"]["pairs"]) == 6 and len(record["series"]["darks"]) == 2
    code, record = _calibrate(tmp_path, "--series", *flats)
    assert code == 0 and record["noise"]["shot"] == pytest.approx(shot, rel=0.05)


def test_series_reports_a_flat_field_without_partner(tmp_path):
    """A flat field with no frame of equal exposure is skipped and named; the pairs are still fitted (exit 2)."""
    names = [_tiff(tmp_path / f"flat_{level}_{copy}.tif", np.full((64, 96, 3), level))
             for level in (0.05, 0.2, 0.5) for copy in "ab"]
    names.append(_tiff(tmp_path / "lonely.tif", np.full((64, 96, 3), 0.3)))
    _simulate(names, tmp_path / "sim", 0.01, 0.003, 10)
    code, record = _calibrate(tmp_path, "--series", *[tmp_path / "sim" / f"{p.stem}.dng" for p in names])
    assert code == 2
    assert [entry["path"].endswith("lonely.dng") for entry in record["failed"]] == [True]
    assert record["noise"]["shot"] == pytest.approx(0.01, rel=0.1)


# --------------------------------------------------------------------------------------------------------------------
# the JSON and the preset


def test_json_fields(captures, tmp_path):
    _, record = _calibrate(tmp_path, captures[LEVELS[0]])
    assert set(record) >= {"method", "camera", "units", "noise", "electrons", "study_light", "files", "failed",
                           "notes", "preset"}
    assert set(record["noise"]) >= {"shot", "read", "shot_interval", "read_interval", "per_channel",
                                    "overdispersion", "points"}
    assert set(record["noise"]["per_channel"]) == {"R", "G", "B"}
    shot, read = record["noise"]["shot"], record["noise"]["read"]
    electrons = record["electrons"]
    # white 1023, black 0: K = shot * 1023 DN/e-, full well 1 / shot, read noise read / shot electrons
    assert electrons["conversion_gain_dn_per_electron"] == pytest.approx(shot * 1023)
    assert electrons["full_well_electrons"] == pytest.approx(1 / shot)
    assert electrons["read_noise_electrons"] == pytest.approx(read / shot)
    assert record["study_light"]["full_well_electrons"] == pytest.approx(1 / shot)
    assert record["study_light"]["bits"] == 10
    (entry,) = record["files"]
    assert entry["path"].endswith("scene.dng") and entry["cfa_pattern"] == "RGGB" and entry["white_level"] == 1023
    regions = entry["regions"]["G"]
    assert 0 < regions["samples"] <= regions["of"] and regions["level_sets"] >= 3
    assert regions["levels"][0] < 0.01 < 0.5 < regions["levels"][1]  # from the black patch to the bright ones


def test_preset_loads_and_trains_and_simulates(captures, tmp_path, monkeypatch):
    """--out writes a preset over camvid_raw_fixed whose noise is the estimate: load_config reads it, `train
    --config` runs a step with it and `simulate --config` captures through it; --plot draws the figure."""
    from warpsense.config import load_config

    monkeypatch.chdir(tmp_path)
    preset, plot = tmp_path / "my_sensor.toml", tmp_path / "noise.png"
    assert main(["calibrate", str(captures[LEVELS[0]]), "--out", str(preset), "--plot", str(plot), "--json",
                 "c.json"]) == 0
    record = json.loads((tmp_path / "c.json").read_text())
    assert record["preset"] == str(preset)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    config = load_config(str(preset))
    assert config.noise.shot == record["noise"]["shot"] and config.noise.read == record["noise"]["read"]
    assert config.quantize.bits == 10 and config.run.name == "my_sensor"
    assert config.cfa.mode == "fixed" and config.data.dataset == "camvid"  # the base preset's
    small = ["--set", "data.dataset=\"scenes\"", "--set", "data.scenes_train=2", "--set", "data.scenes_val=2",
             "--set", "data.batch_size=2", "--set", "data.crop_height=48", "--set", "data.crop_width=64",
             "--set", "data.scene_height=48", "--set", "data.scene_width=64", "--set", "data.paste_classes=\"\"",
             "--set", "train.epochs=1", "--set", "train.warmup_epochs=0", "--set", "train.max_steps_per_epoch=1",
             "--set", "train.plots=false", "--set", "train.cuda_graph=false", "--set", "run.device=\"cpu\"",
             "--set", "model.width=4", "--set", "model.full_width=4", "--set", "optics.enabled=false"]
    assert main(["train", "--config", str(preset), *small, "--no-progress"]) == 0
    assert json.loads((tmp_path / "runs" / "my_sensor" / "config.json").read_text())["noise"]["shot"] == \
        record["noise"]["shot"]
    image = _tiff(tmp_path / "grey.tif", np.full((32, 48, 3), 0.25))
    assert main(["simulate", str(image), "--linear", "--config", str(preset), "--set", "optics.enabled=false",
                 "--out", "sim"]) == 0
    from warpsense.data.raw import load_raw

    _, metadata = load_raw(tmp_path / "sim" / "grey.safetensors")
    assert metadata["simulated"]["noise_shot"] == pytest.approx(record["noise"]["shot"], rel=1e-5)


def test_preset_serves_as_a_study_camera(captures, tmp_path, shared_data, monkeypatch):
    """A study plan takes the --out preset as a camera and the JSON's study_light as a light. The preset inherits
    the CamVid recipe, whose data a plan checks (run from the repository, where ../shared/data is)."""
    from warpsense.study.plan import load_plan

    preset = tmp_path / "my_sensor.toml"
    code, record = _calibrate(tmp_path, captures[LEVELS[0]], "--out", preset)
    assert code == 0
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    plan = tmp_path / "plan.toml"
    light = record["study_light"]
    plan.write_text(f'[study]\nname = "mine"\nseeds = [0]\nreference = "mine"\n'
                    f'[[camera]]\nname = "mine"\npreset = "{preset}"\n'
                    f'[[light]]\nname = "{light["name"]}"\nfull_well_electrons = {light["full_well_electrons"]}\n'
                    f'read_electrons = {light["read_electrons"]}\nbits = {light["bits"]}\n')
    loaded = load_plan(str(plan))
    cell = loaded.config(next(iter(loaded.cells())), tmp_path / "study")
    assert cell.noise.full_well_electrons == pytest.approx(1 / record["noise"]["shot"])


def test_photon_budget_base_gets_electrons(captures, tmp_path):
    """--base camvid_photons: the preset states the sensor in [photons] (full well 1 / shot, read noise read /
    shot electrons), and loads with the photon budget on."""
    from warpsense.config import load_config

    preset = tmp_path / "night.toml"
    code, record = _calibrate(tmp_path, captures[LEVELS[0]], "--out", preset, "--base", "camvid_photons")
    assert code == 0
    config = load_config(str(preset))
    assert config.photons.enabled and not config.noise.enabled
    assert config.photons.full_well_electrons == pytest.approx(1 / record["noise"]["shot"])
    assert config.photons.read_electrons == pytest.approx(record["noise"]["read"] / record["noise"]["shot"])


# --------------------------------------------------------------------------------------------------------------------
# bad input


def _files(folder):
    return sorted(p.name for p in folder.rglob("*") if p.is_file())


def _one_error_line(capsys) -> str:
    error = capsys.readouterr().err.strip()
    assert "Traceback" not in error
    lines = error.splitlines()
    assert len(lines) == 1, error
    return lines[0]


def test_png_is_refused_in_one_line_with_nothing_written(tmp_path, capsys):
    from PIL import Image

    Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(tmp_path / "photo.png")
    before = _files(tmp_path)
    code = main(["calibrate", str(tmp_path / "photo.png"), "--json", str(tmp_path / "c.json"), "--out",
                 str(tmp_path / "p.toml"), "--plot", str(tmp_path / "p.png")])
    assert code == 2
    line = _one_error_line(capsys)
    assert "photo.png" in line and "LibRaw cannot read it" in line
    assert _files(tmp_path) == before


@pytest.mark.parametrize("kind, value, size, reason", [
    ("saturated", 1.0, (64, 96), "saturated"), ("dark", 0.0, (64, 96), "all dark"),
    ("tiny", 0.3, (24, 24), "too few smooth pixels")])
def test_unusable_capture_is_refused_naming_what_is_missing(tmp_path, capsys, kind, value, size, reason):
    image = _tiff(tmp_path / f"{kind}.tif", np.full((*size, 3), value))
    _simulate([image], tmp_path / "sim", 0.01, 0.002, 10)
    capsys.readouterr()
    before = _files(tmp_path)
    capture = tmp_path / "sim" / f"{kind}.safetensors"
    assert main(["calibrate", str(capture), "--json", str(tmp_path / "c.json")]) == 2
    line = _one_error_line(capsys)
    assert str(capture) in line and reason in line
    assert _files(tmp_path) == before


def test_batch_goes_on_past_a_bad_file(captures, tmp_path, capsys):
    """A PNG among the captures: skipped and named, the others calibrated and written, the JSON lists it, exit 2."""
    from PIL import Image

    Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(tmp_path / "photo.png")
    code, record = _calibrate(tmp_path, captures[LEVELS[0]], tmp_path / "photo.png")
    assert code == 2
    assert re.search(r"skipped .*photo\.png", capsys.readouterr().err)
    assert [entry["path"] for entry in record["failed"]] == [str(tmp_path / "photo.png")]
    assert len(record["files"]) == 1 and record["noise"]["shot"] == pytest.approx(LEVELS[0][0], rel=0.1)


def test_captures_of_different_settings_are_not_pooled(captures, tmp_path, capsys):
    code = main(["calibrate", str(captures[LEVELS[0]]), str(captures[LEVELS[1]]), "--json",
                 str(tmp_path / "c.json")])
    assert code == 2
    assert "calibrate them separately" in _one_error_line(capsys)
    assert not (tmp_path / "c.json").exists()


def test_two_captures_of_one_sensor_are_fitted_together(tmp_path):
    shot, read, bits = 0.008, 0.003, 12
    sources = [_tiff(tmp_path / f"scene{seed}.tif", scene(192, 256, seed)) for seed in (1, 2)]
    _simulate(sources, tmp_path / "sim", shot, read, bits)
    code, record = _calibrate(tmp_path, tmp_path / "sim" / "scene1.dng", tmp_path / "sim" / "scene2.dng")
    assert code == 0 and len(record["files"]) == 2
    assert record["noise"]["shot"] == pytest.approx(shot, rel=0.1)
    assert record["noise"]["read"] == pytest.approx(read, rel=0.25)


# --------------------------------------------------------------------------------------------------------------------
# real captures


@pytest.mark.parametrize("name", ["canon_eos_kiss_x4_colorchart_rggb14.dng", "rpi_imx296_checkerboard_bggr10.dng",
                                  "pidng_indoor_gbrg10.dng"])
def test_real_dngs_give_finite_positive_estimates(shared_data, tmp_path, name):
    code, record = _calibrate(tmp_path, shared_data / "dng" / name)
    assert code == 0
    noise = record["noise"]
    assert math.isfinite(noise["shot"]) and noise["shot"] > 0
    assert 0 < noise["shot_interval"][0] < noise["shot"] < noise["shot_interval"][1]
    assert math.isfinite(noise["read"]) and noise["read"] >= 0 and noise["read_interval"][1] > 0
    if name.startswith("pidng"):  # its metadata's black level (0) is below its darkest pixels (~70 of 1023)
        assert any("not resolved" in note for note in record["notes"])
    else:
        assert noise["read_interval"][0] > 0  # resolved: dark regions in the scene
        electrons = record["electrons"]
        assert 1000 < electrons["full_well_electrons"] < 100000 and 0.5 < electrons["read_noise_electrons"] < 50
