"""Plain-torch reference implementations of the sensor ops.

Independent of the Warp kernels (written from the equations, eager torch only): the tests compare the kernels with
them, and the benchmarks use them as the baseline a user would write without warpsense.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def cfa_mosaic_reference(rgb: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """[B,3,H,W], [T,T,3] -> [B,1,H,W]: tile phi over the image and take the per-pixel dot product."""
    tile = phi.shape[0]
    height, width = rgb.shape[-2:]
    reps_y, reps_x = -(-height // tile), -(-width // tile)
    response = phi.permute(2, 0, 1).repeat(1, reps_y, reps_x)[:, :height, :width]
    return (rgb * response.unsqueeze(0)).sum(dim=1, keepdim=True)


def _pcg_hash(state: np.ndarray) -> np.ndarray:
    """PCG hash of Jarzynski & Olano (JCGT 2020), the counter-based generator behind Warp's rand_init/randf."""
    b = (state * np.uint32(747796405) + np.uint32(2891336453)).astype(np.uint32)
    c = (((b >> ((b >> np.uint32(28)) + np.uint32(4))) ^ b) * np.uint32(277803737)).astype(np.uint32)
    return (c >> np.uint32(22)) ^ c


def standard_normal_reference(seed: int, count: int) -> np.ndarray:
    """eps[i] for i < count exactly as the noise kernel draws it: state = pcg(seed + pcg(i)), two uniforms
    u = (pcg(state) >> 8) / 2^24 in order, then Box-Muller sqrt(-2 log(u1 + 5.96e-8)) cos(2 pi u2), in float32."""
    with np.errstate(over="ignore"):
        index = np.arange(count, dtype=np.uint32)
        state = _pcg_hash((np.uint32(seed & 0xFFFFFFFF) + _pcg_hash(index)).astype(np.uint32))
        state = _pcg_hash(state)
        first = (state >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / 16777216.0)
        state = _pcg_hash(state)
        second = (state >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / 16777216.0)
    radius = np.sqrt(np.float32(-2.0) * np.log(first + np.float32(5.96e-8)))
    return (radius * np.cos(np.float32(2.0 * np.pi) * second)).astype(np.float32)


def poisson_gaussian_reference(raw, shot, read, eps: torch.Tensor) -> torch.Tensor:
    """R + sqrt(shot * max(R, 0) + read^2) * eps with a given standard-normal eps of raw's shape."""
    return raw + torch.sqrt(shot * raw.clamp_min(0) + read * read) * eps


