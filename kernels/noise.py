"""Poisson-Gaussian sensor noise R' = R + sqrt(shot * max(R, 0) + read^2) * eps (eq. 5 of the paper,
docs/references.md) as Warp kernels.

``shot`` is a variance coefficient, ``read`` a standard deviation, both 1-element arrays so learnable values stay
on the device. eps ~ N(0, 1) comes from Warp's counter-based generator keyed by (seed, element index): the same on
every device and regenerated in backward instead of being stored. All arrays are flat (contiguous) views.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def standard_normal(seed: wp.int32, index: wp.int32):
    """Box-Muller on two uniforms drawn in a fixed order (C++ leaves the operand order of wp.randn's one-line
    formula to the compiler, so CPU and CUDA builds could disagree)."""
    state = wp.rand_init(seed, index)
    first = wp.randf(state)
    second = wp.randf(state)
    return wp.sqrt(-2.0 * wp.log(first + 5.96e-8)) * wp.cos(2.0 * wp.pi * second)


@wp.func
def noise_sigma(signal: Any, shot: Any, read: Any):
    """Noise standard deviation sqrt(shot * max(R, 0) + read^2), 0 where the variance is negative."""
    zero = type(signal)(0.0)
    return wp.sqrt(wp.max(shot * wp.max(signal, zero) + read * read, zero))


@wp.func
def noise_adjoint(signal: Any, shot: Any, read: Any, sigma: Any, eps: Any, g: Any):
    """(dL/dR, dL/dshot, dL/dread) of R' = R + sigma(R) eps for dL/dR' = g. Where sigma is 0 the noise term is
    taken as constant: its derivative (infinite for sqrt at 0) is defined as 0 there."""
    zero = type(signal)(0.0)
    two = type(signal)(2.0)
    grad_signal = g
    grad_shot = zero
    grad_read = zero
    if sigma > zero:
        d_variance = g * eps / (two * sigma)
        if signal > zero:
            grad_signal = g + d_variance * shot
        grad_shot = d_variance * wp.max(signal, zero)
        grad_read = d_variance * two * read
    return grad_signal, grad_shot, grad_read


@wp.func
def noise_key(i: int, per_image: int, image_stride: int):
    """Counter of element i of a [B, per_image] tensor: its flat index (image_stride 1, one seed for the batch) or
    its index within its image (image_stride 0, a seed per image)."""
    b = i / per_image
    return b * per_image * image_stride + (i - b * per_image)


@wp.kernel
def noise_forward(
    raw: wp.array(dtype=Any),
    shot: wp.array(dtype=Any),
    read: wp.array(dtype=Any),
    seeds: wp.array(dtype=wp.int32),
    per_image: int,
    image_stride: int,
    out: wp.array(dtype=Any),
):
    i = wp.tid()
    signal = raw[i]
    eps = raw.dtype(standard_normal(seeds[i / per_image], noise_key(i, per_image, image_stride)))
    out[i] = signal + noise_sigma(signal, shot[0], read[0]) * eps


@wp.kernel
def noise_backward(
    raw: wp.array(dtype=Any),
    shot: wp.array(dtype=Any),
    read: wp.array(dtype=Any),
    seeds: wp.array(dtype=wp.int32),
    per_image: int,
    image_stride: int,
    grad_out: wp.array(dtype=Any),
    grad_raw: wp.array(dtype=Any),
    partials: wp.array2d(dtype=Any),
):
    """Lane-strided: writes grad_raw and per-lane sums of d/dshot and d/dread into partials[lane, 0:2]
    (`noise_adjoint`)."""
    lane = wp.tid()
    lanes = partials.shape[0]
    zero = raw.dtype(0.0)
    acc_shot = zero
    acc_read = zero
    for i in range(lane, raw.shape[0], lanes):
        signal = raw[i]
        sigma = noise_sigma(signal, shot[0], read[0])
        eps = zero
        if sigma > zero:  # regenerate eps only where it matters
            eps = raw.dtype(standard_normal(seeds[i / per_image], noise_key(i, per_image, image_stride)))
        grad_signal, grad_shot, grad_read = noise_adjoint(signal, shot[0], read[0], sigma, eps, grad_out[i])
        grad_raw[i] = grad_signal
        acc_shot += grad_shot
        acc_read += grad_read
    partials[lane, 0] = acc_shot
    partials[lane, 1] = acc_read


# Above this mean photon count the exact sampler draws from the normal limit N(lambda, lambda), rounded: Warp's
# Poisson sampler works in float32 with a uint32 count, which biases its variance from ~1e6 on and wraps at 2^32.
# At 1e4 the normal limit's skewness error (1 / sqrt(lambda) = 1%) is below the Poisson noise of any statistic.
POISSON_NORMAL_LIMIT = wp.constant(1.0e4)
# seed offset of the read-noise draw, a stream independent of the photon-count draw
READ_STREAM = wp.constant(0x5BD1E995)


@wp.kernel
def poisson_sample(
    raw: wp.array(dtype=Any),
    shot: wp.array(dtype=Any),
    read: wp.array(dtype=Any),
    seeds: wp.array(dtype=wp.int32),
    per_image: int,
    image_stride: int,
    out: wp.array(dtype=Any),
):
    """Exact Poisson shot noise (photon count n ~ Poisson(R / shot), R' = shot * n) plus Gaussian read noise.

    Not differentiable; for evaluation at low light where the Gaussian approximation of eq. 5 breaks down. Counts
    above POISSON_NORMAL_LIMIT come from the normal limit; NaN and infinite inputs pass through unchanged.
    """
    i = wp.tid()
    signal = raw[i]
    if not wp.isfinite(signal):
        out[i] = signal
        return
    seed = seeds[i / per_image]
    key = noise_key(i, per_image, image_stride)
    signal = wp.max(signal, raw.dtype(0.0))
    value = signal
    if shot[0] > raw.dtype(0.0):
        mean = signal / shot[0]
        if mean > raw.dtype(POISSON_NORMAL_LIMIT):
            count = wp.max(wp.floor(mean + wp.sqrt(mean) * raw.dtype(standard_normal(seed, key)) + raw.dtype(0.5)),
                           raw.dtype(0.0))
        else:
            state = wp.rand_init(seed, key)
            count = raw.dtype(wp.poisson(state, wp.float32(mean)))
        value = shot[0] * count
    out[i] = value + read[0] * raw.dtype(standard_normal(seed ^ READ_STREAM, key))


for _float in (wp.float32, wp.float64):
    _flat = wp.array(dtype=_float)
    _seeds = wp.array(dtype=wp.int32)
    wp.overload(noise_forward, [_flat, _flat, _flat, _seeds, int, int, _flat])
    wp.overload(poisson_sample, [_flat, _flat, _flat, _seeds, int, int, _flat])
    wp.overload(noise_backward, [_flat, _flat, _flat, _seeds, int, int, _flat, _flat, wp.array2d(dtype=_float)])
