"""`warpsense simulate` (warpsense/simulate.py): images through a camera to RAW safetensors, DNG and a preview,
checked against a numpy reference of the camera (sRGB curve, Bayer sampling, 10-bit rounding) and against rawpy."""

import re

import numpy as np
import pytest
from PIL import Image

from warpsense.cli import main
from warpsense.data.raw import load_raw, read_capture

rawpy = pytest.importorskip("rawpy")
tifffile = pytest.importorskip("tifffile")

# a camera with nothing but a fixed RGGB mosaic and a 10-bit ADC: its RAW has a closed form
CLEAN = ["--config", "configs/default.toml", "--set", "exposure.enabled=false", "--set", "noise.enabled=false",
         "--set", "cfa.mode=fixed"]


def srgb_decode(codes: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 decoding, written out independently of warpsense.data.color."""
    c = codes.astype(np.float64) / 255
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def rggb_reference(linear: np.ndarray, bits: int = 10) -> np.ndarray:
    """[H, W, 3] linear -> the RGGB mosaic at ``bits``, rounded to the ADC's codes, in units of the white level."""
    height, width = linear.shape[0] // 2 * 2, linear.shape[1] // 2 * 2
    channel = np.array([[0, 1], [1, 2]])
    ys, xs = np.mgrid[:height, :width]
    mosaic = linear[ys, xs, channel[ys % 2, xs % 2]]
    levels = 2**bits - 1
    return np.floor(np.clip(mosaic, 0, 1) * levels + 0.5) / levels


def _png(path, height=40, width=58, seed=0):
    codes = np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)
    Image.fromarray(codes).save(path)
    return codes


def test_srgb_image_gives_the_reference_mosaic_dng_and_preview(tmp_path, capsys):
    codes = _png(tmp_path / "street.png", 41, 58)  # an odd height: cropped to the 2 x 2 tile
    out = tmp_path / "out"
    assert main(["simulate", str(tmp_path / "street.png"), *CLEAN, "--out", str(out)]) == 0
    mosaic, metadata = load_raw(out / "street.safetensors")
    expected = rggb_reference(srgb_decode(codes))
    assert mosaic.shape == (1, 40, 58)
    np.testing.assert_allclose(mosaic[0].numpy(), expected, atol=1e-6)
    assert metadata["cfa_pattern"] == "RGGB" and metadata["white_level"] == 1023 and metadata["bit_depth"] == 10
    with rawpy.imread(str(out / "street.dng")) as raw:
        assert raw.white_level == 1023
        letters = "".join(raw.color_desc.decode()[raw.raw_colors_visible[y, x]] for y in (0, 1) for x in (0, 1))
        assert letters == "RGGB"
        np.testing.assert_array_equal(raw.raw_image_visible, np.round(expected * 1023).astype(np.uint16))
    preview = np.asarray(Image.open(out / "street.preview.png"))
    assert preview.shape == (40, 58, 3) and preview.dtype == np.uint8
    # the preview's red at a tile is the tile's R site, sRGB-encoded again: close to the input's red code there
    assert abs(int(preview[0, 0, 0]) - int(codes[0, 0, 0])) <= 2
    assert "simulated 1 of 1 image(s)" in capsys.readouterr().out
    assert not list(out.glob("*tmp*"))


def test_linear_tiff_gives_the_reference_mosaic(tmp_path):
    linear = np.random.default_rng(1).random((32, 48, 3))
    tifffile.imwrite(tmp_path / "lin.tif", np.round(linear * 65535).astype(np.uint16))
    out = tmp_path / "out"
    assert main(["simulate", str(tmp_path / "lin.tif"), *CLEAN, "--linear", "--out", str(out)]) == 0
    mosaic, _ = load_raw(out / "lin.safetensors")
    expected = rggb_reference(np.round(linear * 65535) / 65535)
    np.testing.assert_allclose(mosaic[0].numpy(), expected, atol=1e-6)


def test_noise_is_fixed_per_image_and_seed(tmp_path):
    _png(tmp_path / "a.png")

    def run(name, *extra):
        assert main(["simulate", str(tmp_path / "a.png"), "--config", "configs/default.toml", *extra,
                     "--out", str(tmp_path / name)]) == 0
        return load_raw(tmp_path / name / "a.safetensors")[0]

    first, again, other_seed = run("1"), run("2"), run("3", "--seed", "1")
    assert np.array_equal(first, again)  # eval mode: the fixed noise seed
    assert not np.array_equal(first, other_seed)
    clean = run("4", "--set", "noise.enabled=false")
    assert float((first - clean).abs().mean()) > 1e-3  # the noise is there


