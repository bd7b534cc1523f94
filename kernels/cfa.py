"""CFA mosaic R(p) = <I(p), phi[p mod T]> (eq. 4 of the paper, docs/references.md) as Warp kernels.

Layouts: rgb [B,3,H,W], phi [T,T,3] (per-site spectral response), raw [B,1,H,W].
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def mosaic_value(rgb: wp.array4d(dtype=Any), phi: wp.array3d(dtype=Any), b: int, y: int, x: int):
    """R(p) = <rgb(p), phi[p mod T]> at pixel (y, x) of image b."""
    tile = phi.shape[0]
    sy = y % tile
    sx = x % tile
    return rgb[b, 0, y, x] * phi[sy, sx, 0] + rgb[b, 1, y, x] * phi[sy, sx, 1] + rgb[b, 2, y, x] * phi[sy, sx, 2]


@wp.func
def mosaic_adjoint(rgb: wp.array4d(dtype=Any), phi: wp.array3d(dtype=Any), b: int, y: int, x: int, site_y: int,
                   site_x: int, g: Any, want_grad_rgb: int, grad_rgb: wp.array4d(dtype=Any)):
    """Adjoint of `mosaic_value` at pixel (y, x) of image b (CFA site (site_y, site_x)) for output gradient g:
    writes d/drgb there (when wanted) and returns the pixel's three terms of d/dphi[site]."""
    if want_grad_rgb != 0:
        grad_rgb[b, 0, y, x] = g * phi[site_y, site_x, 0]
        grad_rgb[b, 1, y, x] = g * phi[site_y, site_x, 1]
        grad_rgb[b, 2, y, x] = g * phi[site_y, site_x, 2]
    return g * rgb[b, 0, y, x], g * rgb[b, 1, y, x], g * rgb[b, 2, y, x]


@wp.func
def site_pixel_count(height: int, width: int, tile: int, site_y: int, site_x: int):
    """(columns, pixels per image) of CFA site (site_y, site_x): the pixels p with p mod T equal to the site."""
    rows = (height - site_y + tile - 1) / tile
    cols = (width - site_x + tile - 1) / tile
    return cols, rows * cols


@wp.func
def site_pixel(m: int, site_y: int, site_x: int, tile: int, cols: int, per_image: int):
    """(image, y, x) of the m-th pixel of a CFA site over the batch (images one after another)."""
    b = m / per_image
    r = m - b * per_image
    return b, site_y + (r / cols) * tile, site_x + (r % cols) * tile


@wp.kernel
def cfa_forward(rgb: wp.array4d(dtype=Any), phi: wp.array3d(dtype=Any), raw: wp.array4d(dtype=Any)):
    b, y, x = wp.tid()
    raw[b, 0, y, x] = mosaic_value(rgb, phi, b, y, x)


@wp.kernel
def cfa_backward(
    rgb: wp.array4d(dtype=Any),
    phi: wp.array3d(dtype=Any),
    grad_raw: wp.array4d(dtype=Any),
    want_grad_rgb: wp.int32,
    grad_rgb: wp.array4d(dtype=Any),
    phi_partials: wp.array3d(dtype=Any),
):
    """One thread per (CFA site, lane): the lane walks that site's pixels with a stride, writes grad_rgb for each and
    keeps a private sum for grad_phi, stored in phi_partials[site, lane, channel] (summed by the caller), so the
    phi gradient needs no atomics and is deterministic."""
    site, lane = wp.tid()
    tile = phi.shape[0]
    lanes = phi_partials.shape[1]
    sy = site / tile
    sx = site % tile
    cols, per_image = site_pixel_count(rgb.shape[2], rgb.shape[3], tile, sy, sx)
    total = rgb.shape[0] * per_image
    acc0 = rgb.dtype(0.0)
    acc1 = rgb.dtype(0.0)
    acc2 = rgb.dtype(0.0)
    for m in range(lane, total, lanes):
        b, y, x = site_pixel(m, sy, sx, tile, cols, per_image)
        d0, d1, d2 = mosaic_adjoint(rgb, phi, b, y, x, sy, sx, grad_raw[b, 0, y, x], want_grad_rgb, grad_rgb)
        acc0 += d0
        acc1 += d1
        acc2 += d2
    phi_partials[site, lane, 0] = acc0
    phi_partials[site, lane, 1] = acc1
    phi_partials[site, lane, 2] = acc2


for _float in (wp.float32, wp.float64):
    wp.overload(cfa_forward, [wp.array4d(dtype=_float), wp.array3d(dtype=_float), wp.array4d(dtype=_float)])
    wp.overload(
        cfa_backward,
        [
            wp.array4d(dtype=_float),
            wp.array3d(dtype=_float),
            wp.array4d(dtype=_float),
            wp.int32,
            wp.array4d(dtype=_float),
            wp.array3d(dtype=_float),
        ],
    )
