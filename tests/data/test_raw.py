"""Raw conversion validated against rawpy/LibRaw on the real captures in ../shared/data/dng."""

from pathlib import Path

import numpy as np
import pytest
import torch

from warpsense.camera.cfa import letters_to_phi
from warpsense.cli import main
from warpsense.ops import cfa_mosaic

rawpy = pytest.importorskip("rawpy")
from warpsense.data.raw import (  # noqa: E402
    RawFileError,
    bin_mosaic,
    convert_file,
    preview_grey,
    read_raw_file,
    write_dng,
)

GOOD = {"canon_eos_kiss_x4_colorchart_rggb14.dng": "RGGB", "pidng_indoor_gbrg10.dng": "GBRG",
        "rpi_imx296_checkerboard_bggr10.dng": "BGGR"}
REMOSAIC_TOLERANCE = 1e-4  # of the white level: LibRaw's 16-bit output quantizes to ~1.5e-5 steps


def rawpy_letters(path):
    with rawpy.imread(str(path)) as raw:
        colors = raw.raw_colors_visible
        description = raw.color_desc.decode()
        return "".join(description[colors[y, x]] for y in range(2) for x in range(2))


@pytest.mark.parametrize("name", list(GOOD))
def test_cfa_letters_equal_rawpy_view(shared_data, name):
    path = shared_data / "dng" / name
    _, metadata = read_raw_file(path)
    assert metadata["cfa_pattern"] == rawpy_letters(path) == GOOD[name]


@pytest.mark.parametrize("name", list(GOOD))
def test_warpsense_remosaics_librarys_linear_demosaic(shared_data, name):
    """cfa_mosaic with the file's layout as one-hot phi, applied to LibRaw's linear demosaic (raw colour space, no
    white balance, linear gamma, no auto-brightness, 16 bits), reproduces the normalised mosaic at every site up to
    one global scale, within REMOSAIC_TOLERANCE (pixels between 1% and 95% of white, away from clipping)."""
    path = shared_data / "dng" / name
    mosaic, metadata = read_raw_file(path)
    with rawpy.imread(str(path)) as raw:
        rgb = raw.postprocess(output_color=rawpy.ColorSpace.raw, gamma=(1, 1), no_auto_bright=True,
                              use_camera_wb=False, use_auto_wb=False, user_wb=[1, 1, 1, 1], output_bps=16,
                              demosaic_algorithm=rawpy.DemosaicAlgorithm.LINEAR, user_flip=0)
    pattern = metadata["cfa_pattern"]
    phi = letters_to_phi([list(pattern[:2]), list(pattern[2:])])
    remosaic = cfa_mosaic(torch.from_numpy(rgb.astype(np.float32)).permute(2, 0, 1)[None], phi)[0, 0].numpy()
    assert remosaic.shape == mosaic.shape
    valid = (mosaic > 0.01) & (mosaic < 0.95)
    scale = (remosaic[valid] * mosaic[valid]).sum() / (remosaic[valid] ** 2).sum()
    assert np.abs(scale * remosaic - mosaic)[valid].max() < REMOSAIC_TOLERANCE


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_simulated_raw_round_trip_through_dng(tmp_path, pattern):
    from warpsense.camera import CFA
    from warpsense.ops import quantize_ste

    radiance = torch.rand(1, 3, 48, 64)
    raw = quantize_ste(CFA(pattern, 2, "fixed")(radiance), 10)[0, 0].numpy()
    write_dng(tmp_path / "sim.dng", raw, pattern, black_level=64, white_level=1023)
    assert rawpy_letters(tmp_path / "sim.dng") == pattern
    mosaic, metadata = read_raw_file(tmp_path / "sim.dng")
    assert metadata["cfa_pattern"] == pattern and metadata["white_level"] == 1023
    expected = (np.round(64 + raw * (1023 - 64)) - 64) / (1023 - 64)
    np.testing.assert_allclose(mosaic, expected, atol=1e-6)


