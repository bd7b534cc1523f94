import pytest
import torch
import torch.nn.functional as F

from tests.conftest import assert_matches_reference, device_params
from warpsense.ops import psf_conv
from warpsense.ops.psf import psf_conv_fft
from warpsense.ops.reference import bilinear_node_weights, psf_conv_reference


def random_psf(channels, grid_y, grid_x, size, dtype=torch.float64, device="cpu"):
    psf = torch.rand(channels, grid_y, grid_x, size, size, dtype=dtype, device=device) + 0.05
    return psf / psf.sum(dim=(-2, -1), keepdim=True)


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    out = psf_conv(torch.rand(1, 3, 8, 9, device=device), random_psf(3, 2, 2, 3, torch.float32, device))
    assert out.shape == (1, 3, 8, 9) and out.device.type == device


def test_exception():
    with pytest.raises(ValueError, match="K odd"):
        psf_conv(torch.rand(1, 3, 8, 8), torch.rand(3, 1, 1, 4, 4))
    with pytest.raises(ValueError, match="channels"):
        psf_conv(torch.rand(1, 2, 8, 8), torch.rand(3, 1, 1, 3, 3))
    with pytest.raises(ValueError, match="method"):
        psf_conv(torch.rand(1, 3, 8, 8), torch.rand(3, 1, 1, 3, 3), method="magic")


@pytest.mark.parametrize("shape,grid,size", [((2, 1, 5, 7), (1, 1), 3), ((1, 3, 9, 6), (3, 2), 5),
                                             ((1, 1, 4, 4), (2, 2), 7)])
def test_cardinality(shape, grid, size):
    assert psf_conv(torch.rand(shape), random_psf(shape[1], *grid, size, torch.float32)).shape == shape


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("grid", [(1, 1), (2, 3), (3, 3)])
def test_feature_vs_reference(device, grid):
    image = torch.rand(2, 3, 11, 13, dtype=torch.float64, device=device)
    psf = random_psf(3, *grid, 5, device=device)
    torch.testing.assert_close(psf_conv(image, psf), psf_conv_reference(image, psf))


def test_invariant_equals_conv2d_with_flipped_kernel_float32():
    image = torch.rand(2, 3, 20, 24)
    psf = random_psf(3, 1, 1, 7, torch.float32)
    padded = F.pad(image, (3, 3, 3, 3), mode="replicate")
    expected = F.conv2d(padded, psf[:, 0, 0].flip(-1, -2).unsqueeze(1), groups=3)
    torch.testing.assert_close(psf_conv(image, psf), expected, rtol=1e-5, atol=1e-6)


def test_point_source_renders_as_psf_not_flipped():
    # asymmetric PSF; the delta sits on a node so the interpolated PSF is that node's PSF
    psf = random_psf(1, 3, 3, 5)
    image = torch.zeros(1, 1, 33, 33, dtype=torch.float64)
    y, x = 16, 16  # the middle node of a corner-aligned 3x3 grid: (16 + 0.5) / 33 = 1/2 of the field
    image[0, 0, y, x] = 1.0
    out = psf_conv(image, psf)
    torch.testing.assert_close(out[0, 0, y - 2 : y + 3, x - 2 : x + 3], psf[0, 1, 1])
    assert out.sum().item() == pytest.approx(1.0)


def test_point_source_between_nodes_renders_interpolated_psf():
    psf = random_psf(1, 2, 2, 3)
    image = torch.zeros(1, 1, 20, 20, dtype=torch.float64)
    image[0, 0, 8, 11] = 1.0
    weights = bilinear_node_weights(20, 20, 2, 2, torch.float64, "cpu")[:, :, 8, 11]
    expected = (weights[..., None, None] * psf[0]).sum(dim=(0, 1))
    torch.testing.assert_close(psf_conv(image, psf)[0, 0, 7:10, 10:13], expected)


