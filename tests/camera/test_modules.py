import pytest
import torch

from warpsense.camera import CFA, Camera, Exposure, Optics, Quantizer, SensorNoise
from warpsense.camera.isp import FixedISP
from warpsense.config import ConfigError, load_config
from warpsense.ops import cfa_mosaic, exposure, poisson_gaussian, psf_conv, quantize_ste
from warpsense.optics import Lens


def test_exposure_module_equals_functional_and_bounds():
    module = Exposure(0.3)
    image = torch.rand(2, 3, 4, 5)
    torch.testing.assert_close(module(image), exposure(image, module.gain_logit))
    for logit, gain in ((-50.0, 0.25), (50.0, 4.0), (0.0, 2.125)):
        assert Exposure(logit).gain().item() == pytest.approx(gain)


@pytest.mark.parametrize("mode", ["softmax", "free", "fixed"])
def test_cfa_module_equals_functional(mode):
    module = CFA("RGGB", 2, mode)
    image = torch.rand(2, 3, 6, 6)
    torch.testing.assert_close(module(image), cfa_mosaic(image, module.phi()))
    assert module.hard_letters() == [["R", "G"], ["G", "B"]]


def test_cfa_softmax_anneals_to_one_hot_and_learns():
    from warpsense.train.schedule import Schedule

    module = CFA("RCCC", 2, "softmax", init_logit=2.0, temperature_start=1.0, temperature_end=0.01)
    schedule = Schedule(epochs=3, warmup_epochs=1)
    module.on_epoch(schedule, 0)  # warm-up: the start temperature
    assert float(module.temperature) == 1.0
    soft = module.phi().detach().clone()
    module.on_epoch(schedule, 1)  # geometric annealing: start * (end / start) ** 0 at the first joint epoch
    assert float(module.temperature) == pytest.approx(1.0)
    module.on_epoch(schedule, 2)  # the last epoch reaches the end temperature
    assert float(module.temperature) == pytest.approx(0.01)
    torch.testing.assert_close(module.phi(), module.hard_phi(), atol=1e-6, rtol=0)
    assert not torch.allclose(soft, module.hard_phi())
    module.on_epoch(schedule, 0)
    module(torch.rand(1, 3, 4, 4)).sum().backward()
    assert module.logits.grad is not None and module.logits.grad.abs().sum() > 0


def test_cfa_temperature_anneals_geometrically_through_the_joint_phase():
    from warpsense.camera.cfa import annealed_temperature
    from warpsense.train.schedule import Schedule

    schedule = Schedule(epochs=6, warmup_epochs=2)
    temperatures = [annealed_temperature(schedule, e, 1.0, 0.05) for e in range(6)]
    assert temperatures[:3] == [1.0, 1.0, 1.0] and temperatures[-1] == pytest.approx(0.05)
    ratios = [b / a for a, b in zip(temperatures[2:], temperatures[3:])]
    assert ratios == pytest.approx([0.05 ** (1 / 3)] * 3)  # geometric over the joint epochs
    assert annealed_temperature(Schedule(3, 2), 2, 1.0, 0.05) == 0.05  # one joint epoch: already the end value
    assert annealed_temperature(Schedule(3, 3), 2, 1.0, 0.05) == 1.0  # no joint phase: never annealed


def test_cfa_layouts_tiles_and_errors():
    assert CFA("BGGR", 4, "fixed").phi().shape == (4, 4, 3)
    assert CFA("GRBG", 1, "fixed").hard_letters() == [["G"]]
    with pytest.raises(KeyError, match="valid layouts: RGGB"):
        CFA("XYZW")
    with pytest.raises(KeyError, match="valid modes"):
        CFA("RGGB", mode="learned")
    assert not any(p.requires_grad for p in CFA("RGGB", 2, "fixed").parameters())


def test_letters_to_phi_refuses_a_flat_layout_and_names_the_filters():
    """A flat "RGGB" (as LearnedCamera.cfa_layout spells it) was read as four rows of one letter, a [4, 1, 3]
    tensor; an unknown letter was a bare KeyError 'X'."""
    from warpsense.camera import layout_letters, letters_to_phi

    with pytest.raises(TypeError, match=r"^letters_to_phi: letters must be rows of letters .* got the string 'RGGB'"):
        letters_to_phi("RGGB")
    with pytest.raises(KeyError, match="unknown filter letter 'X'; filters: R, G, B, C, Y"):
        letters_to_phi([["R", "X"], ["G", "B"]])
    assert torch.equal(letters_to_phi(layout_letters("RGGB", 2)),
                       torch.tensor([[[1.0, 0, 0], [0, 1, 0]], [[0, 1, 0], [0, 0, 1]]]))
    assert letters_to_phi([list("RGBC")]).shape == (1, 4, 3)  # one row of candidates, as the CFA stage uses it