def test_convert_cli_writes_readable_files_and_skips_bad_ones(shared_data, tmp_path, capsys):
    code = main(["convert", str(shared_data / "dng"), "--out", str(tmp_path), "--no-progress"])
    assert code == 2  # the folder holds bad/ files, which fail (exit 2, as every command's errors)
    err = capsys.readouterr().err
    assert "linear_raw_not_cfa.dng: not a colour-filter mosaic" in err
    assert "truncated_leica_m10.dng: LibRaw cannot read it" in err
    assert "TiffTag" not in err and len(err.splitlines()) == 2  # one line per skipped file, nothing else
    outputs = sorted(p.name for p in tmp_path.iterdir())
    assert outputs == sorted(n.replace(".dng", ".safetensors") for n in GOOD)  # no partial files
    from warpsense.data import load_raw

    tensor, metadata = load_raw(tmp_path / "pidng_indoor_gbrg10.safetensors")
    assert tensor.shape == (1, 480, 640) and tensor.dtype == torch.float32
    assert metadata["cfa_pattern"] == "GBRG" and metadata["bit_depth"] == 10 and len(metadata["source_sha256"]) == 64


def test_good_files_convert_with_exit_zero(shared_data, tmp_path):
    assert main(["convert", str(shared_data / "dng" / "*.dng"), "--out", str(tmp_path), "--no-progress"]) == 0
    assert len(list(tmp_path.glob("*.safetensors"))) == 3


@pytest.mark.parametrize("name,reason", [("linear_raw_not_cfa.dng", "not a colour-filter mosaic"),
                                         ("truncated_leica_m10.dng", "LibRaw cannot read it")])
def test_bad_files_clear_errors(shared_data, name, reason):
    with pytest.raises(RawFileError, match=reason):
        read_raw_file(shared_data / "dng" / "bad" / name)


def test_phase_offset_and_binning():
    from warpsense.camera.geometry import phase_offset

    assert phase_offset("RGGB", "RGGB") == (0, 0)
    assert phase_offset("GBRG", "RGGB") == (1, 0)
    assert phase_offset("GRBG", "RGGB") == (0, 1)
    assert phase_offset("BGGR", "RGGB") == (1, 1)
    mosaic = torch.tensor([[1.0, 2.0], [3.0, 4.0]]).repeat(4, 4)
    torch.testing.assert_close(bin_mosaic(mosaic, 2), torch.tensor([[1.0, 2.0], [3.0, 4.0]]).repeat(2, 2))


def test_prepare_capture_crops_into_the_models_phase_then_bins():
    """A GBRG capture 9 x 17 (odd: its last row and column are no whole tile) read by an RGGB model: cropped by one
    row into RGGB, cut to 8 x 16, clipped to [0, 1] and binned by 2 (16 / 8 wide) with each site's plane kept."""
    from warpsense.data.raw import prepare_capture

    sites = {"R": 0.2, "G": 0.5, "B": 1.5}  # B above the white level: clipped
    gbrg = np.array([[sites["G"], sites["B"]], [sites["R"], sites["G"]]], dtype=np.float32)
    mosaic = np.tile(gbrg, (5, 9))[:9, :17]
    prepared, factor, crop = prepare_capture(mosaic, "GBRG", "RGGB", target_width=8)
    assert crop == (1, 0) and factor == 2 and prepared.shape == (4, 8)
    torch.testing.assert_close(prepared, torch.tensor([[0.2, 0.5], [0.5, 1.0]]).repeat(2, 4))


