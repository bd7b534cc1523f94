"""MTF of sampled PSFs (warpsense/optics/mtf.py) against closed forms, and `warpsense lens --plot`."""

import json

import numpy as np
import pytest
from PIL import Image

from warpsense.cli import main
from warpsense.optics import Lens
from warpsense.optics.mtf import lens_mtfs, mtf


def test_a_point_psf_passes_every_frequency():
    psf = np.zeros((9, 9))
    psf[4, 4] = 1.0
    curves = mtf(psf)
    for axis in ("x", "y", "radial"):
        np.testing.assert_allclose(curves[axis], 1.0, atol=1e-12)
    assert curves["frequency"][0] == 0 and curves["frequency"][-1] == 0.5


def test_a_gaussian_psf_gives_the_gaussian_mtf():
    """A Gaussian of sigma pixels has MTF exp(-2 pi^2 sigma^2 f^2) (aliasing and truncation below 1e-4 here)."""
    sigma, half = 1.5, 10
    y, x = np.mgrid[-half:half + 1, -half:half + 1]
    psf = np.exp(-(x**2 + y**2) / (2 * sigma**2))
    curves = mtf(psf * 7.0)  # any scale: normalised at DC
    expected = np.exp(-2 * np.pi**2 * sigma**2 * curves["frequency"] ** 2)
    np.testing.assert_allclose(curves["x"], expected, atol=1e-4)
    np.testing.assert_allclose(curves["y"], expected, atol=1e-4)
    np.testing.assert_allclose(curves["radial"][:100], expected[:100], atol=2e-3)  # rings: a 1/256 wide average


def test_a_horizontal_box_psf_blurs_along_x_only():
    """A 1 x 3 box: |sin(3 pi f) / (3 sin(pi f))| along x (the Dirichlet kernel), 1 along y."""
    psf = np.zeros((5, 5))
    psf[2, 1:4] = 1.0
    curves = mtf(psf)
    f = curves["frequency"][1:]
    np.testing.assert_allclose(curves["x"][1:], np.abs(np.sin(3 * np.pi * f) / (3 * np.sin(np.pi * f))), atol=1e-12)
    np.testing.assert_allclose(curves["y"], 1.0, atol=1e-12)


@pytest.mark.parametrize("psf", [np.zeros((5, 5)), np.ones((3, 4)), np.full((3, 3), np.nan)])
def test_a_psf_that_is_not_one_is_refused(psf):
    with pytest.raises(ValueError, match="mtf: a PSF must"):
        mtf(psf)


def _aberration_free(tmp_path):
    data = json.loads(open("configs/lenses/phone_80deg.json").read())
    data.update(name="perfect", zernike_waves={"4": {"constant": 0.0}}, psf_grid=[3, 3])
    path = tmp_path / "perfect.json"
    path.write_text(json.dumps(data))
    return Lens.from_json(path)


def test_an_aberration_free_lens_has_mtf_one_at_dc_falling_to_nyquist_and_beats_an_aberrated_corner(tmp_path):
    perfect = lens_mtfs(_aberration_free(tmp_path).psf_grid().detach().numpy())
    for where in ("on-axis", "corner"):
        for curves in perfect[where]:
            assert curves["x"][0] == pytest.approx(1.0, abs=1e-12)
            assert np.all(np.diff(curves["x"]) <= 1e-9) and np.all(np.diff(curves["y"]) <= 1e-9)
            assert curves["x"][-1] < 0.9 * curves["x"][0]  # diffraction and the pixel's aperture
    # diffraction: the longer wavelength (red) transfers less than the blue at mid frequencies
    quarter = 64  # 0.25 cycles/pixel
    assert perfect["on-axis"][0]["x"][quarter] < perfect["on-axis"][2]["x"][quarter]
    # the shipped wide lens's corner (defocus, astigmatism, coma) transfers less than an aberration-free one
    wide = Lens.from_json("phone_80deg")
    wide.spec.psf_grid = (3, 3)
    aberrated = lens_mtfs(wide.psf_grid().detach().numpy())
    assert aberrated["corner"][1]["radial"][quarter] < perfect["corner"][1]["radial"][quarter] - 0.1


def test_lens_plot_writes_the_png(tmp_path, capsys):
    out = tmp_path / "lens.png"
    _aberration_free(tmp_path)  # writes perfect.json
    assert main(["lens", str(tmp_path / "perfect.json"), "--plot", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    with Image.open(out) as image:
        assert image.format == "PNG" and image.size[0] > 800 and image.size[1] > 500
    assert [p.name for p in tmp_path.iterdir() if "tmp" in p.name] == []


def test_lens_plot_to_a_missing_folder_is_a_one_line_error_before_any_work(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("warpsense.optics.lens.Lens.from_json", lambda *a, **k: pytest.fail("rendered the lens"))
    assert main(["lens", "phone_80deg", "--plot", str(tmp_path / "nowhere" / "lens.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--plot" in err and "does not exist" in err


def test_lens_plot_suffix_names_its_format_and_an_unknown_one_is_refused_before_any_work(tmp_path, capsys,
                                                                                       monkeypatch):
    """--plot lens.pdf writes a PDF (it wrote PNG bytes under any name); a suffix matplotlib does not write is one
    line naming the formats, before the lens is rendered."""
    for name in ("lens.foo", "lens"):
        with monkeypatch.context() as patched:
            patched.setattr("warpsense.optics.lens.Lens.from_json", lambda *a, **k: pytest.fail("rendered the lens"))
            assert main(["lens", "phone_80deg", "--plot", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--plot" in err and ".pdf" in err and ".png" in err
        assert not (tmp_path / name).exists()
    out = tmp_path / "lens.pdf"
    assert main(["lens", "phone_80deg", "--plot", str(out)]) == 0
    assert out.read_bytes().startswith(b"%PDF")
