"""The torch <-> Warp helper (`warpsense.ops._warp`): which calls skip the custom op's dispatcher (`WarpOp`), the
recorded launches' parameters (set again only when they change), the kept scalar tensors, the psf op's kept node
cells, and forward-mode AD refused with a clear error."""

import gc

import pytest
import torch
from torch._subclasses.fake_tensor import FakeTensorMode
from torch.autograd import forward_ad

from tests.conftest import device_params
from warpsense.ops import _warp, batchnorm, psf, psf_conv, quantize_ste
from warpsense.ops.reference import psf_conv_reference, quantize_reference
from warpsense.ops.sensor import sensor_capture


@pytest.fixture
def op_calls(monkeypatch):
    """Calls of the psf op that went through its torch.library custom op (the dispatcher)."""
    calls = []
    op = psf._psf_conv_cells.op

    def counted(*args, **kwargs):
        calls.append(args)
        return op(*args, **kwargs)

    monkeypatch.setattr(psf._psf_conv_cells, "op", counted)
    return calls


def _inputs(device="cpu", grad=False):
    torch.manual_seed(0)
    image = torch.rand(1, 3, 7, 9, dtype=torch.float64, device=device, requires_grad=grad)
    kernel = torch.rand(3, 2, 2, 3, 3, dtype=torch.float64, device=device)
    return image, kernel / kernel.sum(dim=(-2, -1), keepdim=True)


@pytest.mark.parametrize("device", device_params())
def test_feature_direct_call_without_gradients(op_calls, device):
    """No gradient to track: the implementation runs directly, with the op's result."""
    image, kernel = _inputs(device, grad=True)
    with torch.no_grad():
        out = psf_conv(image, kernel, method="direct")
    assert not op_calls and out.grad_fn is None
    torch.testing.assert_close(out, psf_conv_reference(image.detach(), kernel))
    out = psf_conv(image.detach(), kernel, method="direct")  # gradients on, but no input requires one
    assert not op_calls
    torch.testing.assert_close(out, psf_conv_reference(image.detach(), kernel))


def test_feature_dispatcher_where_torch_needs_it(op_calls):
    """Autograd, fake tensors, the profiler and functorch see the custom op."""
    image, kernel = _inputs(grad=True)
    out = psf_conv(image, kernel, method="direct")
    assert len(op_calls) == 1 and out.grad_fn is not None
    (grad,) = torch.autograd.grad(out.square().sum(), image)
    (expected,) = torch.autograd.grad(psf_conv_reference(image, kernel).square().sum(), image)
    torch.testing.assert_close(grad, expected)
    mode = FakeTensorMode()
    fake_image, fake_kernel = mode.from_tensor(image.detach()), mode.from_tensor(kernel)
    with mode:
        fake = psf_conv(fake_image, fake_kernel, method="direct")
    assert len(op_calls) == 2 and fake.shape == image.shape
    with torch.no_grad(), torch.profiler.profile() as profile:
        psf_conv(image, kernel, method="direct")
    assert len(op_calls) == 3
    assert any(event.name == "warpsense::psf_conv" for event in profile.events())
    seen = []
    torch.vmap(lambda x: seen.append(_warp.WarpOp.direct_call((x,))) or x)(image.detach())
    assert seen == [False]


@pytest.mark.parametrize("method", ["direct", "conv2d", "auto"])
def test_feature_meta_tensors_take_the_fake_implementation(op_calls, method):
    """Meta tensors (shape inference, a model built on the meta device) give the shapes without running a kernel:
    the direct call handed them to Warp ("Unsupported Torch device type meta"), and psf_conv's autocast guard
    refused the meta device ("unsupported scalarType")."""
    image = torch.empty(2, 3, 5, 7, device="meta")
    for grid in [(1, 1)] if method == "conv2d" else [(1, 1), (2, 3)]:
        out = psf_conv(image, torch.empty(3, *grid, 5, 5, device="meta"), method=method)
        assert out.shape == image.shape and out.is_meta
    assert quantize_ste(image, 8).is_meta
    raw = sensor_capture(image, torch.empty(2, 2, 3, device="meta"), 0.01, 0.001, 0, 10)
    assert raw.shape == (2, 1, 5, 7) and raw.is_meta


