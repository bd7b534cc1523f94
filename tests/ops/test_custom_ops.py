"""The Warp ops as torch.library custom ops: schemas, fake implementations and autograd registrations checked by
`torch.library.opcheck`, and a whole camera traced by torch.compile without graph breaks (equal to eager)."""

import pytest
import torch

from tests.conftest import device_params
from warpsense.camera import Camera
from warpsense.config import load_config
from warpsense.ops import (
    batchnorm,
    cfa,
    cross_entropy,
    gate,
    lovasz,
    noise,
    psf,
    quantize,
    sensor,
    smoothness,
    upsample,
)

DOUBLE = dict(dtype=torch.float64)


def _rand(*shape, grad=True):
    return torch.rand(*shape, **DOUBLE).requires_grad_(grad)


def _seeds(batch):
    return torch.arange(batch, dtype=torch.int32) + 7


CASES = {
    "batch_norm_relu": (batchnorm._batch_norm_relu, lambda: (_rand(30, 4), _rand(4), _rand(4), 1e-5)),
    "batch_norm_update_running": (batchnorm._update_running,
                                  lambda: (_rand(5, 4, grad=False), 30, 0.1, _rand(4, grad=False),
                                           _rand(4, grad=False))),
    "channel_gate": (gate._channel_gate, lambda: (_rand(2, 12, 4), _rand(2, 4), _rand(2, 12, 4))),
    "channel_gate_no_residual": (gate._channel_gate, lambda: (_rand(2, 12, 4), _rand(2, 4), None)),
    "cfa_mosaic": (cfa._cfa_mosaic, lambda: (_rand(2, 3, 5, 6), _rand(2, 2, 3))),
    "softmax_cross_entropy": (cross_entropy._softmax_cross_entropy,
                              lambda: (_rand(2, 4, 5, 3), torch.randint(0, 4, (2, 5, 3), dtype=torch.int32),
                                       torch.ones(4, **DOUBLE), 255)),
    "lovasz_softmax_terms": (lovasz._lovasz_terms, lambda: (torch.softmax(_rand(2, 4, 5, 3, grad=False), 1)
                                                            .requires_grad_(),
                                                            torch.randint(0, 4, (2, 5, 3), dtype=torch.int32), 255)),
    "poisson_gaussian": (noise._poisson_gaussian,
                         lambda: (_rand(2, 1, 4, 5), _rand(1) * 0.1, _rand(1) * 0.1, _seeds(2), 0)),
    "poisson_gaussian_exact": (noise._poisson_gaussian_exact,
                               lambda: (_rand(2, 1, 4, 5, grad=False), torch.full((1,), 0.01, **DOUBLE),
                                        torch.full((1,), 0.01, **DOUBLE), _seeds(2), 0)),
    "quantize_ste": (quantize._quantize_ste, lambda: (_rand(2, 12), torch.ones(2, **DOUBLE), 255)),
    "sensor_capture": (sensor._sensor_capture,
                       lambda: (_rand(2, 3, 4, 6), _rand(2, 2, 3), _rand(1) * 0.1, _rand(1) * 0.1,
                                torch.ones(1, **DOUBLE), _seeds(2), 0, 1, 1023)),
    "psf_conv": (psf._psf_conv_cells, lambda: (_rand(2, 3, 6, 7), psf.node_cells(_rand(3, 3, 2, 3, 3)).detach()
                                               .requires_grad_(), 3, 2)),
    "psf_conv_cudnn": (psf._psf_conv_cudnn, lambda: (_rand(2, 3, 6, 7), _rand(3, 3, 3))),
    "smoothness_map": (smoothness._smoothness_map,
                       lambda: (_rand(2, 4, 5, 3), _rand(2, 4, 5), torch.tensor([10.0, 0.1, 0.1], **DOUBLE))),
    "upsample_concat": (upsample._upsample_concat, lambda: (_rand(2, 3, 4, 5), _rand(2, 6, 8, 2))),
}
# the backward ops, with the forward inputs (no grad) and a gradient of the forward output's shape
BACKWARD_CASES = {
    "batch_norm_relu_backward": (batchnorm._batch_norm_relu_backward,
                                 lambda: (_rand(30, 4), _rand(30, 4), _rand(5, 4))),
    "channel_gate_backward": (gate._channel_gate_backward, lambda: (_rand(2, 12, 4), _rand(2, 12, 4), _rand(2, 4))),
    "cfa_mosaic_backward": (cfa._cfa_mosaic_backward,
                            lambda: (_rand(2, 3, 5, 6), _rand(2, 2, 3), _rand(2, 1, 5, 6), True)),
    "poisson_gaussian_backward": (noise._poisson_gaussian_backward,
                                  lambda: (_rand(2, 1, 4, 5), _rand(1), _rand(1), _seeds(2), 0, _rand(2, 1, 4, 5))),
    "quantize_ste_backward": (quantize._quantize_ste_backward,
                              lambda: (_rand(2, 12), torch.ones(2, **DOUBLE), _rand(2, 12))),
    "sensor_capture_backward": (sensor._sensor_capture_backward,
                                lambda: (_rand(2, 3, 4, 6), _rand(2, 2, 3), _rand(1), _rand(1),
                                         torch.ones(1, **DOUBLE), _seeds(2), 0, 1, 1023, _rand(2, 1, 4, 6), True)),
    "psf_conv_backward_image": (psf._psf_backward_image,
                                lambda: (_rand(2, 3, 6, 7), psf.node_cells(_rand(3, 3, 2, 3, 3)), 3, 2)),
    "psf_conv_backward_cells": (psf._psf_backward_cells,
                                lambda: (_rand(2, 3, 6, 7), _rand(2, 3, 6, 7), psf.node_cells(_rand(3, 3, 2, 3, 3)),
                                         3, 2)),
    "softmax_cross_entropy_backward": (cross_entropy._softmax_cross_entropy_backward,
                                       lambda: (_rand(2, 4, 5, 3), torch.randint(0, 4, (2, 5, 3), dtype=torch.int32),
                                                torch.ones(4, **DOUBLE), 255, _rand(2, 4, 5, 3), _rand(2, 5, 3),
                                                torch.float64)),
    "smoothness_map_backward": (smoothness._smoothness_map_backward,
                                lambda: (_rand(2, 4, 5, 3), _rand(2, 4, 5), torch.tensor([10.0, 0.1, 0.1], **DOUBLE),
                                         _rand(2, 4, 5))),
    "upsample_concat_backward": (upsample._upsample_concat_backward, lambda: (_rand(2, 6, 8, 7), 5)),
}


