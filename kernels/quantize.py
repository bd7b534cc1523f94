"""ADC quantization with a clipped straight-through gradient (eq. 6 of the paper, corrected as in
docs/references.md, convention 1):

    Q(R) = floor(clip(R, 0, w) / w * L + 1/2) / L * w,   L = 2^b - 1 steps,   dQ/dR = 1 on [0, w], else 0.

NaN inputs stay NaN (gradient 0 there); +-Inf clip to w / 0 like any out-of-range value.

Layouts: values [B, N] (one row per image), white [B] (per-image white level w > 0).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def quantize_value(value: Any, white: Any, levels: Any):
    """floor(clip(value, 0, w) / w * L + 1/2) / L * w; NaN stays NaN (clamp would turn it into a valid code).

    The code is computed in float64 whatever the storage type: in float32 the product lands on the wrong side of a
    threshold for values within an ulp of it (measured on white noise: 3e-5 of codes at 10 bits, 1.2e-3 at 16, 50%
    at 24). The kernel is memory-bound, so the float64 arithmetic costs no time."""
    result = value
    if not wp.isnan(value):
        white64 = wp.float64(white)
        levels64 = wp.float64(levels)
        code = wp.floor(wp.clamp(wp.float64(value), wp.float64(0.0), white64) / white64 * levels64 + wp.float64(0.5))
        result = type(value)(code / levels64 * white64)
    return result


@wp.func
def passes_gradient(value: Any, white: Any):
    """The clipped straight-through estimator passes the gradient on [0, w] (not at NaN)."""
    return value >= type(value)(0.0) and value <= white


@wp.kernel
def quantize_forward(
    values: wp.array2d(dtype=Any), white: wp.array(dtype=Any), steps: wp.int32, out: wp.array2d(dtype=Any)
):
    b, i = wp.tid()
    out[b, i] = quantize_value(values[b, i], white[b], values.dtype(steps))


@wp.kernel
def quantize_backward(
    values: wp.array2d(dtype=Any),
    white: wp.array(dtype=Any),
    grad_out: wp.array2d(dtype=Any),
    grad_values: wp.array2d(dtype=Any),
):
    b, i = wp.tid()
    if passes_gradient(values[b, i], white[b]):
        grad_values[b, i] = grad_out[b, i]
    else:
        grad_values[b, i] = values.dtype(0.0)


for _float in (wp.float32, wp.float64):
    _rows = wp.array2d(dtype=_float)
    wp.overload(quantize_forward, [_rows, wp.array(dtype=_float), wp.int32, _rows])
    wp.overload(quantize_backward, [_rows, wp.array(dtype=_float), _rows, _rows])
