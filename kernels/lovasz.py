"""Lovasz-softmax loss (Berman, Rannen Triki, Blaschko, CVPR 2018, alg. 1) over all classes at once, from one sort.

Class c's errors e = |fg - p_c| (fg = 1 where the label is c; e = 0 on ignored pixels) sorted in decreasing order
give the Lovasz extension's gradient g_r = J(r, F_r) - J(r - 1, F_(r-1)), J(r, F) = 1 - (G - F) / (G + r - F) at
rank r (G: the class's foreground pixels, F_r: those among the first r; J(0, 0) = 0), and the class's loss
sum_r e_(r) g_r.

The plain-torch form sorts each class's row separately and builds the foreground, the errors, the gathered labels
and every step of J as full-size tensors, forward and backward. Here:

1. `lovasz_keys`: one int32 key per (class, pixel) at c * Q + pixel, Q = P (the pixels) rounded up to whole tiles:
   ``class << (q + 2) | (levels - level(e)) << 2 | valid << 1 | fg``, level(e) = ceil(e * levels) in [0, levels]
   (level 0 only for e = 0), levels = 2^q - 1, q = 29 - class bits; the Q - P padding keys of a class are its
   largest (e = 0, not valid). One stable ascending sort of these keys (torch.sort, the caller) orders the classes
   and, within each, the errors from large to small, every tile of the sorted keys inside one class. Errors closer
   than 1 / levels may swap, which moves a class's loss by at most 1 / levels (the g of a class sum to J_P <= 1)
   and gives those pixels the gradients of the order used (what the exact ranking gives when errors are equal).
2. `lovasz_counts`: each tile (one block) counts its foreground (the keys' bit 0); a cumulative sum of the counts
   along each class (torch) gives every tile the foreground before it, and G.
3. `lovasz_gradient`: each thread takes one sorted key: F_r from its tile's scan of the foreground bits, g_r in
   closed form from (r, F_r) and (r - 1, F_r - fg), and writes d loss_c / d p = sign(p - fg) g_r at the pixel's
   original place (the sort's index; 0 on ignored pixels, sign(0) = 0 as in torch, the sign from the key's flags
   and its level 0); each tile also sums that over its foreground keys. The loss is then sum_pixels d * (p - fg) =
   sum d p - sum_fg d (the caller, in pixel order: no gather of p in sorted order). Every (class, pixel) is written
   by one thread, the sums are tile reductions and torch sums: deterministic.

Layouts: probabilities and the gradient [B, K, H, W] (any strides: a channels-last or strided view is read in
place; the op gives the gradient class planes, which keep each class's scattered writes within the L2 cache),
labels [B, H, W] int32, keys [K * Q] int32, order [K * Q] int64 (the sort's indices c * Q + pixel), counts,
offsets and sums [K * Q / tile] (tile-major), foreground [K] int32. The tile is the launch's block.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def lovasz_keys(
    probabilities: wp.array4d(dtype=Any), labels: wp.array3d(dtype=wp.int32), ignore_index: int, level_bits: int,
    keys: wp.array(dtype=wp.int32),
):
    pixel = wp.tid()
    height = labels.shape[1]
    width = labels.shape[2]
    pixels = labels.shape[0] * height * width
    classes = probabilities.shape[1]
    padded = keys.shape[0] // classes
    levels = (1 << level_bits) - 1
    if pixel >= pixels:  # a class's padding: after all its keys
        for c in range(classes):
            keys[c * padded + pixel] = (c << (level_bits + 2)) | (levels << 2)
        return
    x = pixel % width
    y = (pixel // width) % height
    b = pixel // (width * height)
    label = labels[b, y, x]
    valid = 0
    if label != ignore_index:
        valid = 1
    scale = probabilities.dtype(float(levels))
    for c in range(classes):
        fg = 0
        level = int(0)
        if valid == 1:
            p = probabilities[b, c, y, x]
            error = p
            if label == c:
                fg = 1
                error = probabilities.dtype(1.0) - p
            error = wp.abs(error)
            if error > probabilities.dtype(0.0):
                level = wp.clamp(int(wp.ceil(error * scale)), 1, levels)
        keys[c * padded + pixel] = (c << (level_bits + 2)) | ((levels - level) << 2) | (valid << 1) | fg


@wp.kernel
def lovasz_counts(keys: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32)):
    tile, lane = wp.tid()
    size = wp.block_dim()
    total = wp.tile_sum(wp.tile(keys[tile * size + lane] & 1))
    wp.tile_store(counts, total, offset=tile)


@wp.func
def jaccard_loss(total: Any, rank: Any, seen: Any):
    """J(r, F) = 1 - (G - F) / (G + r - F), J(0, 0) = 0."""
    value = type(total)(0.0)
    if rank > type(total)(0.0):
        value = type(total)(1.0) - (total - seen) / (total + rank - seen)
    return value


@wp.kernel
def lovasz_gradient(
    keys: wp.array(dtype=wp.int32), order: wp.array(dtype=wp.int64), offsets: wp.array(dtype=wp.int32),
    foreground: wp.array(dtype=wp.int32), level_bits: int, gradient: wp.array4d(dtype=Any),
    sums: wp.array(dtype=Any),
):
    tile, lane = wp.tid()
    size = wp.block_dim()
    classes = gradient.shape[1]
    height = gradient.shape[2]
    width = gradient.shape[3]
    pixels = gradient.shape[0] * height * width
    padded = keys.shape[0] // classes
    index = tile * size + lane
    key = keys[index]
    fg = key & 1
    seen_here = wp.untile(wp.tile_scan_inclusive(wp.tile(fg)))
    c = index // padded
    zero = gradient.dtype(0.0)
    total = gradient.dtype(float(foreground[c]))
    rank = gradient.dtype(float(index - c * padded + 1))
    seen = gradient.dtype(float(offsets[tile] + seen_here))
    step = jaccard_loss(total, rank, seen) - jaccard_loss(total, rank - gradient.dtype(1.0),
                                                          seen - gradient.dtype(float(fg)))
    levels = (1 << level_bits) - 1
    value = zero
    if (key & 2) != 0 and ((key >> 2) & levels) != levels:  # valid, e > 0: d e / d p = +1 (background), -1 (fg)
        value = step
        if fg == 1:
            value = -step
    pixel = int(order[index]) - c * padded
    if pixel < pixels:
        x = pixel % width
        y = (pixel // width) % height
        b = pixel // (width * height)
        gradient[b, c, y, x] = value
    foreground_value = zero
    if fg == 1:
        foreground_value = value
    wp.tile_store(sums, wp.tile_sum(wp.tile(foreground_value)), offset=tile)


for _float in (wp.float32, wp.float64):
    _maps = wp.array4d(dtype=_float)
    wp.overload(lovasz_keys, [_maps, wp.array3d(dtype=wp.int32), int, int, wp.array(dtype=wp.int32)])
    wp.overload(lovasz_gradient, [wp.array(dtype=wp.int32), wp.array(dtype=wp.int64), wp.array(dtype=wp.int32),
                                  wp.array(dtype=wp.int32), int, _maps, wp.array(dtype=_float)])
