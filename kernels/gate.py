"""A squeeze-and-excitation gate applied to channels-last activations, with an optional residual, as Warp kernels:

    out[b, s, c] = x[b, s, c] gate[b, c] (+ residual[b, s, c]),

over the S = H W pixels s of each image b (Hu et al. 2018's channel attention, the multiply; docs/references.md).
The backward, one pass over dy and x:

    dx = dy gate,   dgate[b, c] = sum_s dy[b, s, c] x[b, s, c],   dresidual = dy.

Layout as `kernels/batchnorm.py`'s: each thread owns a channel pair of one image and walks its pixels g, g + G, ...
(bfloat16 as int32 words, one pair per 4-byte load); the gate's sums are written per pixel group [B, G, C] in a
fixed order (the op adds them up): deterministic, no atomics. Arithmetic is float32 (float64 for float64 data).
"""

from typing import Any

import warp as wp

from warpsense.kernels.batchnorm import UNROLL, load_pair, pair_of, store_pair

wp.set_module_options({"enable_backward": False})


@wp.func
def image_thread(t: int, pairs: int, groups: int):
    """Thread t of a one-dimensional launch -> (image, pixel group, channel pair); pairs fastest."""
    rest = t / pairs
    return rest / groups, rest % groups, t % pairs


@wp.kernel
def gate_forward(x: wp.array3d(dtype=Any), gate: wp.array2d(dtype=Any), residual: wp.array3d(dtype=Any),
                 add_residual: int, pairs: int, groups: int, out: wp.array3d(dtype=Any)):
    """out = x gate (+ residual where ``add_residual``) for image b's pixel group g."""
    b, group, p = image_thread(wp.tid(), pairs, groups)
    scale = pair_of(gate, b, p)  # image b's gates of channels 2p and 2p + 1
    for start in range(group, x.shape[1], groups * UNROLL):
        for u in range(wp.static(UNROLL)):
            s = start + u * groups
            if s < x.shape[1]:
                value = wp.cw_mul(load_pair(x[b], s, p), scale)
                if add_residual:
                    value += load_pair(residual[b], s, p)
                store_pair(out[b], s, p, value)


@wp.kernel
def gate_backward(grad_out: wp.array3d(dtype=Any), x: wp.array3d(dtype=Any), gate: wp.array2d(dtype=Any),
                  pairs: int, groups: int, grad_x: wp.array3d(dtype=Any), partials: wp.array3d(dtype=Any)):
    """grad_x = dy gate, and partials[b, g] = sum dy x over image b's pixel group g."""
    b, group, p = image_thread(wp.tid(), pairs, groups)
    scale = pair_of(gate, b, p)  # image b's gates of channels 2p and 2p + 1
    total = scale - scale
    for start in range(group, x.shape[1], groups * UNROLL):
        for u in range(wp.static(UNROLL)):
            s = start + u * groups
            if s < x.shape[1]:
                d = load_pair(grad_out[b], s, p)
                total += wp.cw_mul(d, load_pair(x[b], s, p))
                store_pair(grad_x[b], s, p, wp.cw_mul(d, scale))
    partials[b, group, 2 * p] = total[0]
    partials[b, group, 2 * p + 1] = total[1]


for _data, _float in ((wp.int32, wp.float32), (wp.float32, wp.float32), (wp.float64, wp.float64)):
    _pixels = wp.array3d(dtype=_data)
    _table = wp.array2d(dtype=_float)
    wp.overload(gate_forward, [_pixels, _table, _pixels, int, int, int, _pixels])
    wp.overload(gate_backward, [_pixels, _pixels, _table, int, int, _pixels, wp.array3d(dtype=_float)])
