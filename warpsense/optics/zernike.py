"""Zernike polynomials with Noll's indexing and normalisation (Noll 1976, J. Opt. Soc. Am. 66, 207).

Z_j has unit rms over the unit disc, so a coefficient in waves is that term's rms wavefront error in waves.
"""

from __future__ import annotations

import math

import torch


def noll_to_nm(j: int) -> tuple[int, int]:
    """Noll index j >= 1 -> (radial order n, signed azimuthal frequency m); even j are cosines (m > 0)."""
    if j < 1:
        raise ValueError(f"Noll index must be >= 1, got {j}")
    n = 0
    remaining = j - 1
    while remaining > n:
        n += 1
        remaining -= n
    m = (n % 2) + 2 * ((remaining + ((n + 1) % 2)) // 2)
    if m != 0 and j % 2 == 1:
        m = -m
    return n, m


def radial_polynomial(n: int, m: int, rho: torch.Tensor) -> torch.Tensor:
    m = abs(m)
    result = torch.zeros_like(rho)
    for k in range((n - m) // 2 + 1):
        coefficient = (-1) ** k * math.factorial(n - k) / (
            math.factorial(k) * math.factorial((n + m) // 2 - k) * math.factorial((n - m) // 2 - k)
        )
        result = result + coefficient * rho ** (n - 2 * k)
    return result


def zernike(j: int, rho: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Noll-normalised Z_j(rho, theta) on the unit disc (rho in [0, 1], theta in radians)."""
    return zernike_nm(*noll_to_nm(j), rho, theta)


def zernike_nm(n: int, m: int, rho: torch.Tensor, theta: torch.Tensor,
               radial: torch.Tensor | None = None) -> torch.Tensor:
    """Noll-normalised Z_n^m(rho, theta): cos(m theta) for m > 0, sin(|m| theta) for m < 0. ``radial``: R_n^|m|(rho)
    when the caller has it already (a cosine/sine pair shares it)."""
    if radial is None:
        radial = radial_polynomial(n, m, rho)
    radial = math.sqrt(n + 1) * radial
    if m == 0:
        return radial
    angular = torch.cos(m * theta) if m > 0 else torch.sin(-m * theta)
    return math.sqrt(2) * radial * angular


ZERNIKE_NAMES = {
    1: "piston", 2: "tilt x", 3: "tilt y", 4: "defocus", 5: "oblique astigmatism", 6: "vertical astigmatism",
    7: "vertical coma", 8: "horizontal coma", 9: "vertical trefoil", 10: "oblique trefoil", 11: "primary spherical",
    12: "vertical secondary astigmatism", 13: "oblique secondary astigmatism", 14: "vertical quadrafoil",
    15: "oblique quadrafoil",
}
