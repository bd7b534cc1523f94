from warpsense.cli import main
from warpsense.optics import Lens
from warpsense.optics.report import format_report, lens_report


def test_lens_report_numbers_agree_with_the_lens(capsys, monkeypatch):
    lens = Lens.from_json("phone_80deg")
    lens.spec.pupil_samples, lens.spec.psf_grid, lens.spec.psf_kernel_size, lens.spec.oversampling = 32, (2, 2), 9, 3
    report = lens_report(lens, max_size=31)
    outside = lens.energy_outside(reference_size=31).amax(dim=0)
    assert [[round(float(v), 5) for v in row] for row in outside] == report["energy_outside_kernel"]
    assert report["kernel_size_for"]["0.01"] >= report["kernel_size"]
    assert report["sampling_l1"] > 0
    file_terms = {j: [round(v, 5) for v in waves] for j, waves in lens.spec.zernike_waves.items()}
    assert {term["noll"]: term["waves"] for term in report["aberrations"]} == file_terms
    assert {term["noll"]: term["name"] for term in report["aberrations"]}.get(4) == "defocus"
    text = format_report(report)
    assert "energy outside the K x K kernel" in text and "defocus" in text and f"{report['sampling_l1']:.4f}" in text
    monkeypatch.setattr("warpsense.optics.report.lens_report", lambda lens: report)
    assert main(["lens", "phone_80deg", "--json"]) == 0
    assert '"kernel_size": 9' in capsys.readouterr().out


def test_lens_command_unknown_lens_is_a_one_line_error(capsys):
    assert main(["lens", "no_such_lens"]) == 2
    assert "warpsense lens: error: lens 'no_such_lens'" in capsys.readouterr().err


def test_the_shipped_lens_passes_its_own_report_and_the_report_says_what_its_budget_means():
    """phone_68deg's report said its pixel integration "misses the 0.01 tolerance" and showed 2-3% of the energy
    outside K = 15 beside optics.energy_eps = 0.001, with no advice. The pixel integration is exact (sinc on the
    band-limited PSF) once the samples reach the Nyquist rate, which the lens's 5 do; the L1 it printed is the pupil
    sampling's, now named as such; and the energy outside K comes with what energy_eps does and the K for 99%."""
    import pytest

    report = lens_report(Lens.from_json("phone_68deg"))
    text = format_report(report)
    spec = Lens.from_json("phone_68deg").spec
    assert report["nyquist_samples"] == pytest.approx(2 * spec.pixel_pitch_um / (0.465 * spec.f_number), rel=1e-3)
    assert report["pixel_integration_exact"] and "misses" not in text and "NOT exact" not in text
    assert "optics.energy_eps (default 0.001) crops inside the window" in text
    assert f"to keep 99%: psf_kernel_size {report['kernel_size_for']['0.01']} in the lens file" in text
    assert "pupil sampling: D = 64" in text and f"L1 {report['sampling_l1']:.4f}" in text


def test_a_lens_sampled_below_its_nyquist_rate_is_told_to_raise_its_oversampling():
    lens = Lens.from_json("phone_68deg")
    lens.spec.pupil_samples, lens.spec.psf_grid, lens.spec.psf_kernel_size, lens.spec.oversampling = 32, (1, 1), 9, 1
    text = format_report(lens_report(lens, max_size=15))
    assert "NOT exact: raise oversampling in the lens file" in text