def _to(value, device):
    if isinstance(value, torch.Tensor):
        return value.detach().to(device).requires_grad_(value.requires_grad and value.is_leaf)
    return value


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("name", sorted(CASES) + sorted(BACKWARD_CASES))
def test_opcheck(name, device):
    op, make_inputs = {**CASES, **BACKWARD_CASES}[name]
    inputs = [_to(x, device) for x in make_inputs()]
    if name in BACKWARD_CASES:  # backward ops are once differentiable: no inputs that take gradients
        inputs = [x.detach() if isinstance(x, torch.Tensor) else x for x in inputs]
    results = torch.library.opcheck(op.op, inputs)
    assert set(results.values()) == {"SUCCESS"}, results


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("preset", ["camvid_codesign", None])
def test_camera_compiles_without_graph_breaks(preset, device):
    """The ops trace as single nodes through their fake implementations: no graph break, except the one a learnable
    lens takes on purpose (its PSF grid renders eagerly: complex FFTs)."""
    overrides = [] if preset else ["optics.enabled=true", "optics.method=direct"]
    torch.manual_seed(0)
    camera = Camera.from_config(load_config(preset, overrides)).train().to(device)
    learnable_lens = camera.optics.learnable
    torch._dynamo.reset()
    explanation = torch._dynamo.explain(camera)(torch.rand(2, 3, 16, 20, device=device))
    assert not explanation.break_reasons  # the disabled lens splits the graph without a break reason
    assert explanation.graph_count == 1 or learnable_lens
    torch._dynamo.reset()
    compiled = torch.compile(camera, backend="aot_eager", fullgraph=not learnable_lens)
    radiance = torch.rand(2, 3, 16, 20, device=device, requires_grad=True)
    counter = camera.noise.seed_counter.clone()  # (explain ran the camera once)
    eager = camera(radiance)
    (eager_grad,) = torch.autograd.grad(eager.square().sum(), radiance)
    camera.noise.seed_counter.copy_(counter)  # the same noise draw
    traced = compiled(radiance)
    (traced_grad,) = torch.autograd.grad(traced.square().sum(), radiance)
    assert torch.equal(camera.noise.seed_counter, counter + 2)
    torch.testing.assert_close(traced, eager)
    torch.testing.assert_close(traced_grad, eager_grad)
