import json
import math

import pytest
import torch

from warpsense.optics import Lens, LensFileError, collapse_grid, crop_to_energy, noll_to_nm, pupil_psf, zernike

FINE_PUPIL, FINE_PADDING = 128, 16  # image-plane samples lambda N / 16 apart: fine sampling for the physics


def test_noll_table():
    expected = [(0, 0), (1, 1), (1, -1), (2, 0), (2, -2), (2, 2), (3, -1), (3, 1), (3, -3), (3, 3), (4, 0), (4, 2),
                (4, -2), (4, 4), (4, -4)]
    assert [noll_to_nm(j) for j in range(1, 16)] == expected


def test_zernike_unit_rms_and_orthogonal():
    samples = 400
    axis = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples * 2 - 1
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    rho, theta = torch.sqrt(x**2 + y**2), torch.atan2(y, x)
    inside = rho <= 1
    values = torch.stack([zernike(j, rho, theta)[inside] for j in range(1, 16)])
    gram = values @ values.T / inside.sum()
    torch.testing.assert_close(gram, torch.eye(15, dtype=torch.float64), atol=0.02, rtol=0)


def _fine_psf(coefficients, noll, padding=FINE_PADDING):
    coefficients = torch.tensor([coefficients], dtype=torch.float64)
    return pupil_psf(coefficients, noll, torch.zeros(1, dtype=torch.float64), FINE_PUPIL, padding)[0]


def test_airy_first_dark_ring_at_1_22_lambda_n():
    psf = _fine_psf([0.0], [4])
    size = psf.shape[-1]
    centre = size // 2
    spacing = FINE_PUPIL / size  # image-plane sample spacing in units of lambda * N
    profile = psf[centre, centre : centre + int(1.6 * FINE_PADDING)]  # out to 1.6 lambda N: the first ring only
    i = int(profile[1:].argmin()) + 1
    a, b, c = profile[i - 1 : i + 2].tolist()
    minimum = (i + 0.5 * (a - c) / (a - 2 * b + c)) * spacing
    assert minimum == pytest.approx(1.22, rel=0.01)


@pytest.mark.parametrize("noll", [4, 6, 11])
@pytest.mark.parametrize("rms", [0.02, 0.05, 0.07])
def test_strehl_matches_marechal(noll, rms):
    perfect = _fine_psf([0.0], [noll], padding=4).max()  # the peak needs no fine sampling
    strehl = (_fine_psf([rms], [noll], padding=4).max() / perfect).item()
    assert strehl == pytest.approx(math.exp(-((2 * math.pi * rms) ** 2)), rel=0.01)


def _is_radially_symmetric(psf, tolerance):
    centre, radius = psf.shape[-1] // 2, 12
    psf = psf[centre - radius : centre + radius + 1, centre - radius : centre + radius + 1]  # odd, centred
    return (psf - psf.flip(-1)).abs().max() < tolerance and (psf - psf.transpose(-1, -2)).abs().max() < tolerance


def test_defocus_radially_symmetric_coma_not():
    defocus = _fine_psf([0.3], [4], padding=4)
    coma = _fine_psf([0.3], [8], padding=4)
    scale = defocus.max()
    assert _is_radially_symmetric(defocus, 1e-3 * scale)
    assert not _is_radially_symmetric(coma, 1e-2 * coma.max())