def test_predict_on_real_capture_and_refuses_non_bayer(shared_data, tmp_path):
    from warpsense.config import load_config
    from warpsense.train.engine import train

    config = load_config(None, ["cfa.mode=fixed", "train.epochs=1", "train.warmup_epochs=0", "data.scenes_train=8",
                                "data.scenes_val=2", "data.batch_size=4", "data.scene_height=32", "data.scene_width=48",
                                "data.crop_height=32", "data.crop_width=48", f"run.output_dir={tmp_path}",
                                "train.plots=false"])
    run = train(config, progress=False)
    dng = shared_data / "dng" / "pidng_indoor_gbrg10.dng"
    out = tmp_path / "pred.png"
    assert main(["predict", str(run / "checkpoint_last.safetensors"), str(dng), "--out", str(out), "--device", "cpu",
                 "--no-legend"]) == 0
    from PIL import Image

    mosaic, _ = read_raw_file(dng)
    labels = np.asarray(Image.open(out))
    assert labels.shape == (*mosaic.shape, 3)  # as large as the capture
    # convert's output is an input too, and the image type follows the suffix (JPEG bytes for .jpg)
    converted = convert_file(dng, tmp_path / "converted")
    jpeg = tmp_path / "pred.jpg"
    assert main(["predict", str(run / "checkpoint_last.safetensors"), str(converted), "--out", str(jpeg),
                 "--device", "cpu", "--overlay"]) == 0
    with Image.open(jpeg) as image:
        assert image.format == "JPEG" and image.width == mosaic.shape[1] and image.height > mosaic.shape[0]  # legend
    code = main(["predict", str(run / "checkpoint_last.safetensors"), str(dng), "--out", str(tmp_path / "p.xyz")])
    assert code == 2 and not (tmp_path / "p.xyz").exists()
    config.cfa.pattern, config.cfa.mode, config.run.name = "RCCC", "fixed", "rccc"
    run = train(config, progress=False)
    code = main(["predict", str(run / "checkpoint_last.safetensors"),
                 str(shared_data / "dng" / "pidng_indoor_gbrg10.dng"), "--out", str(tmp_path / "no.png")])
    assert code == 2 and not (tmp_path / "no.png").exists()


def _simulated_dng(path, pattern="RGGB"):
    write_dng(path, np.random.default_rng(0).random((32, 48)), pattern, black_level=64, white_level=1023)
    return path


