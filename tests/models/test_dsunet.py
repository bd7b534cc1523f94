"""DSUNet: shapes, the channels-last layout against the contiguous one, the bf16 decoder path, the bottleneck
context module (pyramid pooling), the networks without squeeze-and-excitation, the full-resolution path's width and
depth, and the network a config builds."""

import copy
import dataclasses
import inspect

import pytest
import torch

from warpsense.config import ModelConfig, load_config
from warpsense.models import DSUNet, build_model, count_parameters, network_from_config
from warpsense.models.dsunet import PyramidPooling, SeparableBlock, SqueezeExcitation, build_context


@pytest.mark.parametrize("context", ["none", "pyramid"])
@pytest.mark.parametrize("in_channels, height, width", [(1, 32, 48), (1, 37, 45), (3, 30, 50)])
def test_cardinality(in_channels, height, width, context):
    """Also where the 1/16 map (2 x 3) is smaller than the pyramid's finest bins (4 x 4)."""
    logits = DSUNet(in_channels=in_channels, num_classes=5, width=8, context=context)(
        torch.rand(2, in_channels, height, width))
    assert logits.shape == (2, 5, height, width)


@pytest.mark.parametrize("full_width, full_depth", [(12, 1), (0, 2), (12, 3)])
def test_cardinality_full_resolution_path(full_width, full_depth):
    network = DSUNet(in_channels=1, num_classes=5, width=8, full_width=full_width, full_depth=full_depth)
    assert network(torch.rand(2, 1, 37, 45)).shape == (2, 5, 37, 45)
    channels = full_width or 8
    assert network.stem[0].out_channels == network.head.in_channels == channels
    assert len(network.enc1) == len(network.dec1) == full_depth


def test_exception_full_resolution_path():
    with pytest.raises(ValueError, match="full_depth >= 1, got 0 and 0"):
        DSUNet(width=8, full_depth=0)


@pytest.mark.parametrize("full_width", [0, 12])
def test_cardinality_decoder_stages_take_the_upsampled_features_and_the_skip(full_width):
    """Each decoder stage runs on the deeper features' channels plus its skip's: (8w + 6w, 6w + 4w, 4w + 2w, 2w + f)
    at w = 8, f = full_width or w."""
    network = DSUNet(in_channels=1, num_classes=5, width=8, full_width=full_width)
    assert network(torch.rand(2, 1, 37, 45)).shape == (2, 5, 37, 45)
    f = full_width or 8
    for level, channels in {"4": 64 + 48, "3": 48 + 32, "2": 32 + 16, "1": 16 + f}.items():
        assert getattr(network, f"dec{level}")[0].depthwise.in_channels == channels


def test_feature_full_width_equal_to_width_is_the_default_network():
    torch.manual_seed(0)
    default = DSUNet(in_channels=1, num_classes=4, width=8).double().eval()
    same = DSUNet(in_channels=1, num_classes=4, width=8, full_width=8).double().eval()
    same.load_state_dict(default.state_dict())  # strict: the same parameters and shapes
    image = torch.rand(2, 1, 32, 48, dtype=torch.float64)
    torch.testing.assert_close(same(image), default(image), rtol=0, atol=0)


def test_feature_deeper_full_resolution_path_with_silent_blocks_is_the_shallow_network():
    """The extra full-resolution blocks are residual: with their last BN scale at 0 each adds exactly 0, so the depth-3
    network with the depth-1 network's weights gives its logits; with the scale left as built, it does not."""
    torch.manual_seed(0)
    shallow = DSUNet(in_channels=1, num_classes=4, width=8).double().eval()
    deep = DSUNet(in_channels=1, num_classes=4, width=8, full_depth=3).double().eval()
    missing, unexpected = deep.load_state_dict(shallow.state_dict(), strict=False)
    assert not unexpected and missing and all(key.startswith(("enc1.1.", "enc1.2.", "dec1.1.", "dec1.2."))
                                              for key in missing)
    image = torch.rand(2, 1, 32, 48, dtype=torch.float64)
    assert not torch.allclose(deep(image), shallow(image))
    for stage in (deep.enc1, deep.dec1):
        for block in list(stage)[1:]:
            torch.nn.init.zeros_(block.norm2.weight)
    torch.testing.assert_close(deep(image), shallow(image), rtol=1e-12, atol=1e-12)


def test_parameter_budget():
    assert count_parameters(build_model("dsunet", in_channels=1, num_classes=11, width=16)) < 500_000
    # the camvid presets' width with the context module stays inside the 0.5M budget of the recipe issue
    assert count_parameters(build_model("dsunet", in_channels=1, num_classes=11, width=24, context="pyramid")) < 500_000


def test_exception_unknown_context():
    with pytest.raises(KeyError, match="none, pyramid"):
        build_context("aspp", 16)


