"""DSUNet: shapes, the channels-last layout against the contiguous one, and the bf16 decoder path."""

import pytest
import torch

from warpsense.models import DSUNet, build_model, count_parameters


@pytest.mark.parametrize("in_channels, height, width", [(1, 32, 48), (1, 37, 45), (3, 30, 50)])
def test_cardinality(in_channels, height, width):
    logits = DSUNet(in_channels=in_channels, num_classes=5, width=8)(torch.rand(2, in_channels, height, width))
    assert logits.shape == (2, 5, height, width)


def test_parameter_budget():
    assert count_parameters(build_model("dsunet", in_channels=1, num_classes=11, width=16)) < 500_000


def test_exception_unknown_model():
    with pytest.raises(KeyError, match="dsunet"):
        build_model("unet9000")


@pytest.mark.parametrize("name", ["dsunet", "packunet"])
def test_feature_channels_last_matches_contiguous(name):
    """Same weights, same input, float64: NHWC gives the NCHW logits and parameter gradients up to rounding (both
    registered networks)."""
    torch.manual_seed(0)
    contiguous, channels_last = (build_model(name, in_channels=1, num_classes=4, width=8, channels_last=layout).double()
                                 for layout in (False, True))
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