def test_batch_problems_are_reported_and_the_batch_goes_on(tmp_path, capsys):
    """Issue 14 item 4: a truncated DNG, a plain TIFF named .dng, two inputs with one stem, folders named like raw
    files and a folder without raws: each is one line on stderr, the good files still convert, exit 2."""
    import tifffile

    inputs = tmp_path / "in"
    (inputs / "a").mkdir(parents=True)
    (inputs / "b").mkdir()
    _simulated_dng(inputs / "a" / "frame.dng")
    _simulated_dng(inputs / "b" / "frame.dng", "BGGR")  # same stem as a/frame.dng
    whole = _simulated_dng(inputs / "a" / "whole.dng").read_bytes()
    (inputs / "a" / "cut.dng").write_bytes(whole[: len(whole) // 2])  # truncated inside the pixel data
    tifffile.imwrite(inputs / "a" / "plain.dng", np.zeros((16, 16), dtype=np.uint16))
    (inputs / "a" / "folder.dng").mkdir()
    (tmp_path / "empty").mkdir()
    out = tmp_path / "out"
    code = main(["convert", str(inputs), str(tmp_path / "empty"), "--out", str(out), "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err
    assert "cut.dng: LibRaw cannot" in err
    assert "plain.dng: named .dng but has no DNGVersion tag" in err
    assert "frame.safetensors would overwrite the one from" in err
    assert "folder.dng: is a directory" in err
    assert "empty: no raw files" in err
    assert sorted(p.name for p in out.iterdir()) == ["frame.safetensors", "whole.safetensors"]
    assert all(len(line) < 300 for line in err.splitlines())


def test_predict_legend_scales_with_the_image_and_the_overlay_has_no_checkerboard():
    from warpsense.predict import legend_strip

    small = legend_strip(["sky", "road"], {0, 1}, 2, 480)
    large = legend_strip(["sky", "road"], {0, 1}, 2, 1734)
    assert small.shape[1] == 480 and large.shape[1] == 1734
    assert large.shape[0] >= 1734 // 60 + 8 > small.shape[0]  # the text grows with the capture
    flat = np.tile(np.array([[0.2, 0.5], [0.5, 0.8]]), (3, 4))[:5, :7]  # a flat scene through RGGB, odd size
    preview = preview_grey(flat)
    assert preview.shape == (5, 7)
    np.testing.assert_allclose(preview[:4, :6], 0.5)  # no checkerboard left (the odd last row / column: its edge)


@pytest.mark.parametrize("pattern", ["empty", "*.dng", "empty/**/*.nef"])
def test_convert_with_no_raw_file_is_one_line_error_exit_2(tmp_path, capsys, pattern):
    """An empty folder or a pattern that matches nothing used to print "converted 0 of 0 file(s) ...; 1 failed" and
    two empty progress bars, exit 1: it is an error naming the input, exit 2, nothing written."""
    from tests.reliability.conftest import assert_clean_failure

    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("not a raw file")
    out = tmp_path / "out"
    assert_clean_failure(capsys, ["convert", str(tmp_path / pattern), "--out", str(out)],
                         ("nothing to convert:", str(tmp_path / pattern)), watched=tmp_path)


def test_convert_exits_2_when_a_file_of_the_batch_fails(tmp_path, capsys):
    """The batch goes on past a bad file and the good one converts, but the exit status says it failed: 2, as every
    command's errors (it was 1)."""
    _simulated_dng(tmp_path / "good.dng")
    (tmp_path / "bad.dng").write_bytes(b"not a raw file\n" * 20)
    out = tmp_path / "out"
    assert main(["convert", str(tmp_path / "good.dng"), str(tmp_path / "bad.dng"), "--out", str(out),
                 "--no-progress"]) == 2
    assert "bad.dng" in capsys.readouterr().err and [p.name for p in out.iterdir()] == ["good.safetensors"]


def test_convert_run_again_keeps_up_to_date_outputs_and_goes_on_after_an_interruption(tmp_path, capsys,
                                                                                     monkeypatch):
    """A batch interrupted after its first file exits 130 in one line with that file kept; run again it converts
    only the rest (an output of the same source bytes is kept), a changed source is converted again, and --force
    converts everything."""
    from warpsense.data import raw

    for name in ("a", "b"):
        _simulated_dng(tmp_path / f"{name}.dng")
    out = tmp_path / "out"
    command = ["convert", str(tmp_path / "a.dng"), str(tmp_path / "b.dng"), "--out", str(out), "--no-progress"]
    converted = []
    original = raw.convert_file

    def interrupted_at_b(path, out_dir):
        if path.name == "b.dng" and not converted:
            converted.append(path)
            raise KeyboardInterrupt
        return original(path, out_dir)

    monkeypatch.setattr(raw, "convert_file", interrupted_at_b)
    assert main(command) == 130
    assert capsys.readouterr().err == "warpsense convert: interrupted\n"
    assert sorted(p.name for p in out.iterdir()) == ["a.safetensors"]
    first = (out / "a.safetensors").stat().st_mtime_ns

    calls = []
    monkeypatch.setattr(raw, "convert_file", lambda path, out_dir: calls.append(path.name) or original(path, out_dir))
    assert main(command) == 0
    assert calls == ["b.dng"] and (out / "a.safetensors").stat().st_mtime_ns == first
    assert "(1 up to date from an earlier run, kept)" in capsys.readouterr().out  # b converted, a kept

    write_dng(tmp_path / "a.dng", np.random.default_rng(1).random((32, 48)), "RGGB", black_level=64)  # new bytes
    calls.clear()
    assert main(command) == 0 and calls == ["a.dng"]
    assert "(1 up to date from an earlier run, kept)" in capsys.readouterr().out
    calls.clear()
    assert main([*command, "--force"]) == 0 and calls == ["a.dng", "b.dng"]

    def unreadable(self):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "read_bytes", unreadable)  # a source that cannot be read any more
    with pytest.raises(RawFileError, match=f"^{tmp_path / 'a.dng'}: cannot read it \\(\\[Errno 13\\]"):
        raw.up_to_date(tmp_path / "a.dng", out / "a.safetensors")


@pytest.mark.parametrize("white", [64, 40])
def test_a_white_level_not_above_the_black_level_is_refused(tmp_path, capsys, white):
    """(value - black) / (white - black) made a mosaic of NaN (white at black, with a RuntimeWarning) or of values
    flipped around black (white below it), converted with exit 0."""
    from tests.reliability.conftest import assert_clean_failure

    path = tmp_path / "flat.dng"
    write_dng(path, np.full((32, 48), 64, dtype=np.uint16), "RGGB", black_level=64, white_level=white)
    assert_clean_failure(capsys, ["convert", str(path), "--out", str(tmp_path / "out"), "--no-progress"],
                         (f"{path}: its white level {white} is not above its black level(s) 64",), watched=tmp_path)