def test_energy_conservation_away_from_borders():
    psf = random_psf(3, 3, 3, 5)
    image = torch.zeros(1, 3, 24, 24, dtype=torch.float64)
    image[..., 4:20, 4:20] = torch.rand(1, 3, 16, 16, dtype=torch.float64)
    torch.testing.assert_close(psf_conv(image, psf).sum(dim=(-2, -1)), image.sum(dim=(-2, -1)))


def test_gradcheck_image_and_psf():
    image = torch.rand(2, 2, 7, 8, dtype=torch.float64, requires_grad=True)
    psf = random_psf(2, 2, 3, 3).requires_grad_()
    assert torch.autograd.gradcheck(psf_conv, (image, psf))
    # kernel larger than the image: every border case of the clamped adjoint at once
    small = torch.rand(1, 1, 3, 2, dtype=torch.float64, requires_grad=True)
    big = random_psf(1, 2, 1, 5).requires_grad_()
    assert torch.autograd.gradcheck(psf_conv, (small, big))


@pytest.mark.parametrize("device", device_params())
def test_gradients_match_reference(device):
    image = torch.rand(2, 3, 12, 10, dtype=torch.float64, device=device, requires_grad=True)
    psf = random_psf(3, 3, 2, 5, device=device).requires_grad_()
    grad = torch.rand(2, 3, 10, 12, dtype=torch.float64, device=device).transpose(-1, -2)
    assert_matches_reference(psf_conv, psf_conv_reference, (image, psf), grad)


