"""Edge-aware smoothness of class probabilities (eq. 9 of the paper), one pass over the pixels:

    c[b, y, x] = s_x w_x |P[b, y, x+1] - P[b, y, x]|_1 + s_y w_y |P[b, y+1, x] - P[b, y, x]|_1,
    w_x = exp(-|g[b, y, x+1] - g[b, y, x]| / sigma),   w_y likewise downwards,

the pair terms owned by the pixel on their left / top (0 past the last column / row); the loss is the sum of c.

The plain-torch form builds each difference, its absolute value and the class sum as separate full-size tensors,
forward and backward; here a thread reads its pixel's K probabilities and those of its right and lower neighbours
once. The backward gathers the (up to) four pairs a pixel belongs to, so every gradient is written by one thread:
no atomics, deterministic. |.| has gradient sign(.), with sign(0) = 0 as in torch (flat guide regions are common:
the ADC gives equal neighbours).

Layouts: probabilities [B, H, W, K] (classes innermost: the NHWC memory of a channels-last network's output, no
copy), guide g [B, H, W], params [3] = (1 / sigma, s_x, s_y), map [B, H, W].
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def sign0(value: Any):
    """sign with sign(0) = 0 (torch.sign; Warp's sign is 1 at 0)."""
    result = type(value)(0.0)
    if value > type(value)(0.0):
        result = type(value)(1.0)
    elif value < type(value)(0.0):
        result = type(value)(-1.0)
    return result


@wp.func
def pair_l1(probabilities: wp.array4d(dtype=Any), b: int, y0: int, x0: int, y1: int, x1: int):
    """|P[b, y1, x1] - P[b, y0, x0]|_1 over the classes."""
    total = probabilities.dtype(0.0)
    for k in range(probabilities.shape[3]):
        total += wp.abs(probabilities[b, y1, x1, k] - probabilities[b, y0, x0, k])
    return total


@wp.kernel
def smoothness_forward(
    probabilities: wp.array4d(dtype=Any), guide: wp.array3d(dtype=Any), params: wp.array(dtype=Any),
    out: wp.array3d(dtype=Any),
):
    b, y, x = wp.tid()
    inv_sigma = params[0]
    total = guide.dtype(0.0)
    if x + 1 < probabilities.shape[2]:
        weight = wp.exp(-wp.abs(guide[b, y, x + 1] - guide[b, y, x]) * inv_sigma)
        total += params[1] * weight * pair_l1(probabilities, b, y, x, y, x + 1)
    if y + 1 < probabilities.shape[1]:
        weight = wp.exp(-wp.abs(guide[b, y + 1, x] - guide[b, y, x]) * inv_sigma)
        total += params[2] * weight * pair_l1(probabilities, b, y, x, y + 1, x)
    out[b, y, x] = total


@wp.kernel
def smoothness_backward(
    probabilities: wp.array4d(dtype=Any), guide: wp.array3d(dtype=Any), params: wp.array(dtype=Any),
    grad_map: wp.array3d(dtype=Any), grad_probabilities: wp.array4d(dtype=Any), grad_guide: wp.array3d(dtype=Any),
):
    b, y, x = wp.tid()
    height = probabilities.shape[1]
    width = probabilities.shape[2]
    inv_sigma = params[0]
    zero = guide.dtype(0.0)
    # each pair's d loss / d |P1 - P0|_1 = grad_map[owner] * s * w, and sign(g1 - g0); zero where there is no pair
    right = zero
    right_sign = zero
    left = zero
    left_sign = zero
    down = zero
    down_sign = zero
    up = zero
    up_sign = zero
    if x + 1 < width:
        step = guide[b, y, x + 1] - guide[b, y, x]
        right = grad_map[b, y, x] * params[1] * wp.exp(-wp.abs(step) * inv_sigma)
        right_sign = sign0(step)
    if x > 0:
        step = guide[b, y, x] - guide[b, y, x - 1]
        left = grad_map[b, y, x - 1] * params[1] * wp.exp(-wp.abs(step) * inv_sigma)
        left_sign = sign0(step)
    if y + 1 < height:
        step = guide[b, y + 1, x] - guide[b, y, x]
        down = grad_map[b, y, x] * params[2] * wp.exp(-wp.abs(step) * inv_sigma)
        down_sign = sign0(step)
    if y > 0:
        step = guide[b, y, x] - guide[b, y - 1, x]
        up = grad_map[b, y - 1, x] * params[2] * wp.exp(-wp.abs(step) * inv_sigma)
        up_sign = sign0(step)
    # one pass over the classes: this pixel's gradients (d|P1 - P0| / dP0 = -sign, / dP1 = +sign) and each pair's
    # L1 distance, which the guide's gradient needs
    right_l1 = zero
    left_l1 = zero
    down_l1 = zero
    up_l1 = zero
    for k in range(probabilities.shape[3]):
        here = probabilities[b, y, x, k]
        gradient = zero
        if x + 1 < width:
            difference = probabilities[b, y, x + 1, k] - here
            gradient -= right * sign0(difference)
            right_l1 += wp.abs(difference)
        if x > 0:
            difference = here - probabilities[b, y, x - 1, k]
            gradient += left * sign0(difference)
            left_l1 += wp.abs(difference)
        if y + 1 < height:
            difference = probabilities[b, y + 1, x, k] - here
            gradient -= down * sign0(difference)
            down_l1 += wp.abs(difference)
        if y > 0:
            difference = here - probabilities[b, y - 1, x, k]
            gradient += up * sign0(difference)
            up_l1 += wp.abs(difference)
        grad_probabilities[b, y, x, k] = gradient
    # w = exp(-|g1 - g0| / sigma): dw/dg0 = w sign(g1 - g0) / sigma, dw/dg1 its negative; this pixel is g0 of the
    # pairs it owns (right, down) and g1 of the others
    grad_guide[b, y, x] = inv_sigma * (right * right_l1 * right_sign + down * down_l1 * down_sign
                                       - left * left_l1 * left_sign - up * up_l1 * up_sign)


for _float in (wp.float32, wp.float64):
    _probabilities, _map = wp.array4d(dtype=_float), wp.array3d(dtype=_float)
    wp.overload(smoothness_forward, [_probabilities, _map, wp.array(dtype=_float), _map])
    wp.overload(smoothness_backward, [_probabilities, _map, wp.array(dtype=_float), _map, _probabilities, _map])
