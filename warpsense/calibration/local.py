"""Local noise samples of one CFA site plane: what a single capture's fit reads.

The plane (the pixels of one site of the CFA tile, so that the colour pattern is no edge) is cut into 3 x 3 blocks.
With u0 = (1, 1, 1) / sqrt 3, u1 = (1, 0, -1) / sqrt 2 and u2 = (1, -2, 1) / sqrt 6, each block gives:

- its mean ``m`` (the box filter u0 u0^T, over 3): an estimate of the local signal;
- its detail coefficients sum(f * block) for the four detail filters f = u1 u1^T, u1 u2^T, u2 u1^T, u2 u2^T. The
  four are orthonormal, and orthogonal to the box, so under Gaussian noise of variance v the coefficients are
  independent N(0, v), independent of m. Each is a product of two zero-sum factors, so each annihilates every
  signal of the form f(x) + g(y): rows, columns, horizontal and vertical edges, gradients; only corners, curvature
  across both axes and fine texture leak signal into them. They play the part of the wavelet detail coefficients of
  Foi et al. 2008 (section IV). The sample's energy ``e`` is the square of the u2 u2^T one (`CENTRE`, E[e] = v);
  the other three give the block's own roughness (`OWN`), which the choice of samples reads; at the lower clip the
  four `SIDES` filters (a box along one axis) join them (``energy_black``).

A sample is a block with its ring, the 8 blocks around it (a 9 x 9 window). The ring's mean gives the sample's
level, and the ring's mean detail energy its roughness; neither shares a pixel with the centre block, so choosing
samples by level and roughness does not bias the centre's energy. Samples sit on every other block position
(stride 2): neighbouring blocks then overlap by a third, so their energies are nearly independent
(`STRIDE_CORRELATION`), and the grid costs a quarter of every position's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

_U1 = np.array([1.0, 0.0, -1.0]) / np.sqrt(2.0)
_U2 = np.array([1.0, -2.0, 1.0]) / np.sqrt(6.0)
DETAILS = [np.outer(a, b) for a in (_U1, _U2) for b in (_U1, _U2)]
"""The 4 detail filters: orthonormal, zero-sum along both axes."""
_U0 = np.ones(3) / np.sqrt(3.0)
SIDES = [np.outer(a, b) for a, b in ((_U0, _U1), (_U1, _U0), (_U0, _U2), (_U2, _U0))]
"""The 4 other zero-sum filters of the block's orthonormal basis (a box along one axis, a detail along the other):
with `DETAILS` every direction but the mean. They pass a gradient or an edge along one axis, so they are read only
where a set lies at the lower clip (`energy_black`), where there is little signal to pass and the clipped noise
needs every degree of freedom."""

CENTRE = [3]
"""The detail filters of a sample's energy: u2 u2^T alone, the one that leaks least texture (a third of the others'
on CamVid frames, whose own sensor noise is texture to the simulated one)."""
DEGREES = len(CENTRE)
"""Degrees of freedom of a block's detail energy: v * chi-square(DEGREES) / DEGREES under the noise alone."""
RING_DETAILS = [0, 1, 2, 3]
"""The detail filters of the ring's roughness and of a sample's ``energy_all``: all four."""
OWN = [k for k in RING_DETAILS if k not in CENTRE]
"""The centre's other detail filters (u1 u1^T, u1 u2^T, u2 u1^T): its own roughness, ``own``. Under Gaussian noise
their coefficients are independent of the centre's energy (orthonormal filters), so a choice by them does not bias
it, and they see the texture of the very block whose energy is measured, which its ring may not."""

STRIDE = 2
"""Samples every STRIDE block positions along each axis."""

RING = [(dy, dx) for dy in (-3, 0, 3) for dx in (-3, 0, 3) if (dy, dx) != (0, 0)]
"""The 8 blocks around a sample's centre block (offsets in pixels): they tile its 9 x 9 window with it."""


def _overlap_factor(stride: int, filters: list[int] = CENTRE, bank: list[np.ndarray] = DETAILS) -> float:
    """The variance of a mean of n sample energies (samples ``stride`` apart on a grid, Gaussian noise of variance
    v) is 2 v^2 / n times this: 1 / DEGREES for independent samples, more for overlapping blocks. Under Gaussian
    noise cov(d_k(p)^2, d_l(q)^2) = 2 v^2 c_kl(p - q)^2, c_kl the filters' cross-correlation."""
    total = 0.0
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            if dy % stride or dx % stride:
                continue
            for first in (bank[k] for k in filters):
                for second in (bank[k] for k in filters):
                    shifted = np.zeros((7, 7))
                    shifted[2 + dy:5 + dy, 2 + dx:5 + dx] = second
                    padded = np.zeros((7, 7))
                    padded[2:5, 2:5] = first
                    total += float(np.sum(padded * shifted)) ** 2
    return total / len(filters) ** 2


