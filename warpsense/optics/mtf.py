"""The modulation transfer function of sampled PSFs, and `warpsense lens --plot`: the PSF grid per colour and the MTF
of the on-axis and corner PSFs.

The MTF is |FFT| of the pixel-sampled PSF (zero-padded to `FFT_SIZE` for a fine frequency axis), divided by its value
at DC (the PSF's sum), in cycles per pixel from 0 to the Nyquist frequency 0.5. Since the lens renders each PSF
integrated over the pixel (`warpsense.optics.lens.render_pixels`), it includes the pixel's aperture.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

FFT_SIZE = 256
"""Zero-padded FFT size: frequency steps of 1/256 cycles per pixel."""

COLOURS = ("R", "G", "B")
LINE_COLOURS = ("tab:red", "tab:green", "tab:blue")


def mtf(psf: np.ndarray, size: int = FFT_SIZE) -> dict[str, np.ndarray]:
    """MTF of one sampled PSF [K, K] (rows y, columns x), up to Nyquist.

    Returns:
        {"frequency": [N] cycles/pixel in [0, 0.5], "x": along x (the f_y = 0 row), "y": along y (the f_x = 0
        column), "radial": the mean over the angles of each frequency ring}; each normalised to 1 at DC.
    """
    psf = np.asarray(psf, dtype=np.float64)
    if psf.ndim != 2 or psf.shape[0] != psf.shape[1] or psf.shape[0] < 1:
        raise ValueError(f"mtf: a PSF must be a square [K, K] array, got shape {psf.shape}")
    total = psf.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError(f"mtf: a PSF must have a positive finite sum, got {total}")
    size = max(size, psf.shape[0])
    spectrum = np.abs(np.fft.fft2(psf / total, s=(size, size)))
    half = size // 2
    frequency = np.arange(half + 1) / size
    fy, fx = np.meshgrid(np.fft.fftfreq(size), np.fft.fftfreq(size), indexing="ij")
    ring = np.rint(np.hypot(fy, fx) * size).astype(int)
    inside = ring <= half
    radial = np.bincount(ring[inside], weights=spectrum[inside], minlength=half + 1) / \
        np.maximum(np.bincount(ring[inside], minlength=half + 1), 1)
    return {"frequency": frequency, "x": spectrum[0, : half + 1], "y": spectrum[: half + 1, 0], "radial": radial}


def lens_mtfs(psf_grid: np.ndarray) -> dict[str, list[dict[str, np.ndarray]]]:
    """Per colour, the MTFs (`mtf`) of the on-axis PSF (the grid's centre node; with an even grid the node nearest
    the centre) and of the corner PSF (the last node: the bottom-right corner, field height 1), of a
    [3, Gy, Gx, K, K] PSF grid."""
    grid = np.asarray(psf_grid)
    if grid.ndim != 5 or grid.shape[0] != 3:
        raise ValueError(f"lens_mtfs: expected a [3, Gy, Gx, K, K] PSF grid, got shape {grid.shape}")
    centre = ((grid.shape[1] - 1) // 2, (grid.shape[2] - 1) // 2)
    return {"on-axis": [mtf(grid[c, centre[0], centre[1]]) for c in range(3)],
            "corner": [mtf(grid[c, -1, -1]) for c in range(3)]}


def plot_lens(lens, out_path: str | Path) -> Path:
    """Write the PSF grid of ``lens`` per colour (each node's PSF on a square-root scale, nodes laid out as on the
    sensor) and the MTF of its on-axis and corner PSFs per colour (along x solid, along y dashed), in the format the
    path's suffix names (PNG without one)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warpsense.files import atomic_write, plot_format

    grid = lens.psf_grid().detach().cpu().numpy()
    _, grid_y, grid_x, size, _ = grid.shape
    mtfs = lens_mtfs(grid)
    figure = plt.figure(figsize=(13, 7.5), layout="constrained")
    top, bottom = figure.subfigures(2, 1, height_ratios=[1.1, 1])
    spec = lens.spec
    top.suptitle(f"lens {spec.name}: PSF grid {grid_y}x{grid_x}, K = {size} px (pitch {spec.pixel_pitch_um:g} um, "
                 f"f/{spec.f_number:g}); square-root scale, each node's peak white")
    for colour, axes in enumerate(top.subplots(1, 3)):
        mosaic = np.ones((grid_y * (size + 1) - 1, grid_x * (size + 1) - 1))
        for y in range(grid_y):
            for x in range(grid_x):
                psf = grid[colour, y, x]
                mosaic[y * (size + 1): y * (size + 1) + size, x * (size + 1): x * (size + 1) + size] = \
                    np.sqrt(psf / psf.max())
        axes.imshow(mosaic, cmap="magma", vmin=0, vmax=1, interpolation="nearest")
        axes.set_title(f"{COLOURS[colour]} ({spec.wavelengths_um[colour] * 1000:.0f} nm)")
        axes.set_xticks([])
        axes.set_yticks([])
    bottom.suptitle("MTF (|FFT| of the pixel-integrated PSF): solid along x, dashed along y; Nyquist = 0.5")
    for (where, per_colour), axes in zip(mtfs.items(), bottom.subplots(1, 2, sharey=True)):
        for colour, curves in enumerate(per_colour):
            axes.plot(curves["frequency"], curves["x"], color=LINE_COLOURS[colour], label=f"{COLOURS[colour]} x")
            axes.plot(curves["frequency"], curves["y"], color=LINE_COLOURS[colour], linestyle="--",
                      label=f"{COLOURS[colour]} y")
        axes.set_title(where)
        axes.set_xlim(0, 0.5)
        axes.set_ylim(0, 1.02)
        axes.set_xlabel("spatial frequency (cycles / pixel)")
        axes.grid(alpha=0.3)
    bottom.axes[0].set_ylabel("MTF")
    bottom.axes[0].legend(ncol=3, fontsize=8)
    out_path = Path(out_path)
    with atomic_write(out_path) as temporary:
        figure.savefig(temporary, dpi=110, format=plot_format(out_path))  # the temporary name has no suffix
    plt.close(figure)
    return out_path
