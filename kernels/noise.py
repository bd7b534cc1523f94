"""Poisson-Gaussian sensor noise R' = R + sqrt(shot * max(R, 0) + read^2) * eps (paper eq. 5) as Warp kernels.

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


@wp.kernel
def noise_forward(
    raw: wp.array(dtype=Any),
    shot: wp.array(dtype=Any),
    read: wp.array(dtype=Any),
    seed: wp.int32,
    out: wp.array(dtype=Any),
):
    i = wp.tid()
    signal = raw[i]
    variance = shot[0] * wp.max(signal, raw.dtype(0.0)) + read[0] * read[0]
    eps = raw.dtype(standard_normal(seed, i))
    out[i] = signal + wp.sqrt(wp.max(variance, raw.dtype(0.0))) * eps


@wp.kernel
def noise_backward(
    raw: wp.array(dtype=Any),
    shot: wp.array(dtype=Any),
    read: wp.array(dtype=Any),
    seed: wp.int32,
    grad_out: wp.array(dtype=Any),
    grad_raw: wp.array(dtype=Any),
    partials: wp.array2d(dtype=Any),
):
    """Lane-strided: writes grad_raw and per-lane sums of d/dshot and d/dread into partials[lane, 0:2].

    Where the standard deviation is 0 (shot * R + read^2 = 0) the noise term is taken as constant: its derivative
    (infinite for sqrt at 0) is defined as 0 there.
    """
    lane = wp.tid()
    lanes = partials.shape[0]
    zero = raw.dtype(0.0)
    acc_shot = zero
    acc_read = zero
    for i in range(lane, raw.shape[0], lanes):
        signal = raw[i]
        positive = wp.max(signal, zero)
        sigma = wp.sqrt(wp.max(shot[0] * positive + read[0] * read[0], zero))
        g = grad_out[i]
        if sigma > zero:
            eps = raw.dtype(standard_normal(seed, i))
            d_variance = g * eps / (raw.dtype(2.0) * sigma)
            if signal > zero:
                grad_raw[i] = g + d_variance * shot[0]
            else:
                grad_raw[i] = g
            acc_shot += d_variance * positive
            acc_read += d_variance * raw.dtype(2.0) * read[0]
        else:
            grad_raw[i] = g
    partials[lane, 0] = acc_shot
    partials[lane, 1] = acc_read


@wp.kernel
def poisson_sample(
    raw: wp.array(dtype=Any),
    shot: wp.array(dtype=Any),
    read: wp.array(dtype=Any),
    seed: wp.int32,
    out: wp.array(dtype=Any),
):
    """Exact Poisson shot noise (photon count n ~ Poisson(R / shot), R' = shot * n) plus Gaussian read noise.

    Not differentiable; for evaluation at low light where the Gaussian approximation of eq. 5 breaks down.
    """
    i = wp.tid()
    state = wp.rand_init(seed, i)
    signal = wp.max(raw[i], raw.dtype(0.0))
    value = signal
    if shot[0] > raw.dtype(0.0):
        photons = wp.poisson(state, wp.float32(signal / shot[0]))
        value = shot[0] * raw.dtype(photons)
    out[i] = value + read[0] * raw.dtype(wp.randn(state))


for _float in (wp.float32, wp.float64):
    _flat = wp.array(dtype=_float)
    wp.overload(noise_forward, [_flat, _flat, _flat, wp.int32, _flat])
    wp.overload(poisson_sample, [_flat, _flat, _flat, wp.int32, _flat])
    wp.overload(noise_backward, [_flat, _flat, _flat, wp.int32, _flat, _flat, wp.array2d(dtype=_float)])