@pytest.mark.parametrize("name", ["phone_68deg", "phone_80deg"])
def test_packaged_lenses_energy_and_shape(name):
    lens = Lens.from_json(name)
    grid = lens.psf_grid()
    spec = lens.spec
    assert grid.shape == (3, *spec.psf_grid, spec.psf_kernel_size, spec.psf_kernel_size)
    torch.testing.assert_close(grid.sum(dim=(-2, -1)), torch.ones(grid.shape[:3], dtype=torch.float64))
    assert (grid >= 0).all()
    # the corner blurs more than the centre (field-dependent aberrations), and the PSF grid is not invariant
    centre, corner = grid[1, spec.psf_grid[0] // 2, spec.psf_grid[1] // 2], grid[1, 0, 0]
    assert corner.max() < 0.8 * centre.max()
    assert 2000 < spec.sensor_diagonal_mm * 1000 / spec.pixel_pitch_um < 8000  # a phone sensor's diagonal in pixels


def test_pixel_pitch_sampling_energy_in_kernel():
    lens = Lens.from_json("phone_68deg")
    psf = lens.psf_at(torch.zeros(1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64))
    # the central pixel of a 1.4 um pitch sensor collects most of an f/1.9 diffraction-limited core
    assert psf[1, 0].argmax() == (psf.shape[-1] ** 2) // 2
    assert 0.4 < psf[1, 0].max() < 0.95


def test_psf_gradient_wrt_zernike_gradcheck():
    lens = Lens.from_json("phone_68deg", learnable=True)
    lens.spec.pupil_samples = 16
    height = torch.tensor([0.0, 0.8], dtype=torch.float64)
    azimuth = torch.tensor([0.0, 0.7], dtype=torch.float64)
    offset = (torch.rand_like(lens.offset) * 0.4 - 0.2).requires_grad_()

    def render(parameters):
        options = {"kernel_size": 3, "oversampling": 3}
        return torch.func.functional_call(lens, {"offset": parameters}, (height, azimuth), options)

    assert torch.autograd.gradcheck(render, (offset,), atol=1e-6)


def test_learnable_coefficients_bounded():
    lens = Lens.from_json("phone_68deg", learnable=True)
    with torch.no_grad():
        lens.offset.fill_(100.0)
    delta = lens.coefficients() - lens.base_coefficients
    assert torch.allclose(delta, torch.full_like(delta, lens.spec.learnable_bound_waves))


def test_crop_to_energy_and_collapse():
    grid = Lens.from_json("phone_68deg").psf_grid()
    cropped = crop_to_energy(grid, 0.05)
    assert cropped.shape[-1] < grid.shape[-1] and cropped.shape[-1] % 2 == 1
    torch.testing.assert_close(cropped.sum(dim=(-2, -1)), torch.ones(cropped.shape[:3], dtype=torch.float64))
    assert crop_to_energy(grid, 0.0).shape == grid.shape
    assert collapse_grid(grid, 1e-3).shape == grid.shape  # field-varying lens keeps its grid
    invariant = grid[:, 2:3, 2:3].expand(-1, 5, 5, -1, -1) + 1e-6 * torch.rand_like(grid)
    assert collapse_grid(invariant, 1e-3).shape[1:3] == (1, 1)


LENS = {
    "name": "t", "focal_length_mm": 4.0, "f_number": 2.0, "diagonal_fov_deg": 70, "pixel_pitch_um": 1.4,
    "wavelengths_um": [0.6, 0.55, 0.45], "psf_kernel_size": 7, "psf_grid": [2, 2],
    "zernike_waves": {"4": {"constant": 0.1}},
}


@pytest.mark.parametrize("change,message", [
    ({"focal_length_mm": None}, "missing required key 'focal_length_mm'"),
    ({"bogus": 1}, "unknown key 'bogus'"),
    ({"f_number": "fast"}, "f_number: expected float"),
    ({"psf_kernel_size": 8}, "psf_kernel_size must be an odd int"),
    ({"psf_grid": [2]}, "psf_grid must be"),
    ({"wavelengths_um": [0.5]}, "wavelengths_um must be 3"),
    ({"zernike_waves": {"4": {"cubic": 1.0}}}, "zernike_waves.4"),
    ({"zernike_waves": {"x": {"constant": 1.0}}}, "Noll indices"),
    ({"reference_wavelength_um": 550}, "reference_wavelength_um must be a wavelength in um"),
    ({"psf_kernel_size": 1001}, "psf_kernel_size must be an odd int in 1..101"),
    ({"psf_grid": [1000, 1000]}, "psf_grid must be"),
    ({"pupil_samples": 100000}, "pupil_samples must be in 8..512"),
    ({"oversampling": 99}, "oversampling must be an odd int in 1..31"),
    ({"zernike_waves": {"4": {"constant": 1e300}}}, "coefficients must be finite"),
    ({"lateral_color": [0.001, 0.0]}, "lateral_color must be 3 numbers"),
    ({"axial_color_waves": [0.1, "x", 0.0]}, "axial_color_waves must be 3 numbers"),
])
def test_malformed_lens_file_errors_name_file_and_key(tmp_path, change, message):
    data = dict(LENS)
    for key, value in change.items():
        if value is None:
            data.pop(key)
        else:
            data[key] = value
    path = tmp_path / "bad_lens.json"
    path.write_text(json.dumps(data))
    with pytest.raises(LensFileError, match=message) as error:
        Lens.from_json(path)
    assert "bad_lens.json" in str(error.value)


@pytest.mark.parametrize("content", [b"\xff\xfe{", b"[" * 100000 + b"]" * 100000,
                                     b'{"f_number": ' + b"9" * 5000 + b"}"])
def test_unreadable_lens_json_is_one_line(tmp_path, content):
    path = tmp_path / "odd.json"
    path.write_bytes(content)
    with pytest.raises(LensFileError, match="odd.json: (not UTF-8|invalid JSON)") as error:
        Lens.from_json(path)
    assert "\n" not in str(error.value)


def test_invalid_json_and_unknown_name(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text("{not json")
    with pytest.raises(LensFileError, match="broken.json: invalid JSON"):
        Lens.from_json(path)
    with pytest.raises(LensFileError, match="packaged: phone_68deg, phone_80deg"):
        Lens.from_json("no_such_lens")


def _small(name="phone_80deg", **spec):
    lens = Lens.from_json(name)
    lens.spec.pupil_samples = 32  # coarse pupil: these tests compare the lens with itself
    for key, value in spec.items():
        setattr(lens.spec, key, value)
    return lens


def test_coefficients_are_an_optical_path_shared_by_wavelengths():
    """Waves at the reference wavelength scale by lambda_ref / lambda; axial colour adds defocus per channel."""
    lens = _small(axial_color_waves=(0.1, 0.0, -0.2))
    height = torch.tensor([0.0, 1.0], dtype=torch.float64)
    reference = lens.field_coefficients(height)
    defocus = lens.noll.index(4)
    for channel, wavelength in enumerate(lens.spec.wavelengths_um):
        waves, noll = lens.wavelength_coefficients(reference, height, channel)
        scale = 0.55 / wavelength
        assert noll == lens.noll
        expected = reference * scale
        expected[:, defocus] += lens.spec.axial_color_waves[channel] * scale
        torch.testing.assert_close(waves, expected)
    # the same lens stated at the blue wavelength (coefficients in blue waves) renders the same PSFs
    azimuth = torch.zeros(2, dtype=torch.float64)
    restated = _small(reference_wavelength_um=0.465, axial_color_waves=tuple(a * 0.55 / 0.465 for a in
                                                                            lens.spec.axial_color_waves))
    with torch.no_grad():
        restated.base_coefficients.mul_(0.55 / 0.465)
    torch.testing.assert_close(restated.psf_at(height, azimuth), lens.psf_at(height, azimuth))
    assert not torch.allclose(lens.psf_at(height, azimuth)[:, 1], _small().psf_at(height, azimuth)[:, 1])


def test_lateral_color_moves_the_psf_radially_by_the_magnification_difference():
    lens = Lens.from_json("phone_68deg")
    lens.spec.lateral_color = (0.001, 0.0, -0.001)
    lens.base_coefficients.zero_()  # diffraction-limited: only the tilt moves the centroid
    height = torch.tensor([0.0, 0.6], dtype=torch.float64)
    psf = lens.psf_at(height, torch.zeros(2, dtype=torch.float64), kernel_size=31)
    offsets = torch.arange(31, dtype=torch.float64) - 15
    centroid_x = (psf.sum(dim=-2) * offsets).sum(-1)  # [3, 2], pixels; azimuth 0 is the +x direction
    expected = 0.001 * lens.spec.sensor_diagonal_mm * 500 * 0.6 / lens.spec.pixel_pitch_um  # ~1.2 px
    assert centroid_x[:, 0].abs().max() < 1e-9  # on axis nothing moves
    assert centroid_x[1, 1].abs() < 1e-9
    assert centroid_x[0, 1].item() == pytest.approx(expected, rel=0.1)
    assert centroid_x[2, 1].item() == pytest.approx(-expected, rel=0.1)


def test_energy_outside_kernel_accounts_for_the_cropped_tail():
    lens = _small()
    outside = lens.energy_outside(grid=(3, 3), reference_size=31)
    wide = lens.psf_grid((3, 3), kernel_size=31)
    kernel = lens.psf_grid((3, 3))
    window = wide[..., 8:23, 8:23]
    # the K x K kernel is the wide rendering's centre window, renormalised: the tail moved into the core
    torch.testing.assert_close(kernel, window / window.sum(dim=(-2, -1), keepdim=True))
    torch.testing.assert_close(outside, 1 - window.sum(dim=(-2, -1)))
    assert outside[:, 0, 0].min() > 2 * outside[:, 1, 1].max()  # the 80 deg corner spills far more than the centre
    size = lens.kernel_size_for(0.05, grid=(3, 3), max_size=31)
    assert size > 15 and size % 2 == 1
    assert (lens.energy_outside(size, (3, 3), 31) <= 0.05).all()
    assert not (lens.energy_outside(size - 2, (3, 3), 31) <= 0.05).all()


@pytest.mark.parametrize("name", ["phone_68deg", "phone_80deg"])
def test_pixel_integration_is_exact_against_a_brute_force_midpoint_rule(name, monkeypatch):
    """Pixels are integrated by the box filter in the frequency domain: at the lens's 5 samples per pixel it agrees
    with a 31 x 31 midpoint rule (an independent, nearly converged reference) to well under the 1% L1 tolerance,
    where the 5 x 5 midpoint rule it replaced was 1-2% off (issue 12, item 4)."""
    from warpsense.optics import lens as lens_module

    def midpoint(fine, size, factor):  # the block sum of factor x factor samples per pixel
        start = fine.shape[-1] // 2 - size * factor // 2
        window = fine[:, start : start + size * factor, start : start + size * factor]
        return window.reshape(-1, size, factor, size, factor).sum(dim=(2, 4))

    # the same pupil sampling for every oversampling (no rounding to 5-smooth FFT sizes, which samples the pupil
    # slightly differently per size): the comparison isolates the pixel integration
    monkeypatch.setattr(lens_module, "fast_fft_size", lambda n: n)
    lens = Lens.from_json(name)  # the on-axis node: the sharpest PSF, where the midpoint rule was worst
    lens.spec.psf_kernel_size = 9
    exact = lens.psf_grid((1, 1))
    assert lens.pixel_integration_error(lens.spec.oversampling, grid=(1, 1)) < 0.005
    def midpoint_render(coefficients, noll, azimuth, pupil_samples, zero_padding, size, factor, radius=None):
        fine = lens_module.pupil_psf(coefficients, noll, azimuth, pupil_samples, zero_padding, radius)
        return midpoint(fine, size, factor)

    monkeypatch.setattr(lens_module, "render_pixels", midpoint_render)
    brute_force = lens.psf_grid((1, 1), oversampling=31)
    old_rule = lens.psf_grid((1, 1), oversampling=5)
    assert (exact - brute_force).abs().sum(dim=(-2, -1)).max() < 0.004
    assert (old_rule - brute_force).abs().sum(dim=(-2, -1)).max() > 0.008


def test_corner_pixel_psf_matches_a_direct_rendering_at_its_field_point():
    """Issue 12 item 1: the grid's bilinear PSF at the image's corner pixel equals the lens rendered at that pixel's
    own field height (~1.0); a grid clamped at its outer node centres would give the 0.8-field PSF there."""
    from warpsense.ops.reference import bilinear_node_weights

    lens = _small()
    height, width = 600, 800
    grid = lens.psf_grid((5, 5))
    weights = bilinear_node_weights(height, width, 5, 5, torch.float64, "cpu")[:, :, 0, 0]
    interpolated = (grid * weights[None, :, :, None, None]).sum(dim=(1, 2))
    half_w, half_h = lens.spec.aspect_ratio / 2, 0.5
    x, y = (0.5 / width - 0.5) * 2 * half_w, (0.5 / height - 0.5) * 2 * half_h
    field = torch.tensor([math.hypot(x, y) / math.hypot(half_w, half_h)], dtype=torch.float64)
    direct = lens.psf_at(field, torch.tensor([math.atan2(y, x)], dtype=torch.float64))[:, 0]
    inner = lens.psf_at(field * 0.8, torch.tensor([math.atan2(y, x)], dtype=torch.float64))[:, 0]
    assert field.item() > 0.99
    assert (interpolated - direct).abs().sum(dim=(-2, -1)).max() < 0.02
    assert (inner - direct).abs().sum(dim=(-2, -1)).min() > 0.1


def test_kernel_size_chosen_from_max_energy_outside(tmp_path):
    data = dict(LENS, max_energy_outside=0.02, pupil_samples=32)
    path = tmp_path / "auto_k.json"
    path.write_text(json.dumps(data))
    lens = Lens.from_json(path)
    size = lens.spec.psf_kernel_size
    assert size % 2 == 1 and size != LENS["psf_kernel_size"]
    assert (lens.energy_outside(size, reference_size=63) <= 0.02).all()
    assert not (lens.energy_outside(size - 2, reference_size=63) <= 0.02).all()
    assert lens.psf_grid().shape[-1] == size
    path.write_text(json.dumps(dict(LENS, max_energy_outside=0.9)))
    with pytest.raises(LensFileError, match="max_energy_outside must be in"):
        Lens.from_json(path)


def test_a_kernel_wider_than_the_pupil_window_keeps_the_psf_scale():
    """The FFT's image plane spans D lambda F#, about 77 pixels at D = 64 for phone_80deg: a K = 101 rendering must
    raise D (not the zero padding, which magnified the PSF by 30%), so its centre matches the K = 15 kernel up to the
    pupil discretisation (D = 64 against D = 128 differ by 0.007 in L1)."""
    lens = Lens.from_json("phone_80deg")
    narrow = lens.psf_grid((3, 3))
    wide = lens.psf_grid((3, 3), kernel_size=101)[..., 43:58, 43:58]
    wide = wide / wide.sum(dim=(-2, -1), keepdim=True)
    assert (narrow - wide).abs().sum(dim=(-2, -1)).max() < 0.02


def test_lens_prints_what_it_is():
    from warpsense.optics import Lens

    text = repr(Lens.from_json("phone_68deg"))
    assert text == ("Lens('phone_68deg', f=4.2 mm, f/1.9, 68 deg, pitch 1.4 um, K=15, grid=5x5, learnable=False)")


def test_psf_grid_refuses_an_even_kernel_or_an_empty_grid():
    """An even K rendered each PSF half a pixel off its kernel's centre (centroid 7.995 in a 16-pixel kernel), which
    psf_conv then refused; a 0 x 3 grid failed inside the FFT library. Both are one line naming the argument, as the
    lens file's psf_kernel_size and psf_grid are."""
    lens = Lens.from_json("phone_68deg")
    with pytest.raises(ValueError, match=r"^Lens.psf_at: kernel_size must be an odd int >= 1 .*got 16$"):
        lens.psf_grid((1, 1), kernel_size=16)
    with pytest.raises(ValueError, match=r"^Lens.psf_grid: grid must be \(Gy, Gx\) with ints >= 1, got \(0, 3\)$"):
        lens.psf_grid((0, 3))
    psf = lens.psf_grid((1, 1), kernel_size=15)[1, 0, 0]
    rows = torch.arange(15, dtype=psf.dtype)
    assert float((psf.sum(1) * rows).sum()) == pytest.approx(7.0)  # on-axis PSF centred on the middle pixel


def test_fast_fft_size_is_the_next_5_smooth_number():
    from warpsense.optics.lens import fast_fft_size

    def smooth(n):
        for prime in (2, 3, 5):
            while n % prime == 0:
                n //= prime
        return n == 1

    for n in range(1, 400):
        size = fast_fft_size(n)
        assert size >= n and smooth(size)
        assert not any(smooth(m) for m in range(n, size))
    assert (fast_fft_size(239), fast_fft_size(265), fast_fft_size(202)) == (240, 270, 216)


def test_feature_float32_rendering_matches_float64():
    """The float32 pupil FFTs (the training default) stay within 1e-5 of the energy (L1) of float64 rendering,
    two orders below the 1e-3 K-window tolerance, stopped down too, and give float32 PSFs."""
    lens = Lens.from_json("phone_68deg")
    lens.spec.psf_kernel_size = 9
    for options in ({}, {"f_number": torch.tensor(3.0, dtype=torch.float64), "grid_f_number": 1.4}):
        single = lens.psf_grid((2, 2), dtype=torch.float32, **options)
        double = lens.psf_grid((2, 2), dtype=torch.float64, **options)
        assert single.dtype == torch.float32 and double.dtype == torch.float64
        assert (single.double() - double).abs().sum(dim=(-2, -1)).max() < 1e-5


def test_feature_smooth_fft_size_keeps_the_psf_scale():
    """Rounding the FFT up to a 5-smooth size samples the pupil more finely but keeps the image-plane spacing: the
    PSF's second moment (its size in pixels) matches the unrounded rendering to 2% (the pupil's sampling differs).
    Spacing scaled with the FFT size instead would move it by (270/265)^2 - 1 = 3.8% and (216/202)^2 - 1 = 14% in
    the red and blue channels."""
    from warpsense.optics import lens as lens_module

    lens = Lens.from_json("phone_68deg")
    lens.spec.psf_kernel_size = 15
    rounded = lens.psf_grid((1, 1))[:, 0, 0]
    original = lens_module.fast_fft_size
    try:
        lens_module.fast_fft_size = lambda n: n
        unrounded = lens.psf_grid((1, 1))[:, 0, 0]
    finally:
        lens_module.fast_fft_size = original
    axis = torch.arange(15, dtype=torch.float64) - 7
    radius2 = axis[:, None] ** 2 + axis[None, :] ** 2
    for channel in range(3):
        moment = (rounded[channel] * radius2).sum()
        torch.testing.assert_close(moment, (unrounded[channel] * radius2).sum(), rtol=2e-2, atol=0)


def _reference_pixels(coefficients, noll, azimuth, pupil_samples, padding, size, factor, radius=None):
    """The straightforward rendering `render_pixels` must equal: each node's full M x M pupil, centred FFT, the box
    filter by FFT (`pupil_psf` + `integrate_pixels`), normalised."""
    from warpsense.optics import integrate_pixels

    pixels = integrate_pixels(pupil_psf(coefficients, noll, azimuth, pupil_samples, padding, radius), size, factor)
    return pixels / pixels.sum(dim=(-2, -1), keepdim=True)


# Noll sets: a cosine/sine pair (5, 6), cosines or sines without their partner (8; 3, 7), m = 0 terms, none at all;
# geometries: the lens's (D 64.3, Q 3.7, K 15, 5 per pixel), a pupil that nearly fills the grid (Q 1.2: the support
# is clipped to it), odd and even M, a stopped-down pupil (radius float or tensor)
RENDER_CASES = [([4, 6, 8, 11], 64.3, 3.7, 15, 5, None), ([2, 3, 5, 6, 7], 20.0, 2.5, 5, 3, 0.7),
                ([1, 9, 12, 14], 16.0, 1.2, 3, 3, None), ([4], 30.0, 3.0, 7, 4, "tensor"), ([], 21.0, 2.0, 5, 3, None)]


@pytest.mark.parametrize("noll, pupil, padding, size, factor, radius", RENDER_CASES)
def test_render_pixels_equals_the_full_grid_rendering(noll, pupil, padding, size, factor, radius):
    from warpsense.optics.lens import render_pixels

    generator = torch.Generator().manual_seed(len(noll))
    coefficients = 0.3 * torch.randn(4, len(noll), generator=generator, dtype=torch.float64)
    azimuth = torch.tensor([0.0, 0.7, -2.1, 3.0], dtype=torch.float64)
    radius = torch.tensor(0.85, dtype=torch.float64) if radius == "tensor" else radius
    pixels = render_pixels(coefficients, noll, azimuth, pupil, padding, size, factor, radius)
    assert pixels.shape == (4, size, size)
    expected = _reference_pixels(coefficients, noll, azimuth, pupil, padding, size, factor, radius)
    torch.testing.assert_close(pixels / pixels.sum(dim=(-2, -1), keepdim=True), expected, atol=1e-13, rtol=0)


def test_render_pixels_gradients_equal_the_full_grid_rendering_and_gradcheck():
    """Gradients to the coefficients, the azimuths and a learnable pupil radius (an f-number) equal the reference's;
    float64 gradcheck of the fast path."""
    from warpsense.optics.lens import render_pixels

    noll = [2, 4, 7, 8]
    generator = torch.Generator().manual_seed(3)
    coefficients = (0.2 * torch.randn(2, 4, generator=generator, dtype=torch.float64)).requires_grad_()
    azimuth = torch.tensor([0.3, -1.2], dtype=torch.float64, requires_grad=True)
    radius = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(2, 5, 5, generator=generator, dtype=torch.float64)

    def fast(c, a, r):
        pixels = render_pixels(c, noll, a, 12.0, 2.5, 5, 3, r)
        return pixels / pixels.sum(dim=(-2, -1), keepdim=True)

    inputs = (coefficients, azimuth, radius)
    got = torch.autograd.grad((fast(*inputs) * weights).sum(), inputs)
    want = torch.autograd.grad((_reference_pixels(coefficients, noll, azimuth, 12.0, 2.5, 5, 3, radius) * weights)
                               .sum(), inputs)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, atol=1e-12, rtol=1e-10)
    assert torch.autograd.gradcheck(fast, inputs)


def test_render_pixels_geometry_kept_from_inference_mode_serves_training():
    """The aperture, basis and box matrix are kept between calls; made first under inference mode (an evaluation
    before training), they must still serve a rendering that takes gradients."""
    from warpsense.optics.lens import render_pixels

    coefficients = torch.tensor([[0.1, -0.2]], dtype=torch.float64)
    azimuth = torch.zeros(1, dtype=torch.float64)
    with torch.inference_mode():
        evaluated = render_pixels(coefficients, [5, 11], azimuth, 13.7, 2.9, 5, 3)
    trained = coefficients.clone().requires_grad_()
    pixels = render_pixels(trained, [5, 11], azimuth, 13.7, 2.9, 5, 3)
    pixels.sum().backward()
    assert trained.grad is not None and torch.isfinite(trained.grad).all()
    torch.testing.assert_close(pixels.detach(), evaluated.clone())


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_render_pixels_captured_in_a_cuda_graph_first_matches_eager():
    """A geometry first met while a CUDA graph is being captured is computed inside the graph, not kept (its
    kernels are only recorded then): the replay equals the eager rendering, and a later eager call is right too."""
    from warpsense.optics.lens import _cached_pupil_basis, render_pixels

    device = torch.device("cuda")
    coefficients = torch.tensor([[0.1, -0.2, 0.05]], device=device)
    azimuth = torch.tensor([0.4], device=device)
    arguments = ([4, 7, 8], azimuth, 17.3, 2.7, 5, 3)  # a pupil geometry no other test renders
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    # as before any capture, an eager warm-up on the capturing stream: cuBLAS's handle and the M = 47 FFT plan
    # cannot be created inside a capture (round 22: CUBLAS_STATUS_NOT_INITIALIZED in a fresh process). Another
    # pupil sampling with the same M keeps the pupil basis unseen (the box matrix depends on M only: kept)
    with torch.cuda.stream(stream):
        render_pixels(coefficients, [4, 7, 8], azimuth, 17.4, 2.7, 5, 3)
    kept = _cached_pupil_basis.cache_info().currsize
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.stream(stream), torch.cuda.graph(graph, stream=stream):
        captured = render_pixels(coefficients, *arguments)
    assert _cached_pupil_basis.cache_info().currsize == kept  # computed inside the graph, not kept
    graph.replay()
    torch.cuda.synchronize()
    eager = render_pixels(coefficients, *arguments)
    assert _cached_pupil_basis.cache_info().currsize == kept + 1
    expected = _reference_pixels(coefficients.double(), arguments[0], azimuth.double(), *arguments[2:])
    torch.testing.assert_close((captured / captured.sum(dim=(-2, -1), keepdim=True)).double(), expected,
                               atol=1e-5, rtol=0)
    torch.testing.assert_close(eager, captured)
