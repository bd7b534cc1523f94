"""The photon budget, the aperture and the exposure time (issue 29): each physical relation against a known answer."""

import math

import pytest
import torch
from scipy import optimize, special

from warpsense.camera import Camera
from warpsense.camera.photons import PhotonBudget
from warpsense.config import ConfigError, load_config
from warpsense.optics.lens import Lens, parse_lens
from warpsense.optics.motion import compose, streak_psfs
from warpsense.system import check_config

PHOTONS = ["photons.enabled=true", "noise.enabled=false", "exposure.enabled=false", "cfa.mode=\"fixed\""]
OPTICS = ["optics.enabled=true", "optics.normalize_mean=0.0"]


def _camera(*overrides) -> Camera:
    return Camera.from_config(load_config(None, [*PHOTONS, *overrides])).eval()


def _noise_free(camera: Camera, radiance: torch.Tensor) -> torch.Tensor:
    with torch.no_grad(), camera.overridden(noise_scale=0.0):
        return camera(radiance)


def _interior(raw: torch.Tensor, margin: int = 12) -> torch.Tensor:
    return raw[..., margin:-margin, margin:-margin]


def _flat(level: float, size: int = 48) -> torch.Tensor:
    return torch.full((1, 3, size, size), level)


# --- photon budget ------------------------------------------------------------------------------------------------

def test_mid_grey_electrons_at_the_reference_and_clear_collects_three_times_green():
    quantize_off = "quantize.enabled=false"
    bayer = _camera(quantize_off, "cfa.pattern=\"RGGB\"", "photons.digital_gain=1.0")
    clear = _camera(quantize_off, "cfa.pattern=\"RCCB\"", "photons.digital_gain=1.0")
    yellow = _camera(quantize_off, "cfa.pattern=\"RYYB\"", "photons.digital_gain=1.0")
    white = _flat(1.0, 8)
    green, c, y = (_noise_free(camera, white)[0, 0, 0, 1] for camera in (bayer, clear, yellow))  # site (0, 1)
    assert float(c / green) == pytest.approx(3.0, rel=1e-6)
    assert float(y / green) == pytest.approx(2.0, rel=1e-6)
    # the light level's definition: a clear reference pixel on mid-grey at f/2, 10 ms collects 70 e- at night
    grey = _noise_free(clear, _flat(0.18, 8))[0, 0, 0, 1]
    assert float(grey) * 6000.0 == pytest.approx(70.0, rel=1e-5)  # ADC units * FWC / G = electrons
    pitch = _camera(quantize_off, "cfa.pattern=\"RCCB\"", "photons.digital_gain=1.0", "photons.pixel_pitch_um=6.0",
                    "photons.quantum_efficiency=0.3")
    assert float(_noise_free(pitch, _flat(0.18, 8))[0, 0, 0, 1]) * 6000 == pytest.approx(70.0 * 4 * 0.5, rel=1e-5)


def test_one_stop_smaller_aperture_halves_the_electrons_and_double_exposure_doubles_them():
    patch = torch.zeros(1, 3, 48, 48)
    patch[..., 20:28, 20:28] = 0.3  # away from the borders: every electron the lens spreads stays in the frame

    def electrons(*overrides):
        camera = _camera("quantize.enabled=false", "cfa.enabled=false", *OPTICS, *overrides)
        return float(_noise_free(camera, patch).double().sum())

    base = electrons("optics.f_number=2.0")
    assert electrons(f"optics.f_number={2.0 * math.sqrt(2)}") / base == pytest.approx(0.5, rel=1e-4)
    assert electrons("optics.f_number=2.0", "optics.exposure_ms=20.0") / base == pytest.approx(2.0, rel=1e-4)


def test_shot_limited_snr_grows_as_the_square_root_of_the_electrons():
    def snr(electrons):
        camera = _camera("quantize.enabled=false", "photons.read_electrons=0.0", "cfa.enabled=false",
                         f"photons.mid_grey_electrons={electrons}")
        raw = camera(_flat(0.18, 256))
        return float(raw.mean() / raw.std())

    # a mono pixel on mid-grey collects E_mid / 3 electrons: SNR = sqrt(E_mid / 3)
    assert snr(300.0) == pytest.approx(10.0, rel=0.02)
    assert snr(1200.0) / snr(300.0) == pytest.approx(2.0, rel=0.02)


