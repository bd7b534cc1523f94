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
    assert report["pixel_integration_l1"] > 0
    file_terms = {j: [round(v, 5) for v in waves] for j, waves in lens.spec.zernike_waves.items()}
    assert {term["noll"]: term["waves"] for term in report["aberrations"]} == file_terms
    assert {term["noll"]: term["name"] for term in report["aberrations"]}.get(4) == "defocus"
    text = format_report(report)
    assert "energy outside the K x K kernel" in text and "defocus" in text and f"{report['pixel_integration_l1']:.4f}" in text
    monkeypatch.setattr("warpsense.optics.report.lens_report", lambda lens: report)
    assert main(["lens", "phone_80deg", "--json"]) == 0
    assert '"kernel_size": 9' in capsys.readouterr().out


def test_lens_command_unknown_lens_is_a_one_line_error(capsys):
    assert main(["lens", "no_such_lens"]) == 2
    assert "warpsense lens: error: lens 'no_such_lens'" in capsys.readouterr().err