def test_feature_context_starts_as_the_network_without_it():
    """The pyramid's last BN scale starts at 0: with the other weights shared, the network with the module gives the
    network without it, in training and in evaluation; and the module's parameters do receive gradients."""
    torch.manual_seed(0)
    plain = DSUNet(in_channels=1, num_classes=4, width=8).double()
    pooled = DSUNet(in_channels=1, num_classes=4, width=8, context="pyramid").double()
    missing, unexpected = pooled.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(key.startswith("context.") for key in missing)
    image = torch.rand(2, 1, 40, 56, dtype=torch.float64)
    for mode in (True, False):
        plain.train(mode), pooled.train(mode)
        torch.testing.assert_close(pooled(image), plain(image), rtol=0, atol=0)
    pooled.train()
    pooled(image).square().sum().backward()
    assert pooled.context.norm.weight.grad.abs().max() > 0


def test_feature_pyramid_on_a_constant_map_is_its_matrix_form():
    """On a spatially constant map every pooled region holds the map's value, and upsampling a constant is the
    constant: the module reduces to matrix products on the channel vector (an independent reference, with BN in
    evaluation form); and one pixel changed reaches every output through the 1 x 1 bin."""
    torch.manual_seed(1)
    module = PyramidPooling(8).double().eval()
    torch.nn.init.normal_(module.norm.weight)
    module.norm.running_mean.normal_()
    module.norm.running_var.uniform_(0.5, 2.0)
    value = torch.randn(8, dtype=torch.float64)
    out = module(value.view(1, 8, 1, 1).expand(1, 8, 6, 10).contiguous())
    branches = torch.cat([torch.relu(b.weight[:, :, 0, 0] @ value + b.bias) for b in module.branches])
    fused = module.fuse.weight[:, :, 0, 0] @ branches
    norm = module.norm
    expected = value + (fused - norm.running_mean) / torch.sqrt(norm.running_var + norm.eps) * norm.weight + norm.bias
    torch.testing.assert_close(out, expected.view(1, 8, 1, 1).expand(1, 8, 6, 10))
    changed = value.view(1, 8, 1, 1).expand(1, 8, 6, 10).clone()
    changed[0, :, 0, 0] += 1.0
    assert ((module(changed) - out).abs().sum(dim=1) > 0).all()