def test_batch_goes_on_past_bad_files_and_leaves_nothing_partial(tmp_path, capsys):
    _png(tmp_path / "good.png")
    (tmp_path / "broken.png").write_bytes(b"not a png")
    (tmp_path / "sub").mkdir()
    _png(tmp_path / "sub" / "good.png", seed=3)  # the same stem: would overwrite the first one's outputs
    out = tmp_path / "out"
    code = main(["simulate", str(tmp_path / "good.png"), str(tmp_path / "broken.png"), str(tmp_path / "missing.jpg"),
                 str(tmp_path / "sub" / "good.png"), str(tmp_path / "raw.dng"), *CLEAN, "--out", str(out)])
    assert code == 2
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if "skipped" in line]
    assert len(lines) == 4
    assert any("broken.png: cannot read it as an image" in line for line in lines)
    assert any("missing.jpg: no such file" in line for line in lines)
    assert any("sub/good.png: its outputs good.* would overwrite" in line for line in lines)
    assert any("raw.dng: not a supported sRGB image type" in line and "convert" in line for line in lines)
    assert "simulated 1 of 5 image(s)" in captured.out and "4 failed" in captured.out
    assert sorted(p.name for p in out.iterdir()) == ["good.dng", "good.preview.png", "good.safetensors"]


