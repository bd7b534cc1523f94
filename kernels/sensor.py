"""The whole sensor in one pass: CFA mosaic -> Poisson-Gaussian noise -> ADC quantization (eqs. 4-6 of the paper,
docs/references.md).

    R   = < rgb(p), phi[p mod T] >                         (exposure a(g) is folded into phi by the caller)
    R'  = R + sqrt(shot * max(R, 0) + read^2) * eps         (eps from `noise.standard_normal`, the same draw as the
                                                             per-stage noise kernel)
    out = floor(clip(R', 0, w) / w * L + 1/2) / L * w       (L = 2^b - 1 steps; L = 0: no quantization)

Radiance is read once and the RAW mosaic written once; backward recomputes R and eps instead of storing them.

Layouts: rgb [B, 3, H, W]; phi [T, T, 3]; shot, read, white: 1-element arrays (learnable values stay on the device);
seeds [B] int32, with eps of image b at pixel i keyed by (seeds[b], b * H * W * image_stride + i); out [B, 1, H, W].
"""

from typing import Any

import warp as wp

from warpsense.kernels.cfa import mosaic_adjoint, mosaic_value, site_pixel, site_pixel_count
from warpsense.kernels.noise import noise_adjoint, noise_key, noise_sigma, standard_normal
from warpsense.kernels.quantize import passes_gradient, quantize_value

wp.set_module_options({"enable_backward": False})


@wp.kernel
def sensor_forward(
    rgb: wp.array4d(dtype=Any),
    phi: wp.array3d(dtype=Any),
    shot: wp.array(dtype=Any),
    read: wp.array(dtype=Any),
    seeds: wp.array(dtype=wp.int32),
    image_stride: int,
    noisy: int,
    steps: int,
    white: wp.array(dtype=Any),
    out: wp.array4d(dtype=Any),
):
    b, y, x = wp.tid()
    height = rgb.shape[2]
    width = rgb.shape[3]
    value = mosaic_value(rgb, phi, b, y, x)
    if noisy != 0:
        key = noise_key((b * height + y) * width + x, height * width, image_stride)
        value = value + noise_sigma(value, shot[0], read[0]) * rgb.dtype(standard_normal(seeds[b], key))
    if steps > 0:
        value = quantize_value(value, white[0], rgb.dtype(steps))
    out[b, 0, y, x] = value


@wp.kernel
def sensor_backward(
    rgb: wp.array4d(dtype=Any),
    phi: wp.array3d(dtype=Any),
    shot: wp.array(dtype=Any),
    read: wp.array(dtype=Any),
    seeds: wp.array(dtype=wp.int32),
    image_stride: int,
    noisy: int,
    steps: int,
    white: wp.array(dtype=Any),
    grad_out: wp.array4d(dtype=Any),
    want_grad_rgb: int,
    grad_rgb: wp.array4d(dtype=Any),
    partials: wp.array3d(dtype=Any),
):
    """Thread (CFA site, lane): the lane walks that site's pixels with a stride, writes grad_rgb for each and keeps
    private sums of d/dphi[site] (3), d/dshot and d/dread in partials[site, lane, 0:5] (summed by the caller): no
    atomics, deterministic.

    Chain: clipped straight-through quantizer (gradient 1 on [0, w], else 0; 0 at NaN), then the noise derivative
    (the noise term taken as constant where its standard deviation is 0), then the mosaic.
    """
    site, lane = wp.tid()
    tile = phi.shape[0]
    lanes = partials.shape[1]
    sy = site / tile
    sx = site % tile
    height = rgb.shape[2]
    width = rgb.shape[3]
    cols, per_image = site_pixel_count(height, width, tile, sy, sx)
    total = rgb.shape[0] * per_image
    zero = rgb.dtype(0.0)
    acc0 = zero
    acc1 = zero
    acc2 = zero
    acc_shot = zero
    acc_read = zero
    for m in range(lane, total, lanes):
        b, y, x = site_pixel(m, sy, sx, tile, cols, per_image)
        g = grad_out[b, 0, y, x]
        value = mosaic_value(rgb, phi, b, y, x)
        grad_value = g
        if noisy != 0:
            sigma = noise_sigma(value, shot[0], read[0])
            eps = zero
            if sigma > zero:  # regenerate eps only where it matters
                key = noise_key((b * height + y) * width + x, height * width, image_stride)
                eps = rgb.dtype(standard_normal(seeds[b], key))
            if steps > 0 and not passes_gradient(value + sigma * eps, white[0]):
                g = zero
            grad_value, grad_shot, grad_read = noise_adjoint(value, shot[0], read[0], sigma, eps, g)
            acc_shot += grad_shot
            acc_read += grad_read
        elif steps > 0 and not passes_gradient(value, white[0]):
            grad_value = zero
        d0, d1, d2 = mosaic_adjoint(rgb, phi, b, y, x, sy, sx, grad_value, want_grad_rgb, grad_rgb)
        acc0 += d0
        acc1 += d1
        acc2 += d2
    partials[site, lane, 0] = acc0
    partials[site, lane, 1] = acc1
    partials[site, lane, 2] = acc2
    partials[site, lane, 3] = acc_shot
    partials[site, lane, 4] = acc_read


for _float in (wp.float32, wp.float64):
    _image = wp.array4d(dtype=_float)
    _scalar = wp.array(dtype=_float)
    _common = [_image, wp.array3d(dtype=_float), _scalar, _scalar, wp.array(dtype=wp.int32), int, int, int, _scalar]
    wp.overload(sensor_forward, [*_common, _image])
    wp.overload(sensor_backward, [*_common, _image, int, _image, wp.array3d(dtype=_float)])