def test_noise_module_equals_functional_and_seeds():
    module = SensorNoise(0.015, 0.002, eval_seed=42).eval()
    raw = torch.rand(2, 1, 5, 5)
    torch.testing.assert_close(module(raw), poisson_gaussian(raw, 0.015, 0.002, 42 + torch.arange(2)))
    assert torch.equal(module(raw), module(raw))  # eval: fixed seed
    module.train()
    assert not torch.equal(module(raw), module(raw))  # training: a new seed per call


@pytest.mark.parametrize("eval_seed", [42, 2**31 - 3, -5])
def test_noise_eval_seeds_wrap_into_the_int31_range(eval_seed):
    """eval_seed + the place in the batch, modulo 2^31 - 1 (a seed near the top wraps), or + the image's index."""
    module = SensorNoise(0.015, 0.002, eval_seed=eval_seed).eval()
    expected = [(eval_seed + offset) % (2**31 - 1) for offset in range(4)]
    assert module.seeds(4).tolist() == expected and module.seeds(4).dtype == torch.int32
    index = torch.tensor([7, 0])
    assert module.seeds(2, index).tolist() == [(eval_seed + 7) % (2**31 - 1), expected[0]]


def test_noise_what_if_scale():
    """noise_scale s: the read std times s, the shot variance coefficient times s^2; 1 leaves the levels bitwise."""
    module = SensorNoise(0.015, 0.002)
    shot, read = module.levels()
    module.scale = 0.5
    scaled_shot, scaled_read = module.levels()
    torch.testing.assert_close(scaled_shot, shot * 0.25)
    torch.testing.assert_close(scaled_read, read * 0.5)
    module.scale = 1.0
    assert torch.equal(module.levels()[0], shot) and torch.equal(module.levels()[1], read)


def test_noise_learnable_levels_bounded():
    module = SensorNoise(0.01, 0.002, learnable=True)
    with torch.no_grad():
        module.shot_logit.fill_(50.0)
        module.read_logit.fill_(-50.0)
    shot, read = module.levels()
    assert shot.item() == pytest.approx(0.02) and read.item() == pytest.approx(0.0, abs=1e-12)
    assert module.shot_logit.requires_grad


def test_quantizer_module_equals_functional():
    module = Quantizer(8, 1.0, "max")
    raw = torch.rand(2, 1, 4, 4)
    torch.testing.assert_close(module(raw), quantize_ste(raw, 8, 1.0, "max"))


def test_optics_module_equals_functional_and_normalises():
    optics = Optics(Lens.from_json("phone_68deg"), normalize_mean=0.0)
    image = torch.rand(1, 3, 20, 24)
    # without normalisation the light is the radiance times the throughput (2 / F#)^2 t / 10 ms (f/1.9, 10 ms here)
    torch.testing.assert_close(optics(image), psf_conv(image, optics.psf()) * (2 / 1.9) ** 2)
    normalised = Optics(Lens.from_json("phone_68deg"), normalize_mean=0.5)(image)
    assert normalised.mean().item() == pytest.approx(0.5, rel=1e-5)


def test_learnable_optics_gets_gradient_and_caches_when_frozen():
    optics = Optics(Lens.from_json("phone_68deg", learnable=True), learnable=True, normalize_mean=0.5).train()
    optics.lens.spec.pupil_samples = 24
    optics(torch.rand(1, 3, 16, 16)).square().sum().backward()
    assert optics.lens.offset.grad.abs().sum() > 0
    optics.lens.offset.requires_grad_(False)
    first = optics.psf()
    assert optics.psf() is first  # frozen: rendered once


def test_a_copied_or_pickled_learnable_optics_renders_what_it_loads():
    """The cached PSF grid is dropped by load_state_dict of the module itself: a deepcopy's load refreshed the
    original's cache and kept its own stale grid, and pickling (torch.save of a camera) failed on the hook."""
    import copy
    import pickle

    source = Optics(Lens.from_json("phone_68deg", learnable=True), learnable=True).eval()
    source.lens.spec.pupil_samples = 24
    other = copy.deepcopy(source)
    with torch.no_grad():
        other.lens.offset.add_(0.5)
    image = torch.rand(1, 3, 16, 16)
    for copied in (copy.deepcopy(source), pickle.loads(pickle.dumps(source))):
        with torch.no_grad():
            copied(image)  # caches the grid of the design it starts at
            copied.load_state_dict(other.state_dict())
            torch.testing.assert_close(copied(image), other(image))