def test_a_truncated_compressed_tiff_is_skipped_and_the_batch_goes_on(tmp_path, capsys):
    """tifffile's deflate codec raises zlib.error for a cut strip, which is no OSError nor ValueError: it was a
    traceback that stopped the batch (exit 1) before the good image."""
    linear = np.random.default_rng(0).random((32, 48, 3)).astype(np.float32)
    tifffile.imwrite(tmp_path / "good.tif", linear, photometric="rgb")
    tifffile.imwrite(tmp_path / "whole.tif", linear, photometric="rgb", compression="zlib")
    whole = (tmp_path / "whole.tif").read_bytes()
    (tmp_path / "cut.tif").write_bytes(whole[: len(whole) // 2])
    out = tmp_path / "out"
    code = main(["simulate", "--linear", str(tmp_path / "cut.tif"), str(tmp_path / "good.tif"), *CLEAN,
                 "--out", str(out)])
    assert code == 2
    err = capsys.readouterr().err
    assert f"skipped {tmp_path / 'cut.tif'}: cannot read it as an image (error: Error -5" in err
    assert "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == ["good.dng", "good.preview.png", "good.safetensors"]


def test_a_failing_write_leaves_none_of_the_images_files(tmp_path, monkeypatch, capsys):
    import warpsense.data.raw as raw_module

    def broken_dng(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(raw_module, "write_dng", broken_dng)
    _png(tmp_path / "a.png")
    out = tmp_path / "out"
    assert main(["simulate", str(tmp_path / "a.png"), *CLEAN, "--out", str(out)]) == 2
    assert "a.png: disk full" in capsys.readouterr().err
    assert not out.exists()  # nothing was written: the folder made for the outputs goes too


def test_a_cfa_that_is_not_bayer_gets_no_dng_with_a_note(tmp_path, capsys):
    _png(tmp_path / "a.png")
    out = tmp_path / "out"
    assert main(["simulate", str(tmp_path / "a.png"), *CLEAN, "--set", "cfa.pattern=RCCB", "--out", str(out)]) == 0
    assert "no DNG: the CFA RCCB" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["a.preview.png", "a.safetensors"]
    assert load_raw(out / "a.safetensors")[1]["cfa_pattern"] == "RCCB"


def test_checkpoint_camera_output_is_what_predict_reads(tmp_path, capsys):
    from tests.test_cli import _untrained_checkpoint

    checkpoint = _untrained_checkpoint(tmp_path / "c.safetensors", [], 11)
    _png(tmp_path / "a.png", 48, 64)
    out = tmp_path / "out"
    assert main(["simulate", str(tmp_path / "a.png"), "--checkpoint", checkpoint, "--out", str(out)]) == 0
    assert main(["predict", checkpoint, str(out / "a.safetensors"), "--out", str(tmp_path / "seg.png"),
                 "--device", "cpu"]) == 0
    assert Image.open(tmp_path / "seg.png").size[0] == 64
    # the DNG of the same capture reads back in predict's normalisation equal to the safetensors mosaic
    from_dng, _ = read_capture(out / "a.dng")
    np.testing.assert_allclose(from_dng, load_raw(out / "a.safetensors")[0][0].numpy(), atol=1e-6)


@pytest.mark.parametrize("arguments, message", [
    (["--checkpoint", "c.safetensors", "--config", "configs/default.toml"], "leave out --config and --set"),
    ([], "give the camera: --config"),
])
def test_camera_choice_mistakes_are_one_line_errors(tmp_path, capsys, arguments, message):
    _png(tmp_path / "a.png")
    assert main(["simulate", str(tmp_path / "a.png"), *arguments, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_help_says_the_camera_is_required_without_a_checkpoint(capsys):
    """--config has no default here (the command refuses to run without a camera): its help says so."""
    from warpsense.cli import main

    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "required unless --checkpoint" in text and "default: configs/default.toml" not in text


@pytest.mark.parametrize("shape", [(2, 3, 8, 8), (1, 3, 1, 1), (1, 1, 8, 8)])
def test_simulate_image_takes_one_image_of_at_least_a_tile(shape):
    """A batch of two was refused as the camera's image_index of the wrong length, and a 1 x 1 image as the empty
    crop (1, 3, 0, 0) it became; both are one line naming simulate_image's radiance."""
    import torch

    from warpsense.simulate import load_camera, simulate_image

    sim = load_camera("camvid")
    with pytest.raises(ValueError, match=r"^simulate_image: radiance must be one image \[1, 3, H, W\] of at least "
                                         r"the CFA tile \(2 x 2 pixels\), got " + re.escape(str(shape))):
        simulate_image(sim, torch.rand(shape))
    assert simulate_image(sim, torch.rand(1, 3, 3, 5)).shape == (2, 4)  # cropped to whole tiles


@pytest.mark.parametrize("choice", [["--device", "cuda"], ["--set", "run.device=cuda"]])
def test_cuda_without_a_cuda_gpu_is_refused_before_any_output(tmp_path, capsys, monkeypatch, choice):
    """Before: simulate had no --device, never read run.device and ran on the CPU with exit 0 where train, eval and
    predict refuse cuda without CUDA."""
    import torch

    from tests.reliability.conftest import assert_clean_failure

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    _png(tmp_path / "a.png")
    assert_clean_failure(capsys, ["simulate", str(tmp_path / "a.png"), "--config", "configs/default.toml", *choice,
                                  "--out", str(tmp_path / "out")], ("device cuda", "use cpu or auto"),
                         watched=tmp_path)


@pytest.mark.parametrize("device", [pytest.param("cuda", marks=pytest.mark.cuda)])
def test_the_camera_on_cuda_gives_the_cpus_raw(tmp_path, device):
    _png(tmp_path / "a.png", 32, 48)
    for name, choice in (("cpu", "cpu"), ("other", device)):
        assert main(["simulate", str(tmp_path / "a.png"), "--config", "configs/default.toml", "--device", choice,
                     "--out", str(tmp_path / name)]) == 0
    np.testing.assert_allclose(load_raw(tmp_path / "other" / "a.safetensors")[0].numpy(),
                               load_raw(tmp_path / "cpu" / "a.safetensors")[0].numpy(), atol=2 / 1023)


def test_an_image_cropped_to_whole_cfa_tiles_is_said(tmp_path, capsys):
    """Before: a 101x157 image became a 100x156 RAW without a word (predict says its crop)."""
    _png(tmp_path / "odd.png", 101, 157)
    _png(tmp_path / "even.png", 100, 156)
    assert main(["simulate", str(tmp_path / "odd.png"), str(tmp_path / "even.png"), *CLEAN, "--device", "cpu",
                 "--out", str(tmp_path / "out")]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if "cropped" in line]
    assert notes == [f"warpsense simulate: {tmp_path / 'odd.png'}: cropped 101x157 to 100x156 (HxW, top-left kept): "
                     "whole 2 x 2 CFA tiles"]
    assert load_raw(tmp_path / "out" / "odd.safetensors")[0].shape == (1, 100, 156)


def test_help_gives_a_set_example_the_command_reads(capsys):
    """Before: simulate's --set help said "e.g. --set train.epochs=5", a key simulate never reads."""
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--set quantize.bits=8" in text and "train." not in text