def test_fft_method_exact_for_invariant_psf():
    image = torch.rand(1, 3, 16, 18, dtype=torch.float64)
    psf = random_psf(3, 1, 1, 5)
    torch.testing.assert_close(psf_conv(image, psf, method="fft"), psf_conv(image, psf), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(psf_conv_fft(image, psf[:, 0, 0]), psf_conv_reference(image, psf), rtol=1e-10,
                               atol=1e-12)


def test_alternative_methods_error_versus_direct():
    """Stated error of the approximations on white noise (the worst case) through the 80 deg lens' 5x5 grid: the
    patch-wise method (seams, no blending) is off by ~19% of the image max at worst, FFT with the mean PSF by ~30%;
    neither is exact, and patch-wise is the closer of the two."""
    from warpsense.optics import Lens

    psf = Lens.from_json("phone_80deg").psf_grid()[:, :, :, 4:11, 4:11]
    psf = psf / psf.sum(dim=(-2, -1), keepdim=True)
    image = torch.rand(1, 3, 40, 50, dtype=torch.float64)
    exact = psf_conv(image, psf)
    approximations = {"patch": psf_conv(image, psf, method="patch"), "fft": psf_conv_fft(image, psf.mean(dim=(1, 2)))}
    errors = {m: (out - exact).abs().max().item() / exact.max().item() for m, out in approximations.items()}
    assert 1e-3 < errors["patch"] < 0.25 and 1e-3 < errors["fft"] < 0.4
    assert errors["patch"] < errors["fft"]


def test_inputs_not_mutated_and_autocast():
    image, psf = torch.rand(1, 3, 6, 6), random_psf(3, 1, 1, 3, torch.float32)
    copies = image.clone(), psf.clone()
    psf_conv(image, psf)
    assert torch.equal(image, copies[0]) and torch.equal(psf, copies[1])
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert psf_conv(image.bfloat16(), psf).dtype == torch.float32


@pytest.mark.cuda
@pytest.mark.parametrize("grid,size", [((1, 1), 15), ((5, 5), 15), ((3, 2), 7)])
def test_cuda_matches_reference_forward_and_backward(grid, size):
    image = torch.rand(2, 3, 40, 52, dtype=torch.float64, device="cuda", requires_grad=True)
    psf = random_psf(3, *grid, size, device="cuda").requires_grad_()
    grad = torch.rand(2, 3, 40, 52, dtype=torch.float64, device="cuda")
    assert_matches_reference(psf_conv, psf_conv_reference, (image, psf), grad)


@pytest.mark.parametrize("method", ["auto", "direct", "conv2d", "fft"])
def test_invariant_methods_agree(method):
    image = torch.rand(2, 3, 14, 17, dtype=torch.float64)
    psf = random_psf(3, 1, 1, 5)
    torch.testing.assert_close(psf_conv(image, psf, method=method), psf_conv_reference(image, psf))


@pytest.mark.parametrize("method", ["conv2d", "fft"])
def test_invariant_only_methods_refuse_a_grid(method):
    with pytest.raises(ValueError, match="1x1 grid"):
        psf_conv(torch.rand(1, 3, 8, 8), random_psf(3, 2, 2, 3, torch.float32), method=method)


@pytest.mark.parametrize("method", ["direct", "conv2d", "fft"])
def test_nan_stays_local(method):
    image = torch.rand(1, 1, 20, 20, dtype=torch.float64)
    image[0, 0, 10, 10] = float("nan")
    out = psf_conv(image, random_psf(1, 1, 1, 3), method=method)
    assert out[0, 0, 9:12, 9:12].isnan().all()
    assert out.isnan().sum() == 9


def test_fft_high_dynamic_range_documented_limit():
    """float64 FFT keeps a 1e-6 region beside a 1e3 one to 1e-5 relative; auto never picks FFT (it loses the dark
    side in float32: rounding is relative to the brightest pixel). An FFT's rounding error is a few float64 ulps of
    the brightest pixel, ~1e-12 here, i.e. 1e-6 of the dark side: how many ulps depends on the FFT library's code
    path for the CPU (2.4e-6 measured on one machine, under 1e-6 on another); float32 would be 1e-4, 100x off."""
    image = torch.full((1, 1, 32, 32), 1e-6, dtype=torch.float64)
    image[..., :, :16] = 1e3
    psf = random_psf(1, 1, 1, 3)
    exact = psf_conv_reference(image, psf)
    dark = (slice(None), slice(None), slice(None), slice(20, None))
    torch.testing.assert_close(psf_conv(image, psf, "fft")[dark], exact[dark], rtol=1e-5, atol=0)
    torch.testing.assert_close(psf_conv(image.float(), psf.float(), "auto")[dark], exact[dark].float(), rtol=1e-5,
                               atol=0)


def test_patch_more_nodes_than_pixels_and_autocast_dtype():
    image = torch.rand(1, 3, 4, 5)
    out = psf_conv(image, random_psf(3, 7, 9, 3, torch.float32), method="patch")
    assert out.shape == image.shape and torch.isfinite(out).all()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert psf_conv(image, random_psf(3, 2, 2, 3, torch.float32), method="patch").dtype == torch.float32


@pytest.mark.parametrize("grid", [(3, 0, 0, 5, 5), (3, 0, 2, 5, 5), (3, 2, 0, 5, 5), (3, 1, 1, 0, 0)])
def test_exception_empty_grid(grid):
    with pytest.raises(ValueError, match="non-empty"):
        psf_conv(torch.rand(1, 3, 8, 8), torch.rand(grid))


def test_exception_types_and_devices():
    with pytest.raises(TypeError, match="torch.Tensor"):
        psf_conv(torch.rand(1, 3, 8, 8).numpy(), random_psf(3, 1, 1, 3))
    with pytest.raises(TypeError, match="floating"):
        psf_conv(torch.ones(1, 3, 8, 8, dtype=torch.int32), random_psf(3, 1, 1, 3))


def test_output_dtype_follows_image():
    assert psf_conv(torch.rand(1, 3, 8, 8), random_psf(3, 2, 2, 3)).dtype == torch.float32


def test_grid_covers_corners():
    """The corner pixel is blurred with (almost exactly) the corner node's PSF: the grid is not clamped at the
    outer tile centres any more (issue 12, item 1)."""
    from warpsense.ops.psf import node_axis

    cell, fraction, bounds = node_axis(100, 5)
    assert cell[0] == 0 and fraction[0] == pytest.approx(0.5 / 100 * 4)
    assert cell[-1] == 3 and fraction[-1] == pytest.approx(1 - 0.5 / 100 * 4)
    assert bounds.tolist() == [0, 25, 50, 75, 100]
    weights = bilinear_node_weights(100, 100, 5, 5, torch.float64, "cpu")
    assert weights[0, 0, 0, 0] > 0.96 and weights[-1, -1, -1, -1] > 0.96
    torch.testing.assert_close(weights.sum(dim=(0, 1)), torch.ones(100, 100, dtype=torch.float64))


@pytest.mark.parametrize("device", device_params())
def test_gradients_match_reference_dense_grid(device):
    """More nodes than a cell's width in pixels, rows split across lanes."""
    image = torch.rand(2, 1, 9, 11, dtype=torch.float64, device=device, requires_grad=True)
    psf = random_psf(1, 6, 7, 3, device=device).requires_grad_()
    grad = torch.rand(2, 1, 9, 11, dtype=torch.float64, device=device)
    assert_matches_reference(psf_conv, psf_conv_reference, (image, psf), grad)


@pytest.mark.parametrize("staged", [True, False])
@pytest.mark.parametrize(("height", "width", "grid"), [(1, 1, 3), (1, 4, 3), (4, 1, 3), (2, 3, 6)])
def test_psf_gradient_where_an_axis_has_fewer_pixels_than_cells(staged, height, width, grid, monkeypatch):
    """An axis of fewer pixels than half its cells leaves its first cell empty: the border copies of pixel 0 belong
    to pixel 0's cell (as the forward reads them), not to the empty first cell (the PSF gradient was off by 0.1-1.1
    of its size)."""
    from warpsense.ops import psf as psf_module

    if not staged:
        monkeypatch.setattr(psf_module, "STAGED_BYTES", 0)
    image = torch.rand(1, 1, height, width, dtype=torch.float64, requires_grad=True)
    psf = random_psf(1, grid, grid, 7).requires_grad_()
    grad = torch.rand(1, 1, height, width, dtype=torch.float64)
    assert_matches_reference(psf_conv, psf_conv_reference, (image, psf), grad)


@pytest.mark.parametrize("staged", [True, False])
def test_psf_gradient_rows_split_into_chunks(staged, monkeypatch):
    """The GPU launch splits each cell's rows (and, unstaged, its columns) over several blocks or lanes; force
    that split on the CPU, for the staged PSF adjoint and for the one that stages nothing (large PSFs)."""
    from warpsense.ops import psf as psf_module

    monkeypatch.setitem(psf_module._THREADS_TARGET, "cpu", 10_000)
    if not staged:
        monkeypatch.setattr(psf_module, "STAGED_BYTES", 0)
    chunks = psf_module._chunks
    monkeypatch.setattr(psf_module, "_chunks", lambda wanted, rows, cols: chunks(wanted, rows, cols, min_cols=2))
    assert psf_module._chunks(10, 5, 9) == (5, 2)  # rows and columns both split
    image = torch.rand(2, 2, 13, 10, dtype=torch.float64, requires_grad=True)
    psf = random_psf(2, 3, 2, 5).requires_grad_()
    grad = torch.rand(2, 2, 13, 10, dtype=torch.float64)
    assert_matches_reference(psf_conv, psf_conv_reference, (image, psf), grad)


@pytest.mark.parametrize(("shape", "grid", "size"), [((1, 2, 21, 150), (3, 2), 5), ((1, 1, 19, 23), (2, 3), 15)])
def test_staged_psf_gradient_steps_chunks_and_tap_groups(shape, grid, size):
    """The staged PSF adjoint where a cell is wider than a block's STAGED_COLS (column chunks), taller than its
    STAGED_ROWS (several steps of tiles), and where a tap row takes two groups of TAPS taps (K = 15)."""
    from warpsense.kernels import psf as kernels

    padded_cols = shape[3] + size - 1
    assert padded_cols / (grid[1] - 1) > kernels.STAGED_COLS or size > kernels.TAPS
    assert (shape[2] + size - 1) / (grid[0] - 1) > kernels.STAGED_ROWS
    image = torch.rand(*shape, dtype=torch.float64)
    psf = random_psf(shape[1], *grid, size).requires_grad_()
    grad = torch.rand(*shape, dtype=torch.float64)
    ours = torch.autograd.grad((psf_conv(image, psf, "direct") * grad).sum(), psf)[0]
    expected = torch.autograd.grad((psf_conv_reference(image, psf) * grad).sum(), psf)[0]
    torch.testing.assert_close(ours, expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("device", device_params())
def test_gradcheck_cudnn_invariant_with_warp_psf_gradient(device):
    """The CUDA conv2d path (cuDNN forward and image gradient, the Warp kernel for the PSF gradient), called
    directly so that the CPU suite checks it too: float64 gradcheck and equal to the reference."""
    from warpsense.ops.psf import _psf_conv_cudnn

    image = torch.rand(2, 2, 7, 9, dtype=torch.float64, device=device, requires_grad=True)
    kernel = random_psf(2, 1, 1, 5, device=device)[:, 0, 0].requires_grad_()
    assert torch.autograd.gradcheck(_psf_conv_cudnn, (image, kernel))
    grad = torch.rand(2, 2, 7, 9, dtype=torch.float64, device=device)
    assert_matches_reference(_psf_conv_cudnn, lambda x, k: psf_conv_reference(x, k[:, None, None]), (image, kernel),
                             grad)


@pytest.mark.parametrize("grid,size", [((1, 1), 5), ((3, 4), 7), ((2, 2), 31)])
def test_fft_blend_reference_equals_the_direct_blend(grid, size):
    """The accuracy report's wide-kernel reference (node convolutions by FFT) against the direct blend, including a
    kernel wider than the image."""
    from warpsense.ops.reference import psf_conv_blend_fft

    image = torch.rand(2, 3, 13, 22, dtype=torch.float64)
    psf = torch.rand(3, *grid, size, size, dtype=torch.float64)
    torch.testing.assert_close(psf_conv_blend_fft(image, psf), psf_conv_reference(image, psf), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("parts", [1, 4, 15])
@pytest.mark.parametrize("height,grid", [(60, 3), (24, 5)])
def test_windows_across_cell_boundaries_match_reference(device, height, grid, parts, monkeypatch):
    """K = 15, as in the recipe: each forward thread's window of K + ROWS - 1 rows lies in one cell, in two, or (in
    cells shorter than the window) in more, and each image-adjoint thread's ROWS rows in one cell or two. Every
    case is present in these shapes (checked from the row tables) and equals the reference, with the forward's
    tap columns in one part and split into 4 (uneven) and 15 parts (a launch too small to fill a GPU)."""
    from warpsense.kernels.psf import ROWS
    from warpsense.ops import psf as psf_module
    from warpsense.ops.psf import source_axis

    monkeypatch.setattr(psf_module, "_forward_parts", lambda threads, size, device: parts)

    size = 15
    cell = source_axis(height, grid, size // 2, ROWS - 1)[0]
    window = size + ROWS - 1
    spans = {int(cell[y + window - 1] - cell[y]) for y in range(0, height, ROWS)}
    assert spans == ({0, 1} if grid == 3 else {2, 3})  # one cell and two (60 rows); more than two (24 rows)
    image = torch.rand(1, 2, height, 20, dtype=torch.float64, device=device, requires_grad=True)
    psf = random_psf(2, grid, 2, size, device=device).requires_grad_()
    grad = torch.rand(1, 2, height, 20, dtype=torch.float64, device=device)
    assert_matches_reference(psf_conv, psf_conv_reference, (image, psf), grad)


def test_forward_parts_fill_the_device():
    """A launch that fills a GPU keeps every tap column in one part; a batch of one splits them, at most K ways;
    a CPU never splits (one thread)."""
    from warpsense.ops.psf import _forward_parts

    cuda = torch.device("cuda")
    assert _forward_parts(16 * 3 * 44 * 480, 15, cuda) == 1  # the recipe's training batch
    assert _forward_parts(3 * 24 * 640, 15, cuda) == 3  # one 192 x 640 frame
    assert _forward_parts(10, 15, cuda) == 15
    assert _forward_parts(10, 15, torch.device("cpu")) == 1


def test_exception_too_large_for_int32_offsets():
    """The kernels address their padded planes by int32 element offsets: an image past 2**31 padded elements is a
    clear error naming the shape, before anything is allocated (a meta tensor here)."""
    from warpsense.ops.psf import _check_offsets

    _check_offsets(torch.empty(16, 3, 352, 480, device="meta"), 7)  # the recipe's batch
    with pytest.raises(ValueError, match=r"psf_conv: image \(64, 3, 4000, 3000\) .* int32 offsets"):
        _check_offsets(torch.empty(64, 3, 4000, 3000, device="meta"), 7)


def test_auto_takes_cudnn_alone_for_an_image_past_the_kernels_offsets(monkeypatch):
    """For one PSF, `auto` times its exact paths once per shape on CUDA; an image past the Warp kernels' int32
    offsets leaves cuDNN's conv2d alone (timing the Warp paths would raise), without timing anything."""
    from warpsense.ops import psf as psf_module

    monkeypatch.setattr(psf_module, "_time_path", lambda *a, **k: pytest.fail("timed a path"))
    monkeypatch.setattr(torch.cuda, "is_current_stream_capturing", lambda: False)
    # a stand-in for a CUDA image of that shape (nothing of it is read but these attributes)
    large = type("LargeCudaImage", (), {"shape": torch.Size((64, 3, 4000, 3000)), "dtype": torch.float32,
                                        "requires_grad": False, "device": torch.device("cuda")})()
    assert psf_module._fastest_invariant(large, torch.empty(3, 1, 1, 15, 15)) == "conv2d"


def test_cells_start_on_a_16_byte_boundary():
    """The kernels load a cell's four node values in one 16-byte load on CUDA: a view that starts elsewhere is
    copied (same values), an aligned tensor passed as it is."""
    from warpsense.ops.psf import _nodes

    storage = torch.rand(1 + 3 * 4 * 5 * 5 * 4)
    view = storage[1:].view(3, 4, 5, 5, 4)
    assert view.data_ptr() % 16 == 4
    nodes = _nodes(view).tensor
    assert nodes.data_ptr() % 16 == 0 and torch.equal(nodes, view)
    aligned = torch.rand(3, 4, 5, 5, 4)
    assert _nodes(aligned).tensor is aligned



@pytest.mark.parametrize("device", device_params())
def test_gradients_match_reference_for_channels_last_gradients_of_one_image(device):
    """The kernels read their planes by flat offset: a channels-last gradient of a batch of one padded and reshaped
    to a strided view, which they read as contiguous (gradients summed to about half their values). Both
    gradients against the reference for that layout, the image's too."""
    image = torch.rand(1, 3, 20, 24, dtype=torch.float64, device=device, requires_grad=True)
    psf = random_psf(3, 2, 2, 5, device=device).requires_grad_()
    grad = torch.rand(1, 3, 20, 24, dtype=torch.float64, device=device).to(memory_format=torch.channels_last)
    assert_matches_reference(psf_conv, psf_conv_reference, (image, psf), grad)
    channels_last = image.detach().to(memory_format=torch.channels_last).requires_grad_()
    assert_matches_reference(psf_conv, psf_conv_reference, (channels_last, psf), grad)