STRIDE_CORRELATION = _overlap_factor(STRIDE)
"""2 v^2 / n times this is the variance of a mean of n sample energies STRIDE apart."""
STRIDE_CORRELATION_ALL = _overlap_factor(STRIDE, RING_DETAILS)
"""The same for ``energy_all``, the mean square of all four detail coefficients."""
STRIDE_CORRELATION_BLACK = _overlap_factor(STRIDE, list(range(8)), DETAILS + SIDES)
"""The same for ``energy_black``, the mean square of all eight zero-sum coefficients."""


@dataclass
class PlaneSamples:
    """The samples of one site plane (1-D arrays of one length): centre block ``mean`` and detail ``energy``, ring
    ``level`` and ring ``roughness``; ``rows``, ``cols``: the centre block's top-left pixel in the plane;
    ``energy_all``: the centre's mean square over all four detail filters (4 degrees of freedom), which sets near
    a clip read, where texture is faint and the clipped noise has few distinct values; ``own``: the centre's mean
    square over the `OWN` filters; ``energy_black``: over all eight zero-sum filters (`DETAILS` and `SIDES`).
    ``level``, ``roughness``: the ring's."""

    mean: np.ndarray
    energy: np.ndarray
    level: np.ndarray
    roughness: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    energy_all: np.ndarray
    own: np.ndarray
    energy_black: np.ndarray

    @classmethod
    def empty(cls) -> "PlaneSamples":
        return cls(*(np.zeros(0) for _ in range(4)), np.zeros(0, int), np.zeros(0, int),
                   *(np.zeros(0) for _ in range(3)))

    def __len__(self) -> int:
        return int(self.mean.size)


def plane_samples(plane: np.ndarray, lower: float, upper: float, step: float) -> PlaneSamples:
    """Every sample of ``plane`` (float, [h, w], white-level units) whose ring is not wholly clipped.

    A ring all at a clip bound (a saturated sky, a clipped shadow) carries no noise to read; it is left out by its
    ring alone, never by the centre's own values (which would bias the centre's energy).
    """
    plane = np.asarray(plane, dtype=np.float64)
    height, width = plane.shape
    rows = np.arange(3, height - 2 - 3, STRIDE)
    cols = np.arange(3, width - 2 - 3, STRIDE)
    if rows.size == 0 or cols.size == 0:
        return PlaneSamples.empty()
    # block statistics at every top-left position (valid correlations: [h - 2, w - 2])
    means = ndimage.uniform_filter(plane, 3, mode="constant")[1:-1, 1:-1]
    squares = [ndimage.correlate(plane, f, mode="constant")[1:-1, 1:-1] ** 2 for f in DETAILS]
    energies = sum(squares[k] for k in CENTRE) / DEGREES
    rough = sum(squares[k] for k in RING_DETAILS) / len(RING_DETAILS)
    own = sum(squares[k] for k in OWN) / len(OWN)
    grid_rows, grid_cols = (grid.ravel() for grid in np.meshgrid(rows, cols, indexing="ij"))
    # every zero-sum coefficient's square, at the samples only (the four side filters serve sets at the clip)
    black = (sum(square[grid_rows, grid_cols] for square in squares)
             + sum(ndimage.correlate(plane, f, mode="constant")[1:-1, 1:-1][grid_rows, grid_cols] ** 2
                   for f in SIDES)) / 8
    level = np.zeros(grid_rows.size)
    roughness = np.zeros(grid_rows.size)
    for dy, dx in RING:
        level += means[grid_rows + dy, grid_cols + dx]
        roughness += rough[grid_rows + dy, grid_cols + dx]
    level /= len(RING)
    roughness /= len(RING)
    margin = 1e-6 * step + 1e-12  # every ring pixel at the clip code
    keep = (level > lower + margin) & (level < upper - margin)
    return PlaneSamples(means[grid_rows, grid_cols][keep], energies[grid_rows, grid_cols][keep], level[keep],
                        roughness[keep], grid_rows[keep], grid_cols[keep], rough[grid_rows, grid_cols][keep],
                        own[grid_rows, grid_cols][keep], black[keep])