def test_camera_constructs_only_enabled_stages():
    config = load_config(None, ["noise.enabled=false", "quantize.enabled=false", "exposure.enabled=false"])
    camera = Camera.from_config(config)
    assert camera.optics is None and camera.noise is None and camera.quantizer is None and camera.exposure is None
    radiance = torch.rand(1, 3, 6, 6)
    torch.testing.assert_close(camera(radiance), cfa_mosaic(radiance, camera.cfa.phi()))


def test_camera_chain_equals_functional_composition():
    config = load_config(None, ["optics.enabled=true", "optics.normalize_mean=0.0"])
    camera = Camera.from_config(config).eval()
    radiance = torch.rand(2, 3, 16, 20)
    image = psf_conv(radiance, camera.optics.psf()) * camera.optics.throughput()
    raw = cfa_mosaic(image, camera.cfa.phi() * camera.exposure.gain())
    raw = poisson_gaussian(raw, *camera.noise.levels(), camera.noise.eval_seed + torch.arange(2))
    expected = quantize_ste(raw, 10)
    torch.testing.assert_close(camera(radiance), expected)


def test_fixed_isp_reconstructs_smooth_colour():
    letters = [["R", "G"], ["G", "B"]]
    isp = FixedISP(letters, gamma=1.0)
    colour = torch.tensor([0.2, 0.5, 0.8]).view(1, 3, 1, 1).expand(1, 3, 8, 8)
    raw = cfa_mosaic(colour.contiguous(), CFA("RGGB", 2, "fixed").phi())
    torch.testing.assert_close(isp(raw), colour, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="R/G/B layout"):
        FixedISP([["R", "C"], ["C", "C"]])


@pytest.mark.parametrize("size", [(1, 1), (1, 6), (5, 1)])
def test_fixed_isp_takes_an_image_one_pixel_high_or_wide(size):
    """Reflect padding has nothing to reflect on a side of one pixel: torch refused it ('Padding size should be
    less than the corresponding input dimension'), so a fixed-ISP model failed on a 1 x 1 frame. Such a side now
    repeats its pixel: each colour whose sites the image holds is reconstructed exactly."""
    isp = FixedISP([["R", "G"], ["G", "B"]], gamma=1.0)
    colour = torch.tensor([0.2, 0.5, 0.8]).view(1, 3, 1, 1).expand(1, 3, *size).contiguous()
    rgb = isp(cfa_mosaic(colour, CFA("RGGB", 2, "fixed").phi()))
    present = {(1, 1): [0], (1, 6): [0, 1], (5, 1): [0, 1]}[size]  # R at (0, 0); G beside or below it
    torch.testing.assert_close(rgb[:, present], colour[:, present], atol=1e-6, rtol=0)


def test_camera_fused_equals_per_stage_chain_with_gradients():
    """The fused sensor kernel and the per-stage ops (taken for exact Poisson / max quantization) agree."""
    config = load_config(None, ["noise.learnable=true"])
    camera = Camera.from_config(config).train()
    radiance = torch.rand(2, 3, 8, 10, requires_grad=True)
    seeds = camera.noise.seeds(2)
    camera.noise.seed_counter.sub_(2)  # replay the same draw
    fused = camera(radiance)
    assert camera.fusable()
    raw = cfa_mosaic(radiance, camera.cfa.phi() * camera.exposure.gain())
    expected = quantize_ste(poisson_gaussian(raw, *camera.noise.levels(), seeds), 10)
    torch.testing.assert_close(fused, expected)
    parameters = [radiance, camera.cfa.logits, camera.exposure.gain_logit, camera.noise.shot_logit]
    grad = torch.randn_like(fused)
    for mine, theirs in zip(torch.autograd.grad(fused, parameters, grad),
                            torch.autograd.grad(expected, parameters, grad)):
        torch.testing.assert_close(mine, theirs)


def test_eval_noise_keyed_by_dataset_index():
    camera = Camera.from_config(load_config(None, [])).eval()
    radiance = torch.rand(4, 3, 6, 6)
    whole = camera(radiance, torch.arange(10, 14))
    torch.testing.assert_close(camera(radiance[2:], torch.arange(12, 14)), whole[2:])
    assert not torch.equal(camera(radiance[:2], torch.arange(0, 2)), whole[:2])