class _RoundSTE(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        return torch.floor(x + 0.5)

    @staticmethod
    def backward(ctx, grad):
        return grad


def quantize_reference(raw: torch.Tensor, bits: int, white_level: float = 1.0, mode: str = "full_well"):
    """Clipped-STE quantization in eager torch: clamp (gradient 0 outside [0, w]) then round with identity gradient."""
    levels = (1 << bits) - 1
    rows = raw.reshape(raw.shape[0], -1)
    if mode == "max":
        peak = rows.detach().amax(dim=1, keepdim=True)
        white = torch.where(peak > 0, peak, torch.full_like(peak, white_level))
    else:
        white = torch.full((rows.shape[0], 1), white_level, dtype=raw.dtype, device=raw.device)
    inside = (rows >= 0) & (rows <= white)
    clipped = torch.where(inside, rows, rows.detach().clamp(min=0).minimum(white))
    return (_RoundSTE.apply(clipped / white * levels) / levels * white).view(raw.shape)


def bilinear_node_weights(height: int, width: int, grid_y: int, grid_x: int, dtype, device) -> torch.Tensor:
    """[Gy, Gx, H, W] weight of each PSF-grid node at each pixel: hat functions of the distance to the node, with
    the nodes spread over the whole field (node n at n / (G - 1) of the image, corners included; pixel q's centre
    at (q + 0.5) / size), written from the formula w_n(u) = max(0, 1 - |u (G - 1) - n|)."""

    def axis(n_nodes, size):
        if n_nodes == 1:
            return torch.ones(1, size, dtype=dtype, device=device)
        position = (torch.arange(size, dtype=dtype, device=device) + 0.5) / size * (n_nodes - 1)
        nodes = torch.arange(n_nodes, dtype=dtype, device=device)
        return (1 - (position[None, :] - nodes[:, None]).abs()).clamp_min(0)

    wy, wx = axis(grid_y, height), axis(grid_x, width)
    return wy[:, None, :, None] * wx[None, :, None, :]


def psf_conv_reference(image: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    """Exact spatially varying PSF convolution as a blend of node convolutions (eager torch, memory hungry).

    out(p) = sum_d x(clamp(p - d)) * PSF_{clamp(p - d)}(d), PSF_q = sum_n w_n(q) PSF_n: each source pixel spreads its
    light with the PSF interpolated at the source, so a point source at q renders as PSF_q centred at q.
    """
    batch, channels, height, width = image.shape
    _, grid_y, grid_x, size, _ = psf.shape
    radius = size // 2
    padded = F.pad(image, (radius, radius, radius, radius), mode="replicate")
    weights = bilinear_node_weights(height, width, grid_y, grid_x, image.dtype, image.device)
    weights = F.pad(weights.reshape(1, grid_y * grid_x, height, width), (radius,) * 4, mode="replicate")
    weights = weights.reshape(grid_y, grid_x, height + 2 * radius, width + 2 * radius)
    out = image.new_zeros(batch, channels, height, width)
    for gy in range(grid_y):
        for gx in range(grid_x):
            kernel = psf[:, gy, gx].flip(-1, -2).unsqueeze(1)  # conv2d correlates: flip for a true convolution
            out = out + F.conv2d(padded * weights[gy, gx], kernel, groups=channels)
    return out


def psf_conv_blend_fft(image: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    """`psf_conv_reference`'s blend of node convolutions, each node's convolution done by FFT.

    For references with wide kernels or dense grids (K = 127, 17 x 17 nodes), where the direct blend costs
    Gy Gx H W K^2. Rounding is relative to each node's weighted image maximum (FFT), so use it in float64 and for
    errors well above 1e-12; the direct `psf_conv_reference` stays the reference for pointwise float32 errors.
    """
    batch, channels, height, width = image.shape
    _, grid_y, grid_x, size, _ = psf.shape
    radius = size // 2
    full_h, full_w = height + 2 * radius, width + 2 * radius
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    weights = bilinear_node_weights(height, width, grid_y, grid_x, image.dtype, image.device)
    weights = F.pad(weights.reshape(1, grid_y * grid_x, height, width), (radius,) * 4, mode="replicate")[0]
    kernel_spectra = torch.fft.rfft2(psf.to(image.dtype), s=(full_h, full_w))  # [C, Gy, Gx, full_h, full_w // 2 + 1]
    spectrum = 0
    for node in range(grid_y * grid_x):
        node_y, node_x = divmod(node, grid_x)
        spectrum = spectrum + torch.fft.rfft2(padded * weights[node]) * kernel_spectra[:, node_y, node_x]
    result = torch.fft.irfft2(spectrum, s=(full_h, full_w))
    # circular convolution anchored at (0, 0): the valid part of the padded frame starts at 2r
    return result[..., 2 * radius : 2 * radius + height, 2 * radius : 2 * radius + width]


def edge_aware_smoothness_reference(probabilities: torch.Tensor, guide: torch.Tensor, sigma: float = 0.1):
    """[B,K,H,W], [B,H,W] -> 0-d: half the mean over horizontal neighbour pairs and half the mean over vertical
    ones of exp(-|g_p - g_q| / sigma) |P(p) - P(q)|_1 (eq. 9 of the paper), from shifted slices."""
    guide = guide.unsqueeze(1)
    dx_p = (probabilities[..., :, 1:] - probabilities[..., :, :-1]).abs().sum(dim=1, keepdim=True)
    dy_p = (probabilities[..., 1:, :] - probabilities[..., :-1, :]).abs().sum(dim=1, keepdim=True)
    wx = torch.exp(-(guide[..., :, 1:] - guide[..., :, :-1]).abs() / sigma)
    wy = torch.exp(-(guide[..., 1:, :] - guide[..., :-1, :]).abs() / sigma)
    return 0.5 * ((wx * dx_p).mean() + (wy * dy_p).mean())


# run eagerly under torch.compile: inductor (torch 2.11) fails to generate the split scan of a cumsum over a gather
# of this length (InductorError in SplitScan codegen); its input has no gradient, so the island costs nothing else
@torch.compiler.disable
def lovasz_grad(sorted_labels: torch.Tensor) -> torch.Tensor:
    """Gradient of the Lovasz extension of the Jaccard loss w.r.t. sorted errors (Berman et al. 2018, alg. 1).

    One running count of the foreground, over all rows flattened into one int32 sequence, gives every row's counts
    (each row's offset subtracted): exact for up to 2^31 pixels in all. A cumulative sum along the rows would
    parallelise over the rows only, and with the classes as rows (11 rows of 2.7M pixels at the CamVid recipe's
    batch) it would take most of the loss's time.

    Args:
        sorted_labels: [..., P] ground-truth indicator (0/1) of pixels sorted by decreasing error, per row.
    """
    pixels = sorted_labels.shape[-1]
    rows = sorted_labels.reshape(-1, pixels).to(torch.int32)
    running = rows.reshape(-1).cumsum(0, dtype=torch.int32).view(rows.shape)
    foreground_so_far = running - (running[:, :1] - rows[:, :1])  # minus the count before each row
    gts = foreground_so_far[:, -1:]
    rank = torch.arange(1, pixels + 1, device=rows.device, dtype=torch.int32)
    intersection = (gts - foreground_so_far).to(sorted_labels.dtype)
    union = (gts + rank - foreground_so_far).to(sorted_labels.dtype)  # foreground + background so far
    jaccard = 1.0 - intersection / union
    if pixels > 1:
        jaccard = torch.cat([jaccard[:, :1], jaccard[:, 1:] - jaccard[:, :-1]], dim=-1)
    return jaccard.view(sorted_labels.shape)


def lovasz_softmax_reference(probabilities: torch.Tensor, labels: torch.Tensor, ignore_index: int = 255):
    """`warpsense.ops.lovasz_softmax` in plain torch: [B, K, H, W] class probabilities and [B, H, W] labels -> the
    Lovasz-softmax loss (Berman, Rannen Triki, Blaschko, CVPR 2018) averaged over the classes present in the labels.
    Each class's row is sorted (absent classes masked out, so no host round trip); ignored pixels get error 0 and
    are not foreground, which adds nothing to the loss. 0 when no pixel is labelled."""
    num_classes = probabilities.shape[1]
    probabilities = probabilities.transpose(0, 1).reshape(num_classes, -1)
    labels = labels.reshape(-1)
    valid = labels != ignore_index
    classes = torch.arange(num_classes, device=labels.device)[:, None]
    foreground = ((labels[None] == classes) & valid).to(probabilities.dtype)
    errors = (foreground - probabilities).abs() * valid
    errors_sorted, order = errors.sort(dim=1, descending=True)
    losses = (errors_sorted * lovasz_grad(foreground.gather(1, order))).sum(dim=1)
    present = (foreground.sum(dim=1) > 0).to(losses.dtype)
    return (losses * present).sum() / present.sum().clamp_min(1)


def upsample_concat_reference(x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
    """`warpsense.ops.upsample_concat` in plain torch: bilinear x2 (``align_corners=False``) of x [B, C1, h, w],
    then skip [B, C2, 2h, 2w] appended along the channels."""
    up = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
    return torch.cat([up, skip], dim=1)


def batch_norm_relu_reference(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, running_mean: torch.Tensor,
                              running_var: torch.Tensor, momentum: float = 0.1, eps: float = 1e-5) -> torch.Tensor:
    """`warpsense.ops.batch_norm_relu` in plain torch: batch norm with batch statistics (training mode), then ReLU."""
    return F.relu(F.batch_norm(x, running_mean, running_var, weight, bias, training=True, momentum=momentum, eps=eps))


def channel_gate_reference(x: torch.Tensor, gate: torch.Tensor, residual: torch.Tensor | None = None) -> torch.Tensor:
    """`warpsense.ops.channel_gate` in plain torch: x times its per-image channel gates, plus the residual."""
    out = x * gate.reshape(gate.shape[0], gate.shape[1], 1, 1)
    return out if residual is None else residual + out
