"""The whole sensor in one pass: CFA mosaic -> Poisson-Gaussian noise -> ADC quantization (paper eq. 4-6).

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

from warpsense.kernels.noise import standard_normal

wp.set_module_options({"enable_backward": False})


@wp.func
def capture_signal(rgb: wp.array4d(dtype=Any), phi: wp.array3d(dtype=Any), b: int, y: int, x: int):
    tile = phi.shape[0]
    sy = y % tile
    sx = x % tile
    return rgb[b, 0, y, x] * phi[sy, sx, 0] + rgb[b, 1, y, x] * phi[sy, sx, 1] + rgb[b, 2, y, x] * phi[sy, sx, 2]


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
    zero = rgb.dtype(0.0)
    value = capture_signal(rgb, phi, b, y, x)
    if noisy != 0:
        index = b * height * width * image_stride + y * width + x
        sigma = wp.sqrt(wp.max(shot[0] * wp.max(value, zero) + read[0] * read[0], zero))
        value = value + sigma * rgb.dtype(standard_normal(seeds[b], index))
    if steps > 0 and not wp.isnan(value):
        levels = rgb.dtype(steps)
        w = white[0]
        value = wp.floor(wp.clamp(value, zero, w) / w * levels + rgb.dtype(0.5)) / levels * w
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
    rows = (height - sy + tile - 1) / tile
    cols = (width - sx + tile - 1) / tile
    per_image = rows * cols
    total = rgb.shape[0] * per_image
    zero = rgb.dtype(0.0)
    two = rgb.dtype(2.0)
    acc0 = zero
    acc1 = zero
    acc2 = zero
    acc_shot = zero
    acc_read = zero
    for m in range(lane, total, lanes):
        b = m / per_image
        r = m - b * per_image
        y = sy + (r / cols) * tile
        x = sx + (r % cols) * tile
        g = grad_out[b, 0, y, x]
        value = capture_signal(rgb, phi, b, y, x)
        grad_value = g
        if noisy != 0:
            positive = wp.max(value, zero)
            sigma = wp.sqrt(wp.max(shot[0] * positive + read[0] * read[0], zero))
            eps = zero
            if sigma > zero:
                eps = rgb.dtype(standard_normal(seeds[b], b * height * width * image_stride + y * width + x))
            noisy_value = value + sigma * eps
            if steps > 0 and not (noisy_value >= zero and noisy_value <= white[0]):
                g = zero
            grad_value = g
            if sigma > zero:
                d_variance = g * eps / (two * sigma)
                if value > zero:
                    grad_value = g + d_variance * shot[0]
                acc_shot += d_variance * positive
                acc_read += d_variance * two * read[0]
        elif steps > 0 and not (value >= zero and value <= white[0]):
            grad_value = zero
        acc0 += grad_value * rgb[b, 0, y, x]
        acc1 += grad_value * rgb[b, 1, y, x]
        acc2 += grad_value * rgb[b, 2, y, x]
        if want_grad_rgb != 0:
            grad_rgb[b, 0, y, x] = grad_value * phi[sy, sx, 0]
            grad_rgb[b, 1, y, x] = grad_value * phi[sy, sx, 1]
            grad_rgb[b, 2, y, x] = grad_value * phi[sy, sx, 2]
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