@pytest.mark.parametrize("config", [{}, "camvid_codesign", "camvid_photons"])
def test_camera_on_the_meta_device_gives_the_raw_shape(config):
    """A camera moved to the meta device (shape inference) runs without host reads: the finite check's .item()
    failed on the meta tensor, and the Warp ops had no meta device."""
    camera = Camera.from_config(config).to("meta")
    for mode in (camera.eval, camera.train):
        mode()
        raw = camera(torch.empty(2, 3, 33, 47, device="meta"))
        assert raw.shape == (2, 1, 33, 47) and raw.is_meta
    with pytest.raises(ValueError, match=r"^camera: radiance is on cpu, the camera on meta; move one to the other"):
        camera(torch.rand(1, 3, 8, 8))  # was 'sensor_capture: inputs must be on one device, got rgb on cpu, ...'


@pytest.mark.parametrize("radiance, index, error, message", [
    (torch.rand(1, 3, 6, 6).numpy(), None, TypeError, "camera: radiance must be a torch.Tensor, got ndarray"),
    (torch.rand(1, 1, 6, 6), None, ValueError, r"camera: radiance must be \[B, 3, H, W\] \(linear RGB\), got "
                                               r"\(1, 1, 6, 6\)"),
    (torch.rand(3, 6, 6), None, ValueError, r"camera: radiance must be a non-empty \[B, 3, H, W\] tensor"),
    (torch.randint(0, 256, (1, 3, 6, 6)), None, TypeError, r"camera: radiance must be floating point \(linear\), "
                                                           r"got torch.int64; an sRGB frame is decoded by "
                                                           r"warpsense.data.color.srgb_to_linear"),
    (torch.rand(2, 3, 6, 6), 3, TypeError, r"camera: image_index must be an integer tensor \[B\], got int"),
    (torch.rand(2, 3, 6, 6), torch.tensor([3.0, 4.0]), TypeError, "image_index must be an integer tensor"),
    (torch.rand(2, 3, 6, 6), torch.tensor([3]), ValueError, r"camera: image_index must be \[B\] = \(2,\), one "
                                                            r"index per image, got \(1,\)"),
])
def test_camera_names_a_wrong_radiance_or_image_index(radiance, index, error, message):
    """One line naming the camera's argument: a numpy array and an int index were AttributeErrors from inside, an
    index per batch of the wrong length was 'sensor_capture: seed must be ...', a float index truncated."""
    camera = Camera.from_config(load_config(None, [])).eval()
    with pytest.raises(error, match=message) as raised:
        camera(radiance, index)
    assert "\n" not in str(raised.value)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nan_policy_camera_rejects_non_finite_radiance(bad):
    """Issue 15 D10: one bad pixel is refused at the camera input with a clear error, for the full camera (the
    optics' normalisation would otherwise spread it over the frame and into every camera gradient)."""
    from warpsense.camera.camera import set_finite_check
    from warpsense.config import load_config
    from warpsense.system import build_system

    torch.manual_seed(0)
    model = build_system(load_config("camvid_codesign", ["train.compile=off"]), 11)
    radiance = torch.rand(1, 3, 16, 20)
    radiance[0, 1, 3, 4] = bad
    with pytest.raises(ValueError, match="camera: radiance has 1 non-finite values"):
        model(radiance)
    set_finite_check(model, False)  # the training loop's setting: no check, and the NaN is not local
    logits, _ = model(radiance)
    assert not torch.isfinite(logits).any()
    set_finite_check(model, True)
    assert torch.isfinite(model(torch.rand(1, 3, 16, 20))[0]).all()


def test_physical_sensor_preset_noise_matches_electron_counts():
    """Issue 13: a 4500 e- full well with 2 e- read noise. A flat field at half the white level holds 2250 e-; its
    variance in white-level units is (2250 + 2^2) / 4500^2."""
    from warpsense.camera import SensorNoise

    config = load_config("camvid_codesign_phone")
    stage = SensorNoise.from_config(config.noise)
    shot, read = (float(level) for level in stage.levels())
    assert shot == pytest.approx(1 / 4500) and read == pytest.approx(2 / 4500)
    noise = SensorNoise(shot, read).train()
    flat = torch.full((4, 1, 128, 128), 0.5, dtype=torch.float64)
    variance = noise(flat).var().item()
    assert variance == pytest.approx((2250 + 4) / 4500**2, rel=0.05)
    from warpsense.system import check_config

    with pytest.raises(ConfigError, match="noise.read_electrons needs noise.full_well_electrons"):
        check_config(load_config(None, ["noise.read_electrons=2"]))