def test_feature_jit_trace_records_the_op():
    """torch.jit.trace records the custom op, not what its implementation runs around the kernel (a direct call
    would leave the kernel out of the trace)."""
    raw = torch.rand(2, 1, 4, 5)
    with torch.no_grad():
        traced = torch.jit.trace(lambda x: quantize_ste(x, 4), raw)
    assert "warpsense::quantize_ste" in str(traced.graph)
    other = torch.rand(2, 1, 4, 5)
    torch.testing.assert_close(traced(other), quantize_reference(other, 4))


def test_module_mutating_op_always_dispatches():
    """An op that writes its arguments (the running statistics) keeps the dispatcher, which tracks versions."""
    assert not batchnorm._update_running.direct and psf._psf_conv_cells.direct
    running = torch.zeros(4)
    version = running._version
    with torch.no_grad():
        batchnorm._update_running(torch.rand(5, 4), 30, 0.1, running, torch.ones(4))
    assert running._version > version


def _dual(f, x, t):
    with forward_ad.dual_level():
        return forward_ad.unpack_dual(f(forward_ad.make_dual(x, t))).tangent


FORWARD_MODE = {
    "dual tensor": lambda f, x, t: _dual(f, x, t),
    "torch.func.jvp": lambda f, x, t: torch.func.jvp(f, (x,), (t,))[1],
    "jacfwd": lambda f, x, t: torch.func.jacfwd(f)(x),
    "jvp over vmap": lambda f, x, t: torch.func.jvp(torch.func.vmap(f), (x[None],), (t[None],))[1],
    "vmap over jvp": lambda f, x, t: torch.func.vmap(lambda y, u: torch.func.jvp(f, (y,), (u,))[1])(x[None], t[None]),
    "hessian": lambda f, x, t: torch.func.hessian(lambda y: f(y).square().sum())(x),
}


@pytest.mark.parametrize("transform", list(FORWARD_MODE))
@pytest.mark.parametrize("argument", ["image", "kernel"])
def test_exception_forward_mode_ad_refused(transform, argument):
    """The ops have reverse-mode formulas only: a forward-mode tangent reaching one is an error naming the op (torch
    itself gave no tangent under a dual level and a zero one under torch.func.jvp)."""
    image, kernel = _inputs()
    f = (lambda x: psf_conv(x, kernel, method="direct")) if argument == "image" else (
        lambda k: psf_conv(image, k, method="direct"))
    x = image if argument == "image" else kernel
    with pytest.raises(NotImplementedError, match="warpsense::psf_conv: forward-mode AD .* not implemented"):
        FORWARD_MODE[transform](f, x, torch.rand_like(x))


@pytest.mark.parametrize("transform", ["torch.func.jvp", "jacfwd"])
def test_feature_forward_mode_ad_around_a_constant(transform):
    """An op whose inputs carry no tangent runs inside forward-mode AD (even after the functional's own casts wrap
    its inputs at the jvp level): the derivative is the one the rest of the function gives. (Nested beneath another
    transform, as in hessian, such a wrapped constant is refused too: `forward_tangents` cannot read it there.)"""
    image, kernel = _inputs()
    scale = psf_conv_reference(image, kernel).sum()
    x = torch.rand(3, dtype=torch.float64)
    f = lambda y: y * psf_conv(image, kernel, method="direct").sum()  # noqa: E731
    torch.testing.assert_close(FORWARD_MODE[transform](f, x, torch.ones(3, dtype=torch.float64)),
                               {"torch.func.jvp": scale * torch.ones(3, dtype=torch.float64),
                                "jacfwd": scale * torch.eye(3, dtype=torch.float64)}[transform])
    with forward_ad.dual_level():  # a dual level open, no dual input
        torch.testing.assert_close(psf_conv(image, kernel, method="direct"), psf_conv_reference(image, kernel))