def test_gradcheck_pyramid():
    torch.manual_seed(2)
    module = PyramidPooling(4).double()
    torch.nn.init.normal_(module.norm.weight)
    x = torch.rand(2, 4, 5, 7, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(module, (x,))


def test_exception_unknown_model():
    with pytest.raises(KeyError, match="dsunet"):
        build_model("unet9000")


def test_feature_channels_last_matches_contiguous():
    """Same weights, same input, float64: NHWC gives the NCHW logits and parameter gradients up to rounding (with the
    context module, its BN scale moved off 0)."""
    torch.manual_seed(0)
    contiguous, channels_last = (DSUNet(in_channels=1, num_classes=4, width=8, channels_last=layout,
                                        context="pyramid").double() for layout in (False, True))
    torch.nn.init.normal_(contiguous.context.norm.weight)
    channels_last.load_state_dict(contiguous.state_dict())
    assert next(channels_last.parameters()).is_contiguous(memory_format=torch.channels_last)
    image = torch.rand(2, 1, 35, 50, dtype=torch.float64)
    target = torch.randn(2, 4, 35, 50, dtype=torch.float64)
    outputs = []
    for network in (contiguous, channels_last):
        logits = network(image)
        (logits * target).sum().backward()
        outputs.append((logits, [p.grad for p in network.parameters()]))
    (logits_a, grads_a), (logits_b, grads_b) = outputs
    torch.testing.assert_close(logits_b, logits_a, rtol=1e-9, atol=1e-10)
    for grad_a, grad_b in zip(grads_a, grads_b):
        torch.testing.assert_close(grad_b, grad_a, rtol=1e-8, atol=1e-9)


def test_feature_decoder_stays_bfloat16_under_autocast():
    """Under bf16 autocast the upsampled decoder features stay bf16 (autocast alone would run the upsampling in
    float32 and promote every skip concatenation to float32), and the upsampling is the plain bilinear one."""
    network = DSUNet(in_channels=1, num_classes=3, width=8).eval()
    low = torch.rand(1, 8, 4, 6).bfloat16()
    like = torch.empty(1, 8, 8, 12, dtype=torch.bfloat16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        upsampled = network._up(low, like)
    assert upsampled.dtype == torch.bfloat16
    reference = torch.nn.functional.interpolate(low.float(), size=(8, 12), mode="bilinear", align_corners=False)
    torch.testing.assert_close(upsampled.float(), reference, rtol=1e-2, atol=1e-2)


def logits_and_gradients(network, image, target):
    """The network's logits and its parameters' gradients for the loss (logits * target).sum()."""
    network.zero_grad()
    logits = network(image)
    (logits * target).sum().backward()
    return logits.detach(), [p.grad.clone() for p in network.parameters()]


def test_feature_deterministic_mode_takes_the_deterministic_resampling(monkeypatch):
    """Under torch's deterministic algorithms (run.deterministic) the network resizes and pools through
    warpsense.models.resample, not through torch's ops whose CUDA backward adds atomically, with the same logits
    and gradients (float64)."""
    torch.manual_seed(3)
    network = DSUNet(in_channels=1, num_classes=4, width=8, context="pyramid").double()
    torch.nn.init.normal_(network.context.norm.weight)
    image = torch.rand(2, 1, 40, 56, dtype=torch.float64)
    target = torch.randn(2, 4, 40, 56, dtype=torch.float64)
    reference_logits, reference_grads = logits_and_gradients(network, image, target)

    def refuse(*args, **kwargs):
        raise AssertionError("a nondeterministic torch op was used in deterministic mode")

    monkeypatch.setattr(torch.nn.functional, "interpolate", refuse)
    monkeypatch.setattr(torch.nn.functional, "adaptive_avg_pool2d", refuse)
    previous = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        logits, grads = logits_and_gradients(network, image, target)
    finally:
        torch.use_deterministic_algorithms(previous)
    torch.testing.assert_close(logits, reference_logits, rtol=1e-10, atol=1e-12)
    for grad, reference in zip(grads, reference_grads):
        torch.testing.assert_close(grad, reference, rtol=1e-9, atol=1e-11)


def test_feature_fused_ops_are_the_torch_ones(monkeypatch):
    """A channels-last network on a fused device joins its four decoder levels with `upsample_concat`, runs every
    batch norm followed by a ReLU (all but the context module's) as `batch_norm_relu` and every squeeze-and-
    excitation gate (with its block's residual) as `channel_gate`: the same logits, gradients and running
    statistics (float64) as torch's ops."""
    from warpsense.models import dsunet

    torch.manual_seed(4)
    network = DSUNet(in_channels=1, num_classes=4, width=8, context="pyramid", channels_last=True).double()
    fused_network = copy.deepcopy(network)
    image = torch.rand(2, 1, 40, 56, dtype=torch.float64)
    target = torch.randn(2, 4, 40, 56, dtype=torch.float64)
    monkeypatch.setattr(dsunet, "FUSED_DEVICES", ())
    reference_logits, reference_grads = logits_and_gradients(network, image, target)
    joins, norms, gates = [], [], []
    fused_join, fused_norm, fused_gate = dsunet.upsample_concat, dsunet.batch_norm_relu, dsunet.channel_gate
    monkeypatch.setattr(dsunet, "upsample_concat", lambda x, skip: joins.append(x.shape) or fused_join(x, skip))
    monkeypatch.setattr(dsunet, "batch_norm_relu", lambda x, *args: norms.append(x.shape) or fused_norm(x, *args))
    monkeypatch.setattr(dsunet, "channel_gate", lambda x, *args: gates.append(x.shape) or fused_gate(x, *args))
    monkeypatch.setattr(dsunet, "FUSED_DEVICES", ("cpu",))
    logits, grads = logits_and_gradients(fused_network, image, target)
    assert len(joins) == 4
    assert len(norms) == sum(isinstance(m, torch.nn.BatchNorm2d) for m in network.modules()) - 1
    assert len(gates) == sum(isinstance(m, SqueezeExcitation) for m in network.modules()) > 0
    torch.testing.assert_close(logits, reference_logits, rtol=1e-10, atol=1e-12)
    for grad, reference in zip(grads, reference_grads):
        torch.testing.assert_close(grad, reference, rtol=1e-9, atol=1e-11)
    for (key, buffer), reference in zip(fused_network.state_dict().items(), network.state_dict().values()):
        torch.testing.assert_close(buffer, reference, rtol=1e-12, atol=1e-14, msg=key)
    norms.clear()
    gates.clear()
    joins.clear()
    with torch.no_grad():  # evaluation: running statistics and torch's gate (faster at batch 1 under graph replay)
        eval_logits = fused_network.eval()(image)
    assert not norms and not gates and len(joins) == 4
    monkeypatch.setattr(dsunet, "FUSED_DEVICES", ())
    with torch.no_grad():
        torch.testing.assert_close(eval_logits, network.eval()(image), rtol=1e-10, atol=1e-12)
    monkeypatch.setattr(dsunet, "FUSED_DEVICES", ("cpu",))
    joins.clear()
    with torch.no_grad():  # one image, eager: torch's joins (less host time per call); the same logits
        single = fused_network(image[:1])
    assert not joins
    monkeypatch.setattr(dsunet, "_capturing", lambda x: True)  # inside a CUDA graph capture: the fused joins
    with torch.no_grad():
        torch.testing.assert_close(fused_network(image[:1]), single, rtol=1e-10, atol=1e-12)
    assert len(joins) == 4


def test_feature_without_squeeze_is_the_network_with_its_se_gates_removed():
    """``squeeze=False`` builds the same network minus every squeeze-and-excitation: with the shared weights copied
    and each SE of the full network replaced by the identity, the two give the same logits."""
    torch.manual_seed(0)
    full = DSUNet(in_channels=1, num_classes=4, width=8).double().eval()
    lean = DSUNet(in_channels=1, num_classes=4, width=8, squeeze=False).double().eval()
    assert not any(isinstance(m, SqueezeExcitation) for m in lean.modules())
    missing, unexpected = lean.load_state_dict(full.state_dict(), strict=False)
    assert not missing and unexpected and all(".squeeze." in key for key in unexpected)
    se_parameters = sum(p.numel() for m in full.modules() if isinstance(m, SqueezeExcitation) for p in m.parameters())
    assert count_parameters(lean) == count_parameters(full) - se_parameters > 0
    for module in full.modules():
        if isinstance(module, SeparableBlock):
            module.squeeze = torch.nn.Identity()
    image = torch.rand(2, 1, 40, 56, dtype=torch.float64)
    torch.testing.assert_close(lean(image), full(image), rtol=0, atol=0)


def test_module_network_from_config_takes_every_model_key():
    """Every [model] key but the network's name and what it reads (model.input: the system's) reaches DSUNet."""
    config = load_config(None, ["model.width=8", "model.context=pyramid", "model.squeeze=false",
                                "model.channels_last=false", "model.num_classes=5", "model.full_width=12",
                                "model.full_depth=2"])
    network = network_from_config(config.model, in_channels=1, num_classes=11, tile=2)
    expected = DSUNet(in_channels=1, num_classes=5, width=8, context="pyramid", squeeze=False, full_width=12,
                      full_depth=2)
    assert [name for name, _ in network.named_parameters()] == [name for name, _ in expected.named_parameters()]
    assert network.memory_format == torch.contiguous_format and network.head.out_channels == 5
    keys = {spec.name for spec in dataclasses.fields(ModelConfig)}
    assert keys - set(inspect.signature(DSUNet).parameters) == {"name", "input"}


def test_module_network_from_config_passes_a_network_only_its_own_keys(monkeypatch):
    """A registered network receives the [model] keys its constructor names, no others: it need not accept (and
    refuse) the knobs of another network."""
    from warpsense import models

    with pytest.raises(KeyError, match=r"unknown model 'gone'; valid models: dsunet\b"):
        network_from_config(ModelConfig(name="gone"), in_channels=1, num_classes=11, tile=2)
    received = {}

    def tiny(in_channels, num_classes, width):
        received.update(in_channels=in_channels, num_classes=num_classes, width=width)
        return torch.nn.Identity()

    monkeypatch.setitem(models.MODELS, "tiny", tiny)
    network_from_config(ModelConfig(name="tiny", width=3, full_width=12, context="pyramid"), in_channels=1,
                        num_classes=11, tile=2)
    assert received == {"in_channels": 1, "num_classes": 11, "width": 3}


def test_feature_torch_ops_context_runs_no_warp_op(monkeypatch):
    """`dsunet.torch_ops` (the benchmarks' plain-torch baseline) keeps a network on a fused device off every Warp
    op, or off the named ones, and restores the fused ops after."""
    from warpsense.models import dsunet

    monkeypatch.setattr(dsunet, "FUSED_DEVICES", ("cpu",))
    calls = []
    for name in ("upsample_concat", "batch_norm_relu", "channel_gate"):
        fused = getattr(dsunet, name)
        monkeypatch.setattr(dsunet, name, lambda *args, fused=fused, name=name: calls.append(name) or fused(*args))
    network = build_model("dsunet", in_channels=1, num_classes=4, width=8, channels_last=True).double()
    image = torch.rand(2, 1, 32, 32, dtype=torch.float64)
    with dsunet.torch_ops():
        network(image)
    assert calls == [] and dsunet.FUSED_DEVICES == ("cpu",)
    network(image)
    assert set(calls) == {"upsample_concat", "batch_norm_relu", "channel_gate"}
    calls.clear()
    with dsunet.torch_ops("norm"):  # one op off, the others as shipped
        network(image)
    assert set(calls) == {"upsample_concat", "channel_gate"}
    with pytest.raises(KeyError, match="valid: joins, norm, gate"):
        with dsunet.torch_ops("relu"):
            pass