@pytest.mark.parametrize("exact", [False, True])
def test_flat_field_statistics_match_the_stated_electrons_read_noise_and_gain(exact):
    gain, well, read = 4.0, 6000.0, 3.0
    camera = _camera("quantize.enabled=false", "cfa.enabled=false", "photons.mid_grey_electrons=150.0",
                     f"photons.analog_gain={gain}", f"photons.full_well_electrons={well}",
                     f"photons.read_electrons={read}", "photons.digital_gain=1.0")
    with torch.no_grad(), camera.overridden(exact_noise=exact):
        raw = camera(_flat(0.18, 256)).double()
    electrons = 150.0 / 3  # mono: the mean of the three bands
    in_electrons = raw * well / gain
    assert float(in_electrons.mean()) == pytest.approx(electrons, rel=0.01)
    assert float(in_electrons.var()) == pytest.approx(electrons + read**2, rel=0.03)


def test_full_well_and_gain_clip_at_the_top_code():
    unity = _camera("cfa.enabled=false", "photons.digital_gain=1.0", "photons.mid_grey_electrons=6000.0")
    # mid-grey gives 2000 e- (mono); 0.9 linear gives 10000 e- > 6000 e- full well: the top code
    assert float(_noise_free(unity, _flat(0.9, 8)).min()) == 1.0
    assert float(_noise_free(unity, _flat(0.18, 8)).max()) == pytest.approx(2000 / 6000, abs=1 / 1023)
    high = _camera("cfa.enabled=false", "photons.digital_gain=1.0", "photons.mid_grey_electrons=6000.0",
                   "photons.analog_gain=4.0")  # clips at 6000 / 4 = 1500 e-: mid-grey (2000 e-) clips
    assert float(_noise_free(high, _flat(0.18, 8)).min()) == 1.0


def test_digital_gain_maps_mid_grey_through_clear_to_one_half_and_is_recorded():
    camera = _camera("quantize.enabled=false", "cfa.pattern=\"RCCB\"", "photons.analog_gain=8.0")
    assert float(_noise_free(camera, _flat(0.18, 8))[0, 0, 0, 1]) == pytest.approx(0.5, rel=1e-5)
    assert "photons.digital_gain" in camera.state_dict()
    assert camera.learned().analog_gain == pytest.approx(8.0)
    assert camera.learned().digital_gain == pytest.approx(0.5 * 6000 / (70 * 8.0))  # what predict scales a capture by


# --- aperture -----------------------------------------------------------------------------------------------------

def _perfect_lens(pupil_samples: int = 128) -> Lens:
    spec = parse_lens({"name": "perfect", "focal_length_mm": 4.0, "f_number": 2.0, "diagonal_fov_deg": 60.0,
                       "pixel_pitch_um": 1.0, "wavelengths_um": [0.55, 0.55, 0.55], "psf_kernel_size": 31,
                       "psf_grid": [1, 1], "zernike_waves": {}, "pupil_samples": pupil_samples}, "test lens")
    return Lens(spec)


