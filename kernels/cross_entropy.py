"""Softmax over the classes and the cross-entropy of each pixel's label, one pass forward and one backward:

    p[b, k, y, x] = exp(z_k - m) / S,   S = sum_j exp(z_j - m),   m = max_j z_j,
    loss[b, y, x] = w[t] (log S + m - z_t)        (t = the pixel's label; 0 where it is ignored),
    dz_k = p_k (dp_k - sum_j dp_j p_j) + w[t] dloss (p_k - [k = t]).

The training loss needs both outputs (the OHEM term the losses, the Lovasz and smoothness terms the
probabilities). In torch that is a float32 cast of the bf16 logits, log_softmax + nll_loss and softmax, each with
its own backward, the two gradients added and cast back: ~2.9 GB of memory traffic at the recipe's batch against
~0.5 GB here. One thread per pixel reads its K logits (a contiguous run in channels-last memory) and writes every
output element once: deterministic.

Layouts: logits and their gradient [B, K, H, W] in the logits' dtype (bfloat16, float32 or float64; any strides),
probabilities and their gradient [B, K, H, W] and losses [B, H, W] in the arithmetic type (float32; float64 for
float64 logits), labels [B, H, W] int32, weights [K].
"""

from typing import Any

import warp as wp

from warpsense.kernels.upsample import widen

wp.set_module_options({"enable_backward": False})


@wp.kernel
def softmax_cross_entropy_forward(
    logits: wp.array4d(dtype=Any), labels: wp.array3d(dtype=wp.int32), weights: wp.array(dtype=Any),
    ignore_index: int, probabilities: wp.array4d(dtype=Any), losses: wp.array3d(dtype=Any),
):
    b, y, x = wp.tid()
    classes = logits.shape[1]
    top = widen(logits[b, 0, y, x])
    for k in range(1, classes):
        top = wp.max(top, widen(logits[b, k, y, x]))
    total = type(top)(0.0)
    for k in range(classes):
        total += wp.exp(widen(logits[b, k, y, x]) - top)
    scale = type(top)(1.0) / total
    for k in range(classes):
        probabilities[b, k, y, x] = wp.exp(widen(logits[b, k, y, x]) - top) * scale
    label = labels[b, y, x]
    loss = type(top)(0.0)
    if label != ignore_index and label >= 0 and label < classes:
        loss = weights[label] * (wp.log(total) + top - widen(logits[b, label, y, x]))
    losses[b, y, x] = loss


@wp.kernel
def softmax_cross_entropy_backward(
    probabilities: wp.array4d(dtype=Any), labels: wp.array3d(dtype=wp.int32), weights: wp.array(dtype=Any),
    ignore_index: int, grad_probabilities: wp.array4d(dtype=Any), grad_losses: wp.array3d(dtype=Any),
    grad_logits: wp.array4d(dtype=Any),
):
    b, y, x = wp.tid()
    classes = probabilities.shape[1]
    dot = probabilities.dtype(0.0)
    for k in range(classes):
        dot += grad_probabilities[b, k, y, x] * probabilities[b, k, y, x]
    label = labels[b, y, x]
    scale = probabilities.dtype(0.0)
    if label != ignore_index and label >= 0 and label < classes:
        scale = weights[label] * grad_losses[b, y, x]
    for k in range(classes):
        p = probabilities[b, k, y, x]
        value = p * (grad_probabilities[b, k, y, x] - dot + scale)
        if k == label:
            value -= scale
        grad_logits[b, k, y, x] = grad_logits.dtype(value)


for _logits, _float in ((wp.bfloat16, wp.float32), (wp.float32, wp.float32), (wp.float64, wp.float64)):
    _maps, _labels, _pixels = wp.array4d(dtype=_float), wp.array3d(dtype=wp.int32), wp.array3d(dtype=_float)
    wp.overload(softmax_cross_entropy_forward,
                [wp.array4d(dtype=_logits), _labels, wp.array(dtype=_float), int, _maps, _pixels])
    wp.overload(softmax_cross_entropy_backward,
                [_maps, _labels, wp.array(dtype=_float), int, _maps, _pixels, wp.array4d(dtype=_logits)])