def test_camera_from_a_preset_name_path_or_dict_equals_from_its_config(tmp_path):
    reference = Camera.from_config(load_config("camvid_learned_cfa"))
    path = tmp_path / "camera.toml"
    path.write_text('base = "camvid_learned_cfa"\n')
    for source in ("camvid_learned_cfa", path, load_config("camvid_learned_cfa").to_dict()):
        camera = Camera.from_config(source)
        assert [type(stage) for stage in camera.children()] == [type(stage) for stage in reference.children()]
        for (name, value), (_, expected) in zip(camera.state_dict().items(), reference.state_dict().items()):
            assert name.endswith("seed_counter") or torch.equal(value, expected), name  # noise seeds are random
    assert Camera.from_config({"optics": {"enabled": False}}).optics is None  # a partial dict: the rest defaults
    with pytest.raises(ConfigError, match="no_such_key"):
        Camera.from_config({"optics": {"no_such_key": 1}})
    with pytest.raises(TypeError, match="Camera.from_config"):
        Camera.from_config(42)


@pytest.mark.parametrize("sections, message", [
    ({"photons": {"enabled": True}}, "photons.enabled states the noise from electrons: set noise.enabled = false"),
    ({"noise": {"read_electrons": 2.0}}, "noise.read_electrons needs noise.full_well_electrons"),
])
def test_camera_from_config_refuses_what_the_stages_refuse(sections, message):
    """Camera.from_config runs the stages' checks (`Camera.check_config`), as the system does: it built a photon
    budget beside the noise and exposure stages it replaces (noise drawn twice), and ignored read_electrons."""
    with pytest.raises(ValueError, match=f"^Camera.from_config: {message}"):
        Camera.from_config(sections)


def test_gumbel_cfa_explores_one_hot_choices_and_learns_straight_through():
    torch.manual_seed(0)
    module = CFA("RGGB", 2, "gumbel", init_logit=0.0, candidates="RGBCY").train()  # uniform start
    seen = set()
    for _ in range(60):
        phi = module.phi()
        rows = {tuple(row) for row in phi.reshape(-1, 3).tolist()}
        assert rows <= {(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0, 1.0), (1.0, 1.0, 0.0)}
        seen |= rows
    assert len(seen) == 5  # every candidate filter is tried
    image = torch.rand(1, 3, 4, 4)
    module(image).sum().backward()
    assert module.logits.grad is not None and float(module.logits.grad.abs().sum()) > 0
    with torch.no_grad():
        module.logits.zero_()
        module.logits[..., 3] = 5.0  # clear everywhere
    module.eval()
    assert module.hard_letters() == [["C", "C"], ["C", "C"]]
    torch.testing.assert_close(module.phi(), torch.ones(2, 2, 3))
    assert module.summary()["cfa_layout"] == "CCCC"


def test_free_cfa_transmittances_stay_in_zero_one():
    module = CFA("RYYB", 2, "free", candidates="RGBCY")
    with torch.no_grad():
        module.responses.mul_(100)
    phi = module.phi().detach()
    assert float(phi.min()) >= 0 and float(phi.max()) <= 1
    assert module.hard_letters() == [["R", "Y"], ["Y", "B"]]


def test_nan_policy_camera_takes_finite_radiance_whose_sum_overflows():
    """The check sums the radiance first (one reduction): a float64 sum that overflows from finite pixels is counted
    exactly and passes."""
    from warpsense.camera import Camera
    from warpsense.config import load_config

    camera = Camera.from_config(load_config(None, []))
    radiance = torch.full((1, 3, 8, 10), 1e307, dtype=torch.float64)
    assert torch.isinf(radiance.sum())
    assert camera(radiance).shape == (1, 1, 8, 10)
    radiance[0, 2, 1, 1] = float("inf")
    with pytest.raises(ValueError, match="camera: radiance has 1 non-finite values"):
        camera(radiance)


def test_camera_differentiates_with_respect_to_the_scene_without_warnings():
    """Gradients with respect to the radiance are a normal use: the finite check must not make torch warn about
    converting a tensor that requires grad to a Python number (it read the sum of the graph-carrying radiance), and
    a non-finite pixel is still refused."""
    import warnings

    camera = Camera.from_config(load_config(None, ["noise.enabled=false"])).eval()
    radiance = torch.rand(1, 3, 8, 10, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        raw = camera(radiance)
        (gradient,) = torch.autograd.grad(raw.sum(), radiance)
    assert torch.isfinite(gradient).all() and gradient.abs().sum() > 0
    bad = radiance.detach().clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="camera: radiance has 1 non-finite values"):
        camera(bad.requires_grad_())