def test_feature_launch_sets_changed_parameters_only(monkeypatch):
    """A parameter holding the same pointer, shape and strides is not rebuilt; new contents at the same pointer,
    other tensors and other scalars are seen."""
    built = []
    build = _warp._array_ctype
    monkeypatch.setattr(_warp, "_array_ctype", lambda value: built.append(value) or build(value))
    raw = torch.rand(2, 1, 5, 6, dtype=torch.float64)
    out = quantize_ste(raw, 4)
    first = len(built)
    torch.testing.assert_close(out, quantize_reference(raw, 4))
    raw.mul_(0.5)  # same pointer, new contents
    torch.testing.assert_close(quantize_ste(raw, 4), quantize_reference(raw, 4))
    torch.testing.assert_close(quantize_ste(raw, 6), quantize_reference(raw, 6))  # another scalar
    other = torch.rand(2, 1, 5, 6, dtype=torch.float64)
    torch.testing.assert_close(quantize_ste(other, 6), quantize_reference(other, 6))  # another tensor
    assert 0 < len(built) - first < 3 * first  # the repeated calls rebuilt fewer structs than they passed


def test_feature_kept_cells():
    """The node cells of a PSF without gradients are kept while it is unchanged; an in-place change, a PSF that
    takes gradients or a dropped PSF are handled."""
    image, kernel = _inputs()
    cells = psf._kept_cells(kernel)
    assert psf._kept_cells(kernel) is cells
    torch.testing.assert_close(cells, psf.node_cells(kernel), rtol=0, atol=0)
    kernel[1].mul_(0.5)  # in place: the version counter moves
    torch.testing.assert_close(psf_conv(image, kernel, method="direct"), psf_conv_reference(image, kernel))
    assert psf._kept_cells(kernel) is not cells
    learnable = kernel.clone().requires_grad_()
    fresh = psf._kept_cells(learnable)
    assert fresh.grad_fn is not None and psf._kept_cells(learnable) is not fresh
    key = id(kernel)
    assert key in psf._CELLS
    del kernel
    gc.collect()
    assert key not in psf._CELLS


def test_feature_kept_cells_not_from_inference_mode():
    """Cells made under inference mode are not kept: a later training step with the same fixed PSF saves its cells
    for the backward, which an inference tensor refuses."""
    image, kernel = _inputs(grad=True)
    with torch.inference_mode():
        psf_conv(image.detach(), kernel, method="direct")
    assert id(kernel) not in psf._CELLS
    out = psf_conv(image, kernel, method="direct")
    (grad,) = torch.autograd.grad(out.sum(), image)
    (expected,) = torch.autograd.grad(psf_conv_reference(image, kernel).sum(), image)
    torch.testing.assert_close(grad, expected)


def test_feature_scalar_tensors_kept_in_plain_eager_only():
    """A Python number's tensor is one shared tensor per (value, dtype, device) in plain eager mode; inference mode
    and fake tensors make a new one each time."""
    like = torch.rand(3)
    first = _warp.scalar_tensor(0.25, like)
    assert _warp.scalar_tensor(0.25, like) is first and first.tolist() == [0.25]
    assert _warp.scalar_tensor(0.5, like) is not first
    assert _warp.scalar_tensor(0.25, like.double()).dtype == torch.float64
    with torch.inference_mode():
        made = _warp.scalar_tensor(0.25, like)
        assert made is not first and made.is_inference() and _warp.scalar_tensor(0.25, like) is not made
    mode = FakeTensorMode()
    fake_like = mode.from_tensor(like)
    with mode:
        assert _warp.scalar_tensor(0.25, fake_like) is not first


def test_feature_sensor_capture_after_inference_mode_trains():
    """A capture in inference mode first (its white level not kept), then one with gradients: the backward saves
    and uses its scalar arguments."""
    rgb, phi = torch.rand(1, 3, 4, 6, dtype=torch.float64), torch.rand(2, 2, 3, dtype=torch.float64)
    with torch.inference_mode():
        sensor_capture(rgb, phi, 0.01, 0.002, 3, 10, 0.75)
    rgb.requires_grad_()
    (grad,) = torch.autograd.grad(sensor_capture(rgb, phi, 0.01, 0.002, 3, 10, 0.75).sum(), rgb)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
