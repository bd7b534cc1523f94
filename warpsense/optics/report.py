"""A lens's numerical budget: how much light its K x K kernel leaves out per node, which K a tolerance needs, and
how far its pixel integration is from converged."""

from __future__ import annotations

from warpsense.optics.lens import Lens
from warpsense.optics.zernike import ZERNIKE_NAMES

ENERGY_TARGETS = (1e-2, 1e-3)
SAMPLING_REFERENCE = 15  # samples per pixel of the rendering the lens's own is compared with


def nyquist_samples(spec) -> float:
    """Samples per pixel at which the bluest channel's intensity PSF is sampled at its Nyquist rate: its spectrum ends
    at 1 / (lambda F#), so samples lambda F# / 2 apart or closer hold all of it, and the pixel's box filter, applied
    as sinc on that spectrum (`warpsense.optics.lens.render_pixels`), integrates exactly."""
    return 2 * spec.pixel_pitch_um / (min(spec.wavelengths_um) * spec.f_number)


def fft_window_pixels(spec) -> float:
    """Width in pixels of the image plane the pupil's FFT spans for the bluest channel (D lambda F#, D = the pupil
    samples): a PSF's tail beyond it wraps around into the kernel."""
    return spec.pupil_samples * min(spec.wavelengths_um) * spec.f_number / spec.pixel_pitch_um


def lens_report(lens: Lens, max_size: int = 63) -> dict:
    """Energy outside the lens's kernel per node (max over R, G, B), the kernel size each of `ENERGY_TARGETS`
    needs (measured within a ``max_size`` window), whether its oversampling integrates pixels exactly
    (`nyquist_samples`), how far its rendering moves from one at `SAMPLING_REFERENCE` samples per pixel, and its
    Zernike terms by name (Noll numbering, `ZERNIKE_NAMES`)."""
    from warpsense.config import OpticsConfig

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
        "default_energy_eps": OpticsConfig().energy_eps,
        "oversampling": spec.oversampling,
        "nyquist_samples": round(nyquist_samples(spec), 3),
        "pixel_integration_exact": spec.oversampling >= nyquist_samples(spec),
        "pupil_samples": spec.pupil_samples,
        "fft_window_pixels": round(fft_window_pixels(spec), 1),
        "sampling_reference": SAMPLING_REFERENCE,
        "sampling_l1": round(lens.pixel_integration_error(spec.oversampling, reference=SAMPLING_REFERENCE), 5),
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
    # what the numbers mean for the camera, and what to change: the K window is a budget of the lens file, which
    # optics.energy_eps (a crop inside the window) cannot enlarge
    worst = max(max(row) for row in report["energy_outside_kernel"])
    kernel, for_one_percent = report["kernel_size"], report["kernel_size_for"].get("0.01")
    lines.append(f"  the K = {kernel} window keeps >= {1 - worst:.1%} of every PSF and moves the rest into it;")
    lines.append(f"  optics.energy_eps (default {report['default_energy_eps']:g}) crops inside the window, it cannot "
                 "widen it")
    if for_one_percent and for_one_percent > kernel:
        lines.append(f"  to keep 99%: psf_kernel_size {for_one_percent} in the lens file, about "
                     f"{(for_one_percent / kernel) ** 2:.1f}x the convolution's cost")
        lines.append("  (`warpsense bench --suite accuracy` gives the image error of each K)")
    verdict = "exact" if report["pixel_integration_exact"] else "NOT exact: raise oversampling in the lens file"
    lines.append(f"pixel integration: the box filter as sinc on the band-limited PSF, {report['oversampling']} "
                 f"samples per pixel")
    lines.append(f"  against the {report['nyquist_samples']:.1f} the bluest channel's band limit needs ({verdict})")
    lines.append(f"pupil sampling: D = {report['pupil_samples']}, an FFT window {report['fft_window_pixels']:.0f} "
                 f"pixels wide; L1 {report['sampling_l1']:.4f} between {report['oversampling']} and "
                 f"{report['sampling_reference']} samples per pixel,")
    lines.append("  whose FFT grids differ (the pupil's stepped edge, and the PSF's tail beyond the window wrapping "
                 "around);")
    lines.append("  raise pupil_samples to lower it, at a higher rendering cost (`warpsense bench --suite accuracy` "
                 "gives its image error)")
    return "\n".join(lines)
