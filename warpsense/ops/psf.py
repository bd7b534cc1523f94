"""Spatially varying PSF convolution (Warp kernels as the custom ops warpsense::psf_conv and its two adjoints) and
its alternative methods.

PSF grid convention (one place: `node_axis`): the Gy x Gx nodes cover the whole field, corners included. Along an
axis of ``size`` pixels, node n sits at the normalised position n / (G - 1) of the field (0 and 1 are the image
edges), pixel q's centre at (q + 0.5) / size; between nodes the PSF is bilinear. G = 1 is the invariant case.
"""

from __future__ import annotations

import contextlib
import functools
import time
import weakref

import torch
import torch.nn.functional as F

from warpsense.choices import PSF_METHODS
from warpsense.kernels import psf as kernels
from warpsense.ops._warp import Vectors, launch, may_keep, prepare, save_inputs, warp_op
from warpsense.ops.arguments import check_same_device, check_tensor

_THREADS_TARGET = {"cuda": 1 << 18, "cpu": 1}  # threads the PSF-gradient launch aims for (fill a large GPU; serial CPU)
_FORWARD_THREADS = {"cuda": 1 << 17, "cpu": 1}  # threads below which the forward splits its tap columns


def _forward_parts(threads: int, size: int, device: torch.device) -> int:
    """Parts the forward splits the tap columns into: 1 when its launch has at least the device's
    `_FORWARD_THREADS`, else as many as it takes to reach them (a batch of one on a GPU), at most ``size``; the
    parts' outputs are summed (a fixed order: deterministic)."""
    wanted = _FORWARD_THREADS.get(device.type, 1)
    return max(1, min(size, -(-wanted // max(threads, 1))))


@functools.lru_cache(maxsize=64)
def _node_axis_cached(size: int, nodes: int, dtype: torch.dtype, device: torch.device):
    position = (torch.arange(size, dtype=torch.float64) + 0.5) / size * max(nodes - 1, 0)
    cell = position.floor().clamp(0, max(nodes - 2, 0))
    fraction = (position - cell) if nodes > 1 else torch.zeros(size, dtype=torch.float64)
    cells = max(nodes - 1, 1)
    bounds = torch.searchsorted(cell.contiguous(), torch.arange(cells + 1, dtype=torch.float64))
    bounds[-1] = size
    return (cell.to(torch.int32).to(device), fraction.to(dtype).to(device), bounds.to(torch.int32).to(device))


def node_axis(size: int, nodes: int, dtype=torch.float64, device="cpu"):
    """Bilinear coordinates of the pixels of one axis in a grid of ``nodes`` corner-aligned nodes.

    Returns:
        cell: int32 [size], the lower node of each pixel's cell (0 .. max(nodes - 2, 0)).
        fraction: [size] weight of the upper node, in [0, 1] (0 everywhere when nodes == 1).
        bounds: int32 [cells + 1], the first pixel of each cell; the last entry is ``size``.
    """
    return _node_axis_cached(int(size), int(nodes), dtype, torch.device(device))


def node_cells(psf: torch.Tensor) -> torch.Tensor:
    """[C, Gy, Gx, K, K] node PSFs -> [C, cells_y * cells_x, K, K, 4]: each grid cell's corner PSFs (00, 01, 10,
    11), so the kernels read a tap's four node values at once. Differentiable (slices: deterministic backward)."""
    channels, grid_y, grid_x, size, _ = psf.shape
    low_y, high_y = slice(0, max(grid_y - 1, 1)), slice(min(1, grid_y - 1), grid_y)
    low_x, high_x = slice(0, max(grid_x - 1, 1)), slice(min(1, grid_x - 1), grid_x)
    corners = [psf[:, low_y, low_x], psf[:, low_y, high_x], psf[:, high_y, low_x], psf[:, high_y, high_x]]
    cells = torch.stack(corners, dim=-1)
    return cells.reshape(channels, -1, size, size, 4).contiguous()


@functools.lru_cache(maxsize=64)
def _source_axis_cached(size: int, nodes: int, radius: int, extra: int, dtype: torch.dtype, device: torch.device):
    cell, fraction, _ = _node_axis_cached(size, nodes, dtype, torch.device("cpu"))
    clamped = (torch.arange(size + 2 * radius + extra) - radius).clamp(0, size - 1)
    cells = cell[clamped]
    # each cell's first padded source by the sources' own cells, as the forward reads them: a border copy belongs to
    # the cell of the pixel it copies, also where that is not the first or last cell (an axis of fewer pixels than
    # cells leaves cells empty; by the pixels' bounds shifted, the first copies went to an empty first cell)
    padded_bounds = torch.searchsorted(cells[:size + 2 * radius].contiguous(),
                                       torch.arange(max(nodes - 1, 1) + 1, dtype=cells.dtype))
    return cells.to(device), fraction[clamped].to(device), padded_bounds.to(torch.int32).to(device)


def source_axis(size: int, nodes: int, radius: int, extra: int, dtype=torch.float64, device="cpu"):
    """`node_axis` over the padded source coordinates the kernels use: source s of an axis padded by ``radius``
    (plus ``extra`` at the end) is pixel clamp(s - radius). Returns (cell, fraction) per padded source and each
    cell's first padded source (the cells in order, the last ending at size + 2 * radius; a border copy belongs to
    its pixel's cell)."""
    return _source_axis_cached(int(size), int(nodes), int(radius), int(extra), dtype, torch.device(device))


def _source_tables(image: torch.Tensor, grid_y: int, grid_x: int, radius: int):
    height, width = image.shape[-2:]
    rows = source_axis(height, grid_y, radius, kernels.ROWS - 1, image.dtype, image.device)
    cols = source_axis(width, grid_x, radius, 0, image.dtype, image.device)
    return rows, cols


def _padded_source(image: torch.Tensor, radius: int, extra: int = 0) -> torch.Tensor:
    """[B, C, H, W] -> [B*C, H + 2r + ROWS - 1 (+ extra), W + 2r], edge-replicated (the kernels' clamp-to-edge
    borders)."""
    batch, channels = image.shape[:2]
    padded = F.pad(image, (radius, radius, radius, radius + kernels.ROWS - 1 + extra), mode="replicate")
    # contiguous: the kernels read by flat offset (a channels-last pad of one image reshapes to a strided view)
    return padded.reshape(batch * channels, *padded.shape[-2:]).contiguous()


def _padded_gradient(grad_out: torch.Tensor, radius: int, dtype: torch.dtype, extra: int = 0) -> torch.Tensor:
    """[B, C, H, W] -> [B*C, H + 4r + ROWS - 1 (+ extra), W + 4r + TAPS - 1], zero-padded: the outputs beyond the
    image a source would reach contribute nothing."""
    batch, channels = grad_out.shape[:2]
    pad = 2 * radius
    padded = F.pad(grad_out.to(dtype), (pad, pad + kernels.TAPS - 1, pad, pad + kernels.ROWS - 1 + extra))
    return padded.reshape(batch * channels, *padded.shape[-2:]).contiguous()  # read by flat offset


FORWARD_BLOCK = kernels.FORWARD_BOUNDS[0]
"""Threads per block of the forward and image-adjoint launches (their kernels' launch bounds): blocks of 128 keep
more warps a multiprocessor than Warp's 256 for a kernel of many registers a thread (docs/benchmarks.md, PSF
convolution)."""
CELLS_BLOCK = 128
"""Threads per block of the PSF-adjoint launch: as the forward's, blocks of 128 never hold fewer warps a
multiprocessor than blocks of 256 for a kernel of many registers a thread (docs/benchmarks.md, PSF convolution)."""


def _nodes(cells: torch.Tensor) -> Vectors:
    """The cells as the kernels' 4-vectors: they load a 4-vector by its flat offset, in one 16-byte load on CUDA,
    so the tensor must be contiguous and start on a 16-byte boundary (a copy when a view is not)."""
    cells = cells.contiguous()
    if cells.data_ptr() % 16:
        cells = cells.clone()
    return Vectors(cells)


def _offsets_fit(shape, radius: int) -> bool:
    """Whether the kernels' int32 element offsets reach every element for an image of ``shape`` [B, C, H, W]: the
    largest plane (the image adjoint's zero-padded gradient) below 2**31 elements."""
    batch, channels, height, width = shape
    return batch * channels * (height + 4 * radius + kernels.ROWS - 1) * (width + 4 * radius + kernels.TAPS - 1) \
        < 2**31


def _check_offsets(image: torch.Tensor, radius: int) -> None:
    """`_offsets_fit`, or a one-line ValueError naming the shape (each kernel launcher calls it)."""
    if not _offsets_fit(image.shape, radius):
        raise ValueError(f"psf_conv: image {tuple(image.shape)} with a {2 * radius + 1}-tap PSF is too large for "
                         "the Warp kernels' int32 offsets (2**31 padded elements); split the batch, or use "
                         "method 'conv2d' or 'fft' for one PSF")


def _fold_padding(grad_source: torch.Tensor, radius: int) -> torch.Tensor:
    """Adjoint of edge-replicate padding: [N, H + 2r, W + 2r] -> [N, H, W], each border pixel collecting the
    gradient of its copies (slices and sums: deterministic)."""
    if radius == 0:
        return grad_source
    columns = grad_source[..., radius:-radius].clone()
    columns[..., 0] += grad_source[..., :radius].sum(-1)
    columns[..., -1] += grad_source[..., -radius:].sum(-1)
    rows = columns[:, radius:-radius].clone()
    rows[:, 0] += columns[:, :radius].sum(1)
    rows[:, -1] += columns[:, -radius:].sum(1)
    return rows


@warp_op("psf_conv_backward_image", lambda grad_out, cells, grid_y, grid_x: torch.empty_like(grad_out))
def _psf_backward_image(grad_out: torch.Tensor, cells: torch.Tensor, grid_y: int, grid_x: int) -> torch.Tensor:
    """The image adjoint: every padded source gathers the outputs it reached through its own PSF, then the
    padding folds back onto the border pixels."""
    batch, channels, height, width = grad_out.shape
    radius = cells.shape[2] // 2
    _check_offsets(grad_out, radius)
    rows, cols = _source_tables(grad_out, grid_y, grid_x, radius)
    padded_grad = _padded_gradient(grad_out, radius, cells.dtype)
    grad_source = padded_grad.new_empty(batch * channels, height + 2 * radius, width + 2 * radius)
    launch(kernels.psf_kernels(cells.shape[2]).backward_source,
           (batch * channels, -(-(height + 2 * radius) // kernels.ROWS), width + 2 * radius),
           [padded_grad, _nodes(cells), max(grid_x - 1, 1), rows[0], rows[1], cols[0], cols[1], grad_source],
           grad_out.device, threads_per_block=FORWARD_BLOCK)
    return _fold_padding(grad_source, radius).view(batch, channels, height, width)


def _chunks(wanted: int, rows: int, cols: int, min_cols: int = 32) -> tuple[int, int]:
    """Split a cell of about rows x cols sources into row and column chunks, about ``wanted`` in all, so that the
    PSF-gradient launch fills the device: rows first (whole rows keep the sliding window long), then columns in
    runs of at least ``min_cols``."""
    row_chunks = max(1, min(rows, wanted))
    col_chunks = max(1, min(-(-wanted // row_chunks), cols // min_cols))
    return row_chunks, col_chunks


@functools.lru_cache(maxsize=64)
def _widest_cell(width: int, grid_x: int, radius: int) -> int:
    """Padded source columns of the widest grid cell (the border cells take the padding), from the host's tables:
    no device read, so the launch can be captured in a CUDA graph."""
    bounds = source_axis(width, grid_x, radius, 0)[2]
    return int((bounds[1:] - bounds[:-1]).max())


STAGED_BYTES = 40 * 1024
"""Shared memory a block of the staged PSF adjoint may take (`kernels.psf.staged_tiles`); larger PSFs (K > 63 in
float32, K > 37 in float64) run `kernels.psf.psf_backward_cells`, which stages nothing."""


@warp_op("psf_conv_backward_cells", lambda image, grad_out, cells, grid_y, grid_x: torch.empty_like(cells))
def _psf_backward_cells(image: torch.Tensor, grad_out: torch.Tensor, cells: torch.Tensor, grid_y: int,
                        grid_x: int) -> torch.Tensor:
    """The PSF adjoint: per (image, cell, chunk of sources) partial sums, then one deterministic sum."""
    batch, channels, height, width = image.shape
    size = cells.shape[2]
    radius = size // 2
    _check_offsets(image, radius)
    cells_y, cells_x = max(grid_y - 1, 1), max(grid_x - 1, 1)
    rows, cols = _source_tables(image, grid_y, grid_x, radius)
    cell_rows, cell_cols = -(-(height + 2 * radius) // cells_y), -(-(width + 2 * radius) // cells_x)
    target = _THREADS_TARGET.get(image.device.type, 1)
    tiles = kernels.staged_tiles(size)
    if tiles.elements * image.element_size() <= STAGED_BYTES:
        col_chunks = -(-_widest_cell(width, grid_x, radius) // kernels.STAGED_COLS)
        planes = batch * channels * cells_y * cells_x * col_chunks
        row_splits = max(1, min(-(-cell_rows // kernels.STAGED_ROWS), -(-target // (tiles.threads * planes))))
        partials = image.new_empty(batch * row_splits * col_chunks, channels, cells_y * cells_x, size * size, 4)
        # rows below each plane, so that every tile a block loads whole and unchecked lies inside its plane: the
        # columns of a tile's last rows run on past a row's end, and the gradient's tile one row past the plane's
        source = _padded_source(image, radius, -(-kernels.STAGED_COLS // (width + 2 * radius)))
        padded_grad = _padded_gradient(grad_out, radius, image.dtype,
                                       1 + -(-tiles.cols // (width + 4 * radius + kernels.TAPS - 1)))
        fractions = source_axis(width, grid_x, radius, kernels.STAGED_COLS, image.dtype, image.device)[1]
        launch(kernels.psf_cells_staged(size), (planes * row_splits, tiles.threads),
               [source.view(-1, source.shape[-1]), source.shape[1], padded_grad.view(-1, padded_grad.shape[-1]),
                padded_grad.shape[1], rows[2], rows[1], cols[2], fractions, channels, cells_y, cells_x, row_splits,
                col_chunks, Vectors(partials)], image.device, threads_per_block=tiles.threads)
        return partials.sum(dim=0).view_as(cells)
    source, padded_grad = _padded_source(image, radius), _padded_gradient(grad_out, radius, image.dtype)
    tap_groups = channels * size * -(-size // kernels.TAPS)
    lanes = batch * cells_y * cells_x
    row_chunks, col_chunks = _chunks(-(-target // (tap_groups * lanes)), cell_rows, cell_cols)
    partials = image.new_empty(batch * row_chunks * col_chunks, channels, cells_y * cells_x, size * size, 4)
    launch(kernels.psf_backward_cells, (lanes * row_chunks * col_chunks, tap_groups),
           [source, padded_grad, rows[2], rows[1], cols[2], cols[1], size, channels, cells_y, cells_x, row_chunks,
            col_chunks, Vectors(partials)], image.device, threads_per_block=CELLS_BLOCK)
    return partials.sum(dim=0).view_as(cells)


def _psf_backward(ctx, grad_out):
    image, cells = ctx.saved_tensors
    grid_y, grid_x = ctx.arguments
    grad_image = _psf_backward_image(grad_out, cells, grid_y, grid_x) if ctx.needs_input_grad[0] else None
    grad_cells = _psf_backward_cells(image, grad_out, cells, grid_y, grid_x) if ctx.needs_input_grad[1] else None
    return grad_image, grad_cells, None, None


@warp_op("psf_conv", lambda image, cells, grid_y, grid_x: torch.empty_like(image), _psf_backward, save_inputs)
def _psf_conv_cells(image: torch.Tensor, cells: torch.Tensor, grid_y: int, grid_x: int) -> torch.Tensor:
    """Exact varying convolution with the PSF given per grid cell (`node_cells`)."""
    batch, channels, height, width = image.shape
    size = cells.shape[2]
    radius = size // 2
    _check_offsets(image, radius)
    rows, cols = _source_tables(image, grid_y, grid_x, radius)
    threads = batch * channels * -(-height // kernels.ROWS) * width
    parts = _forward_parts(threads, size, image.device)
    taps = -(-size // parts)
    parts = -(-size // taps)
    out = image.new_empty(parts, batch, channels, height, width)
    launch(kernels.psf_kernels(size).forward, (parts, batch * channels, -(-height // kernels.ROWS), width),
           [_padded_source(image, radius), _nodes(cells), max(grid_x - 1, 1), rows[0], rows[1], rows[2], cols[0],
            cols[1], taps, out.view(parts, batch * channels, height, width)], image.device,
           threads_per_block=FORWARD_BLOCK)
    return out[0] if parts == 1 else out.sum(dim=0)


def _check(image: torch.Tensor, psf: torch.Tensor, method: str) -> None:
    check_tensor("psf_conv", "image", image, 4, "[B, C, H, W]")
    check_tensor("psf_conv", "psf", psf)
    if psf.dim() != 5 or 0 in psf.shape or psf.shape[3] != psf.shape[4] or psf.shape[3] % 2 == 0:
        raise ValueError(f"psf_conv: psf must be a non-empty [C, Gy, Gx, K, K] with K odd, got {tuple(psf.shape)}")
    if psf.shape[0] != image.shape[1]:
        raise ValueError(f"psf_conv: psf has {psf.shape[0]} channels, image has {image.shape[1]}")
    check_same_device("psf_conv", image=image, psf=psf)
    if method not in PSF_METHODS:
        raise ValueError(f"psf_conv: method must be one of {PSF_METHODS}, got {method!r}")
    invariant = psf.shape[1] == psf.shape[2] == 1
    if method in ("conv2d", "fft") and not invariant:
        raise ValueError(f"psf_conv: method {method!r} is exact only for one PSF (a 1x1 grid), got a "
                         f"{psf.shape[1]}x{psf.shape[2]} grid; use 'auto', 'direct' or 'patch'")


def psf_conv(image: torch.Tensor, psf: torch.Tensor, method: str = "auto") -> torch.Tensor:
    """Convolve with a spatially varying PSF (eq. 2 of the paper, docs/references.md).

    Args:
        image: [B, C, H, W] linear irradiance (float32 or float64; half types compute in float32).
        psf: [C, Gy, Gx, K, K] node PSFs (K odd) on a corner-aligned grid (`node_axis`), bilinear in between. Cast
            to the image's float type. Value policy: the convolution is linear in the PSF and takes any values
            (negative lobes, sums other than 1 for vignetting); energy is conserved only for PSFs summing to 1,
            which is the lens's job (`Lens.psf_grid`). A NaN or inf PSF value makes the outputs it reaches NaN.
        method: "auto" (default: the fastest exact method; the Warp kernel for a varying grid; for one PSF the
            fastest of cuDNN conv2d, a cuDNN forward with the Warp adjoints as its backward, and the Warp kernel,
            timed once per shape and gradient need on CUDA; FFT is left out for its precision), "direct" (Warp
            kernel),
            "conv2d" (cuDNN on the edge-padded image; one PSF only), "fft" (torch.fft; one PSF only; NaN stays
            local, but float32 rounding is relative to the image maximum: dark pixels beside 1e9 brighter ones
            lose their precision) or "patch" (each node's region convolved with that node's PSF, no blending:
            seams; an approximation for comparison).

    Returns:
        [B, C, H, W], float64 for a float64 image, else float32 (a float16 or bfloat16 image's result is float32,
        as it is computed). A point source at pixel q renders as PSF_q centred at q (not
        flipped); borders clamp to edge. Differentiable w.r.t. image and psf for every method.
    """
    _check(image, psf, method)
    compute_dtype = torch.float64 if image.dtype == torch.float64 else torch.float32
    # autocast has no meta device ("unsupported scalarType"); meta tensors take the ops' fake implementations
    with torch.autocast(image.device.type, enabled=False) if not image.is_meta else contextlib.nullcontext():
        image, psf = image.to(compute_dtype), psf.to(compute_dtype)
        invariant = psf.shape[1] == psf.shape[2] == 1
        if method == "auto":
            method = _fastest_invariant(image, psf) if invariant else "direct"
        if method in _EXACT_PATHS:
            return _EXACT_PATHS[method](image, psf)
        if method == "fft":
            return psf_conv_fft(image, psf[:, 0, 0])
        return psf_conv_patch(image, psf)


def _direct(image: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    image, psf = prepare(image, psf)
    return _psf_conv_cells(image, _kept_cells(psf), psf.shape[1], psf.shape[2])


_CELLS: dict[int, tuple] = {}  # id(psf) -> (weak reference to psf, its version, node_cells(psf))


def _kept_cells(psf: torch.Tensor) -> torch.Tensor:
    """`node_cells(psf)`, kept while ``psf`` lives unchanged (same tensor, same version counter) when no gradient
    flows to it: a fixed PSF grid (a frozen lens, a camera in eval) is rearranged once instead of per call (a stack
    kernel and its host time). Computed afresh where a kept tensor is not allowed (`may_keep`: tracing,
    capturing a CUDA graph, inference mode) and for an inference tensor (no version counter). A change through
    ``.data`` is not seen."""
    # is_compiling first: dynamo folds it to True and never traces into the host-side checks
    if (torch.compiler.is_compiling() or (psf.requires_grad and torch.is_grad_enabled()) or psf.is_inference()
            or not may_keep(psf)):
        return node_cells(psf)
    key = id(psf)
    kept = _CELLS.get(key)
    if kept is not None and kept[0]() is psf and kept[1] == psf._version:
        return kept[2]
    with torch.no_grad():
        cells = node_cells(psf)
    _CELLS[key] = (weakref.ref(psf, lambda _, key=key: _CELLS.pop(key, None)), psf._version, cells)
    return cells


def _conv2d_warp_gradient(image: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    image, kernel = prepare(image, psf[:, 0, 0])
    return _psf_conv_cudnn(image, kernel)


# exact paths by name; "conv2d_warp_gradient" is one of auto's candidates, not a public method
_EXACT_PATHS = {
    "direct": _direct,
    "conv2d": lambda image, psf: psf_conv_conv2d(image, psf[:, 0, 0]),
    "conv2d_warp_gradient": _conv2d_warp_gradient,
}
_FASTEST: dict = {}


def _fastest_invariant(image: torch.Tensor, psf: torch.Tensor) -> str:
    """The fastest exact path for one PSF at this shape and gradient need: measured once per (shape, K, dtype,
    which inputs need gradients) on CUDA (forward + backward where a gradient is needed, 10 repeats after a
    warm-up) and cached; conv2d on the CPU, where the Warp backend runs serially."""
    needs = (image.requires_grad and torch.is_grad_enabled(), psf.requires_grad and torch.is_grad_enabled())
    key = (tuple(image.shape), psf.shape[-1], image.dtype, image.device, needs)
    if (image.device.type != "cuda" or torch.compiler.is_compiling()
            or torch.cuda.is_current_stream_capturing()):
        return _FASTEST.get(key, "conv2d")
    if key not in _FASTEST:
        if not _offsets_fit(image.shape, psf.shape[-1] // 2):  # too large for the Warp paths: cuDNN's alone
            _FASTEST[key] = "conv2d"
            return "conv2d"
        probe = torch.rand_like(image).requires_grad_(needs[0])
        kernel = psf.detach().clone().requires_grad_(needs[1])
        with torch.enable_grad() if any(needs) else torch.no_grad():
            timings = {name: _time_path(path, probe, kernel) for name, path in _EXACT_PATHS.items()}
        _FASTEST[key] = min(timings, key=timings.get)
    return _FASTEST[key]


def _time_path(path, probe: torch.Tensor, kernel: torch.Tensor, repeats: int = 10) -> float:
    for repeat in range(repeats + 1):
        if repeat == 1:  # the first call compiles, tunes and allocates
            torch.cuda.synchronize()
            start = time.perf_counter()
        out = path(probe, kernel)
        if out.requires_grad:
            out.sum().backward()
    torch.cuda.synchronize()
    return time.perf_counter() - start


def _cudnn_backward(ctx, grad_out):
    image, kernel = ctx.saved_tensors
    channels, size = kernel.shape[0], kernel.shape[-1]
    cells = kernel[:, None, :, :, None].expand(channels, 1, size, size, 4).contiguous()
    grad_image = _psf_backward_image(grad_out, cells, 1, 1) if ctx.needs_input_grad[0] else None
    # one node: its bilinear weight is 1 on the first corner and 0 on the others
    grad_kernel = _psf_backward_cells(image, grad_out, cells, 1, 1)[:, 0, :, :, 0] if ctx.needs_input_grad[1] else None
    return grad_image, grad_kernel


@warp_op("psf_conv_cudnn", lambda image, kernel: torch.empty_like(image), _cudnn_backward, save_inputs)
def _psf_conv_cudnn(image: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """One PSF: the forward by cuDNN (a depthwise convolution), both gradients by the Warp adjoint kernels, which
    are faster than cuDNN's depthwise data and weight gradients."""
    radius = kernel.shape[-1] // 2
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    return F.conv2d(padded, kernel.flip(-1, -2).unsqueeze(1), groups=image.shape[1])


def psf_conv_conv2d(image: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Spatially invariant convolution with kernel [C, K, K] by depthwise conv2d (cuDNN) on the edge-padded image."""
    radius = kernel.shape[-1] // 2
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    return F.conv2d(padded, kernel.flip(-1, -2).unsqueeze(1).to(image.dtype), groups=image.shape[1])


def psf_conv_fft(image: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Spatially invariant convolution with kernel [C, K, K] by torch.fft on the edge-padded image.

    Non-finite pixels are convolved as 0 and then mark every output they reach as NaN, as a direct convolution
    would (an FFT would spread them over the whole plane)."""
    radius = kernel.shape[-1] // 2
    height, width = image.shape[-2:]
    bad = ~torch.isfinite(image)
    clean = torch.where(bad, torch.zeros((), dtype=image.dtype, device=image.device), image)
    padded = F.pad(clean, (radius,) * 4, mode="replicate")
    full_h, full_w = height + 2 * radius, width + 2 * radius
    spectrum = torch.fft.rfft2(padded, s=(full_h, full_w))
    kernel_spectrum = torch.fft.rfft2(kernel.to(image.dtype), s=(full_h, full_w))
    result = torch.fft.irfft2(spectrum * kernel_spectrum, s=(full_h, full_w))
    # circular convolution of the padded image with the kernel anchored at (0, 0): valid part starts at 2r
    result = result[..., 2 * radius : 2 * radius + height, 2 * radius : 2 * radius + width]
    reached = F.max_pool2d(F.pad(bad.to(image.dtype), (radius,) * 4, mode="replicate"), kernel.shape[-1], stride=1)
    return torch.where(reached > 0, torch.full((), float("nan"), dtype=image.dtype, device=image.device), result)


def nearest_node_edges(size: int, nodes: int) -> list[int]:
    """Pixel edges of the regions whose nearest node is each of ``nodes`` corner-aligned nodes (``nodes + 1``
    entries from 0 to ``size``; a region may be empty when there are more nodes than pixels)."""
    if nodes == 1:
        return [0, size]
    return [0] + [min(size, max(0, round((k - 0.5) / (nodes - 1) * size))) for k in range(1, nodes)] + [size]


def psf_conv_patch(image: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    """Patch-wise approximation: the region nearest each node convolved with that node's PSF (cuDNN), no blending."""
    _, channels, height, width = image.shape
    _, grid_y, grid_x, size, _ = psf.shape
    radius = size // 2
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    row_edges, col_edges = nearest_node_edges(height, grid_y), nearest_node_edges(width, grid_x)
    pieces = []
    for gy in range(grid_y):
        y0, y1 = row_edges[gy], row_edges[gy + 1]
        if y1 <= y0:
            continue
        row = []
        for gx in range(grid_x):
            x0, x1 = col_edges[gx], col_edges[gx + 1]
            if x1 <= x0:
                continue
            window = padded[..., y0 : y1 + 2 * radius, x0 : x1 + 2 * radius]
            kernel = psf[:, gy, gx].flip(-1, -2).unsqueeze(1).to(image.dtype)
            row.append(F.conv2d(window, kernel, groups=channels))
        pieces.append(torch.cat(row, dim=-1))
    return torch.cat(pieces, dim=-2)
