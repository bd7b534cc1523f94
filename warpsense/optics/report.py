"""A lens's numerical budget: how much light its K x K kernel leaves out per node, which K a tolerance needs, and
how far its pixel integration is from converged."""

from __future__ import annotations

from warpsense.optics.lens import Lens
from warpsense.optics.zernike import ZERNIKE_NAMES

ENERGY_TARGETS = (1e-2, 1e-3)
PIXEL_INTEGRATION_TOLERANCE = 0.01  # L1, a fraction of each PSF's unit energy, against 15 x 15 samples per pixel


def lens_report(lens: Lens, max_size: int = 63) -> dict:
    """Energy outside the lens's kernel per node (max over R, G, B), the kernel size each of `ENERGY_TARGETS`
    needs (measured within a ``max_size`` window), the pixel-integration error at the lens's oversampling, and its
    Zernike terms by name (Noll numbering, `ZERNIKE_NAMES`)."""
    spec = lens.spec
    outside = lens.energy_outside(reference_size=max_size).amax(dim=0)
    return {
        "lens": spec.name,
        "kernel_size": spec.psf_kernel_size,
        "grid": list(spec.psf_grid),
        "aberrations": [{"noll": j, "name": ZERNIKE_NAMES.get(j, f"Noll {j}"),
                         "waves": [round(float(v), 5) for v in row]}
                        for j, row in zip(lens.noll, lens.coefficients().detach())],
        "energy_outside_kernel": [[round(float(v), 5) for v in row] for row in outside],
        "kernel_size_for": {str(target): lens.kernel_size_for(target, max_size=max_size) for target in ENERGY_TARGETS},
        "oversampling": spec.oversampling,
        "pixel_integration_l1": round(lens.pixel_integration_error(spec.oversampling), 5),
        "pixel_integration_tolerance": PIXEL_INTEGRATION_TOLERANCE,
    }


def format_report(report: dict) -> str:
    lines = [f"lens {report['lens']}: K = {report['kernel_size']}, {report['grid'][0]}x{report['grid'][1]} PSF grid",
             "Zernike terms in waves (constant, x h, x h^2 over the normalised field height h):"]
    lines += [f"  {term['noll']:2d} {term['name']:<30s}" + "".join(f"{value:9.4f}" for value in term["waves"])
              for term in report["aberrations"]]
    lines += ["energy outside the K x K kernel per node (max over R, G, B; renormalised into the core):"]
    lines += ["  " + "  ".join(f"{value:7.4f}" for value in row) for row in report["energy_outside_kernel"]]
    for target, size in report["kernel_size_for"].items():
        lines.append(f"kernel size for <= {float(target):g} outside at every node: {size}")
    verdict = "meets" if report["pixel_integration_l1"] <= report["pixel_integration_tolerance"] else "misses"
    lines.append(f"pixel integration: {report['oversampling']}x{report['oversampling']} samples per pixel, L1 "
                 f"{report['pixel_integration_l1']:.4f} against 15x15 ({verdict} the "
                 f"{report['pixel_integration_tolerance']:g} tolerance)")
    return "\n".join(lines)