def _ee50_radius(psf: torch.Tensor, pitch: float) -> float:
    """Radius (um) holding half the energy of a centred PSF [K, K], interpolated on the sorted pixel radii."""
    size = psf.shape[-1]
    axis = (torch.arange(size, dtype=torch.float64) - size // 2) * pitch
    radius = torch.sqrt(axis[:, None] ** 2 + axis[None, :] ** 2).reshape(-1)
    order = torch.argsort(radius)
    energy = torch.cumsum(psf.reshape(-1)[order].double(), 0) / psf.sum()
    index = int(torch.searchsorted(energy, torch.tensor(0.5, dtype=torch.float64)))
    return float(radius[order][index])


def test_one_stop_smaller_aperture_widens_the_diffraction_core_by_sqrt2_as_airy_says():
    lens = _perfect_lens()
    pitch = 0.25
    zero = torch.zeros(1, dtype=torch.float64)

    def radius(f_number):
        with torch.no_grad():
            psf = lens.psf_at(zero, zero, sample_pitch_um=pitch, kernel_size=41, f_number=f_number,
                              grid_f_number=2.0)
        return _ee50_radius(psf[1, 0], pitch)

    # Airy: encircled energy 1 - J0(v)^2 - J1(v)^2 at v = pi r / (lambda N) is 1/2 at v = 1.6163
    v50 = optimize.brentq(lambda v: 1 - special.j0(v) ** 2 - special.j1(v) ** 2 - 0.5, 1.0, 2.5)
    airy = v50 * 0.55 * 2.0 / math.pi
    assert radius(2.0) == pytest.approx(airy, rel=0.08)
    assert radius(2.0 * math.sqrt(2)) / radius(2.0) == pytest.approx(math.sqrt(2), rel=0.06)


def test_stopping_down_scales_each_wavefront_term_by_its_radial_order():
    spec = parse_lens({"name": "defocus", "focal_length_mm": 4.0, "f_number": 2.0, "diagonal_fov_deg": 60.0,
                       "pixel_pitch_um": 1.0, "wavelengths_um": [0.55, 0.55, 0.55], "psf_kernel_size": 15,
                       "psf_grid": [1, 1], "zernike_waves": {"4": {"constant": 0.6}}, "pupil_samples": 64},
                      "test lens")
    zero = torch.zeros(1, dtype=torch.float64)
    lens = Lens(spec)
    # Noll 4 (defocus) has radial order 2: at F# 2 sqrt 2 the pupil radius is 1 / sqrt 2 and 0.6 waves become 0.3;
    # rendered on the same grid, that equals a lens file stating 0.3 waves at that F#
    stopped = lens.psf_at(zero, zero, f_number=2.0 * math.sqrt(2), grid_f_number=2.0)
    spec_half = parse_lens({**{k: getattr(spec, k) for k in ("name", "focal_length_mm", "diagonal_fov_deg",
                                                              "pixel_pitch_um", "psf_kernel_size")},
                            "f_number": 2.0 * math.sqrt(2), "wavelengths_um": [0.55, 0.55, 0.55],
                            "psf_grid": [1, 1], "zernike_waves": {"4": {"constant": 0.3}}, "pupil_samples": 64},
                           "test lens")
    direct = Lens(spec_half).psf_at(zero, zero, f_number=2.0 * math.sqrt(2), grid_f_number=2.0)
    torch.testing.assert_close(stopped, direct, atol=1e-9, rtol=0)


def test_f_number_gradcheck_float64():
    lens = _perfect_lens(pupil_samples=16)
    zero = torch.zeros(1, dtype=torch.float64)
    weights = torch.rand(3, 1, 5, 5, dtype=torch.float64)

    def psf(f_number):
        return (lens.psf_at(zero, zero, kernel_size=5, oversampling=3, f_number=f_number, grid_f_number=1.8)
                * weights).sum()

    assert torch.autograd.gradcheck(psf, (torch.tensor(2.3, dtype=torch.float64, requires_grad=True),))


# --- exposure time and motion blur --------------------------------------------------------------------------------

def _radial_variance(psf: torch.Tensor, azimuth: float) -> float:
    size = psf.shape[-1]
    axis = torch.arange(size, dtype=torch.float64) - size // 2
    along = axis[None, :] * math.cos(azimuth) + axis[:, None] * math.sin(azimuth)
    weights = psf.double() / psf.sum()
    mean = (weights * along).sum()
    return float((weights * (along - mean) ** 2).sum())


def test_streak_has_the_stated_length_and_gradcheck():
    for length in (3.0, 6.0):
        streak = streak_psfs(torch.tensor([length], dtype=torch.float64), torch.tensor([0.6]), 11, samples=400)[0]
        assert float(streak.sum()) == pytest.approx(1.0)
        # a uniform segment of length L has variance L^2 / 12; the bilinear spread adds 1/6 pixel^2 on average
        measured = _radial_variance(streak, 0.6)
        assert math.sqrt(12 * max(measured - 1 / 6, 0)) == pytest.approx(length, rel=0.03)
    lengths = torch.tensor([2.3, 4.1], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda length: streak_psfs(length, torch.tensor([0.3, 2.0]), 9, samples=64),
                                    (lengths,))


def test_doubling_the_exposure_doubles_the_corner_blur_length_on_the_psf_grid():
    def corner(exposure_ms, speed):
        camera = _camera(*OPTICS, f"optics.exposure_ms={exposure_ms}", f"optics.corner_speed_px_per_ms={speed}",
                         "optics.energy_eps=0.0")
        optics = camera.optics
        psf = optics.psf()  # [3, Gy, Gx, K, K]: the corner node is [.., -1, -1]
        _, azimuth = optics.lens.field_points()
        return psf[1, -1, -1], float(azimuth[-1])

    lens_only, azimuth = corner(10.0, 0.0)
    base = _radial_variance(lens_only, azimuth)
    lengths = []
    for exposure in (10.0, 20.0):
        psf, _ = corner(exposure, 0.3)
        streak_variance = _radial_variance(psf, azimuth) - base  # variances add under convolution
        lengths.append(math.sqrt(12 * (streak_variance - 1 / 6)))
    assert lengths[0] == pytest.approx(0.3 * 10.0, rel=0.05)  # h = 1 at the corner: 3 pixels in 10 ms
    assert lengths[1] / lengths[0] == pytest.approx(2.0, rel=0.05)


def test_compose_equals_a_direct_convolution():
    psf = torch.rand(3, 2, 1, 5, 5, dtype=torch.float64)
    blur = torch.rand(2, 1, 3, 3, dtype=torch.float64)
    out = compose(psf, blur)
    assert out.shape == (3, 2, 1, 7, 7)
    expected = torch.zeros(7, 7, dtype=torch.float64)
    for y in range(5):
        for x in range(5):
            expected[y : y + 3, x : x + 3] += psf[2, 1, 0, y, x] * blur[1, 0]
    torch.testing.assert_close(out[2, 1, 0], expected)


# --- learning -----------------------------------------------------------------------------------------------------

def test_gradients_reach_f_number_exposure_time_gain_and_cfa():
    camera = Camera.from_config(load_config(None, [
        "photons.enabled=true", "noise.enabled=false", "exposure.enabled=false", *OPTICS, "cfa.mode=\"gumbel\"",
        "cfa.init_logit=0.0", "cfa.candidates=\"RGBCY\"", "optics.f_number_learnable=true", "optics.f_number=2.8",
        "optics.exposure_learnable=true", "optics.corner_speed_px_per_ms=0.2", "photons.gain_learnable=true",
        "photons.analog_gain=4.0"])).train()
    camera.optics.lens.spec.pupil_samples = 16
    camera(torch.rand(2, 3, 24, 24)).square().mean().backward()
    for name in ("optics.f_number_logit", "optics.exposure_logit", "photons.gain_logit", "cfa.logits"):
        grad = dict(camera.named_parameters())[name].grad
        assert grad is not None and float(grad.abs().sum()) > 0, name
    learned = camera.learned()
    assert learned.f_number == pytest.approx(2.8, rel=1e-5) and learned.exposure_ms == pytest.approx(10.0, rel=1e-5)
    assert learned.analog_gain == pytest.approx(4.0, rel=1e-5)


def test_photon_stage_gradcheck_float64():
    stage = PhotonBudget(mid_grey_electrons=70.0, analog_gain=3.0, gain_learnable=True, read_electrons=2.0)
    stage = stage.double().eval()
    exposure = torch.rand(1, 1, 4, 4, dtype=torch.float64, requires_grad=True)
    logit = stage.gain_logit.detach().clone().requires_grad_(True)
    # eval noise is keyed by a fixed seed: the sample is a smooth function of the exposure and the gain
    assert torch.autograd.gradcheck(
        lambda e, g: torch.func.functional_call(stage, {"gain_logit": g}, (e,)), (exposure, logit))


@pytest.mark.parametrize("overrides, message", [
    (["photons.enabled=true"], "noise.enabled = false"),
    (["photons.enabled=true", "noise.enabled=false"], "exposure.enabled = false"),
    (["photons.enabled=true", "noise.enabled=false", "exposure.enabled=false", "optics.enabled=true"],
     "normalize_mean = 0"),
    (["optics.f_number_learnable=true", "optics.normalize_mean=0.0", "optics.f_number=9.0"],
     r"optics.f_number = 9.0 must lie within \[optics.f_number_min, optics.f_number_max\]"),
    (["optics.exposure_learnable=true"], "normalize_mean = 0"),
    (["photons.gain_learnable=true", "photons.analog_gain=100.0"],
     r"photons.analog_gain = 100.0 must lie within \[1, photons.gain_max\]"),
    (["cfa.candidates=\"RGQ\""], "unknown filter letter 'Q'"),
    (["cfa.pattern=\"RYYB\""], "'Y', which is not a candidate"),
])
def test_inconsistent_designs_are_one_line_config_errors(overrides, message):
    with pytest.raises(ConfigError, match=message):
        check_config(load_config(None, overrides))
