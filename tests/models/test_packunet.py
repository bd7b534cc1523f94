"""PackUNet: shapes, the parameter budget, the 2 x 2 packing and the thin full-resolution path (its channels-last
layout is tested with DSUNet's, in test_dsunet.py)."""

import pytest
import torch

from warpsense.models import PackUNet, build_model, count_parameters


@pytest.mark.parametrize("in_channels, height, width", [(1, 32, 48), (1, 37, 45), (3, 30, 50)])
def test_cardinality(in_channels, height, width):
    logits = PackUNet(in_channels=in_channels, num_classes=5, width=8)(torch.rand(2, in_channels, height, width))
    assert logits.shape == (2, 5, height, width)


def test_parameter_budget():
    """The registry's default width stays within the 0.5M budget for CamVid's 11 classes."""
    assert 400_000 < count_parameters(build_model("packunet", in_channels=1, num_classes=11, width=22)) < 500_000


def test_feature_packing_sees_each_cfa_site():
    """The packed path's join block reads one channel per 2 x 2 site: a mosaic lit at one site only reaches the
    join convolution's input as that one packed channel (the pixel-unshuffle order: (0,0), (0,1), (1,0), (1,1))."""
    network = PackUNet(in_channels=1, num_classes=3, width=4).eval()
    seen = {}
    network.join.register_forward_hook(lambda module, inputs, output: seen.update(x=inputs[0]))
    for site, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        mosaic = torch.zeros(1, 1, 16, 16)
        mosaic[..., dy::2, dx::2] = 1.0
        network(mosaic)
        packed = seen["x"][:, -4:]
        assert torch.equal(packed[0, site], torch.ones(8, 8))
        assert packed.sum() == 64


def test_feature_one_pixel_reaches_its_neighbourhood_at_full_resolution():
    """A one-pixel change moves the logits most near that pixel (the full-resolution detail path and head),
    not uniformly over the frame."""
    torch.manual_seed(0)
    network = PackUNet(in_channels=1, num_classes=3, width=8).eval()
    image = torch.rand(1, 1, 64, 64)
    changed = image.clone()
    changed[..., 32, 33] += 1.0
    with torch.no_grad():
        difference = (network(changed) - network(image)).abs().sum(dim=1)[0]
    near = difference[30:35, 31:36].max()
    far = difference[:8, :8].max()
    assert near > 10 * far


def test_module_trains_on_a_toy_task():
    """A few AdamW steps fit a vertical-stripe labelling (thin, one pixel wide classes at full resolution)."""
    torch.manual_seed(0)
    network = PackUNet(in_channels=1, num_classes=2, width=8, channels_last=False)
    image = torch.zeros(4, 1, 32, 32)
    image[..., ::4] = 1.0
    target = (image[:, 0] > 0.5).long()
    optimizer = torch.optim.AdamW(network.parameters(), lr=1e-2)
    for _ in range(60):
        loss = torch.nn.functional.cross_entropy(network(image), target)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    network.eval()
    accuracy = (network(image).argmax(dim=1) == target).float().mean()
    assert accuracy > 0.99
