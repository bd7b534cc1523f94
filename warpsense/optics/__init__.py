"""Lens files, Zernike pupil PSFs and PSF-grid utilities (docs/references.md, convention 3)."""

from warpsense.optics.lens import Lens, LensFileError, LensSpec, integrate_pixels, parse_lens, pupil_psf
from warpsense.optics.psf_support import collapse_grid, crop_to_energy
from warpsense.optics.zernike import noll_to_nm, zernike

__all__ = [
    "Lens", "LensFileError", "LensSpec", "collapse_grid", "crop_to_energy", "integrate_pixels", "noll_to_nm",
    "parse_lens", "pupil_psf", "zernike",
]
