"""Lens files (JSON) and the pupil-FFT PSF model (docs/references.md, convention 3).

A lens file gives first-order data (focal length, f-number, field of view, pixel pitch), three wavelengths, the
PSF kernel size and grid, and Zernike coefficients (Noll index) each with a field dependence
c_j(h) = constant + linear * h + quadratic * h^2 in the normalised field height h in [0, 1] (0 on axis, 1 at the
image corner). Coefficients are given in the meridional frame of each field point (the pupil frame is rotated by
the field azimuth), as for a rotationally symmetric lens: coma points radially, astigmatism is sagittal/tangential.

Chromatic behaviour: the coefficients are waves at ``reference_wavelength_um`` (default: the middle,
green wavelength), i.e. an optical path difference OPD = c * lambda_ref that every wavelength shares; at wavelength
lambda the phase is OPD / lambda waves. ``axial_color_waves`` adds per-channel defocus (Noll 4, waves at the
reference wavelength: longitudinal chromatic aberration) and ``lateral_color`` a per-channel relative
magnification (0.001: that channel's image is 0.1% larger, its PSF moves outward by 0.001 x the image height; a
radial tilt, Noll 2, at that wavelength). ``max_energy_outside`` (optional) replaces ``psf_kernel_size`` by the
smallest odd K that leaves at most that fraction of every node's energy outside the kernel (measured within a
63-pixel window; `Lens.energy_outside`).
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from warpsense.files import located
from warpsense.optics.zernike import noll_to_nm, radial_polynomial, zernike, zernike_nm
from warpsense.resources import CONFIG_DIR

REQUIRED_KEYS = {
    "name": str, "focal_length_mm": float, "f_number": float, "diagonal_fov_deg": float, "pixel_pitch_um": float,
    "wavelengths_um": list, "psf_kernel_size": int, "psf_grid": list, "zernike_waves": dict,
}
OPTIONAL_KEYS = {
    "description": (str, ""), "aspect_ratio": (float, 4.0 / 3.0), "oversampling": (int, 5),
    "pupil_samples": (int, 64), "learnable_bound_waves": (float, 0.25), "reference_wavelength_um": (float, None),
    "axial_color_waves": (list, [0.0, 0.0, 0.0]), "lateral_color": (list, [0.0, 0.0, 0.0]),
    "max_energy_outside": (float, None),
}
FIELD_TERMS = ("constant", "linear", "quadratic")
# bounds that keep a lens's rendering within memory (a 1001-pixel kernel or 512-node grid would ask for 10s of GB)
MAX_KERNEL_SIZE, MAX_GRID, MAX_OVERSAMPLING, MAX_PUPIL_SAMPLES = 101, 33, 31, 512
ENERGY_WINDOW = 63  # pixels: the rendering that "energy outside K" is measured against


class LensFileError(ValueError):
    """A lens file is malformed; the message names the file and the key."""


@dataclass
class LensSpec:
    name: str
    focal_length_mm: float
    f_number: float
    diagonal_fov_deg: float
    pixel_pitch_um: float
    wavelengths_um: tuple[float, float, float]
    psf_kernel_size: int
    psf_grid: tuple[int, int]
    zernike_waves: dict[int, tuple[float, float, float]]
    description: str = ""
    aspect_ratio: float = 4.0 / 3.0
    oversampling: int = 5
    pupil_samples: int = 64
    learnable_bound_waves: float = 0.25
    reference_wavelength_um: float | None = None
    axial_color_waves: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lateral_color: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_energy_outside: float | None = None

    def __post_init__(self):
        if self.reference_wavelength_um is None:
            self.reference_wavelength_um = self.wavelengths_um[1]

    @property
    def sensor_diagonal_mm(self) -> float:
        return 2 * self.focal_length_mm * math.tan(math.radians(self.diagonal_fov_deg) / 2)


def _typed(value, expected, where):
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, expected) or isinstance(value, bool):
        raise LensFileError(f"{where}: expected {expected.__name__}, got {value!r}")
    return value


def parse_lens(data: dict, source: str) -> LensSpec:
    """Validate a decoded lens file; every error names ``source`` and the key."""
    if not isinstance(data, dict):
        raise LensFileError(f"{source}: top level must be a JSON object")
    unknown = set(data) - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS)
    if unknown:
        valid = ", ".join(sorted(set(REQUIRED_KEYS) | set(OPTIONAL_KEYS)))
        raise LensFileError(f"{source}: unknown key {sorted(unknown)[0]!r}; valid keys: {valid}")
    values = {}
    for key, expected in REQUIRED_KEYS.items():
        if key not in data:
            raise LensFileError(f"{source}: missing required key {key!r}")
        values[key] = _typed(data[key], expected, f"{source}: {key}")
    for key, (expected, default) in OPTIONAL_KEYS.items():
        if data.get(key, default) is not None:
            values[key] = _typed(data.get(key, default), expected, f"{source}: {key}")
    for key in ("focal_length_mm", "f_number", "pixel_pitch_um", "aspect_ratio"):
        if not values[key] > 0:
            raise LensFileError(f"{source}: {key} must be > 0, got {values[key]}")
    if not 0 < values["diagonal_fov_deg"] < 180:
        raise LensFileError(f"{source}: diagonal_fov_deg must be in (0, 180), got {values['diagonal_fov_deg']}")
    wavelengths = values["wavelengths_um"]
    if len(wavelengths) != 3 or not all(isinstance(w, (int, float)) and 0.2 < w < 2.0 for w in wavelengths):
        raise LensFileError(f"{source}: wavelengths_um must be 3 wavelengths (R, G, B) in um, got {wavelengths}")
    values["wavelengths_um"] = tuple(float(w) for w in wavelengths)
    eps = values.get("max_energy_outside")
    if eps is not None and not 0 < eps <= 0.5:
        raise LensFileError(f"{source}: max_energy_outside must be in (0, 0.5], got {eps}")
    reference = values.get("reference_wavelength_um")
    if reference is not None and not 0.2 < reference < 2.0:
        raise LensFileError(f"{source}: reference_wavelength_um must be a wavelength in um, got {reference}")
    for key, limit in (("axial_color_waves", 5.0), ("lateral_color", 0.05)):
        triple = values[key]
        if len(triple) != 3 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and abs(v) <= limit
                                       for v in triple):
            raise LensFileError(f"{source}: {key} must be 3 numbers (R, G, B) of magnitude <= {limit}, got {triple}")
        values[key] = tuple(float(v) for v in triple)
    size = values["psf_kernel_size"]
    if not 1 <= size <= MAX_KERNEL_SIZE or size % 2 == 0:
        raise LensFileError(f"{source}: psf_kernel_size must be an odd int in 1..{MAX_KERNEL_SIZE}, got {size}")
    grid = values["psf_grid"]
    if len(grid) != 2 or not all(isinstance(g, int) and not isinstance(g, bool) and 1 <= g <= MAX_GRID
                                 for g in grid):
        raise LensFileError(f"{source}: psf_grid must be [Gy, Gx] with ints in 1..{MAX_GRID}, got {grid}")
    values["psf_grid"] = tuple(grid)
    if not 1 <= values["oversampling"] <= MAX_OVERSAMPLING or values["oversampling"] % 2 == 0:
        raise LensFileError(f"{source}: oversampling must be an odd int in 1..{MAX_OVERSAMPLING}, "
                            f"got {values['oversampling']}")
    if not 8 <= values["pupil_samples"] <= MAX_PUPIL_SAMPLES:
        raise LensFileError(f"{source}: pupil_samples must be in 8..{MAX_PUPIL_SAMPLES}, got {values['pupil_samples']}")
    for key in ("focal_length_mm", "f_number", "pixel_pitch_um", "learnable_bound_waves"):
        if not math.isfinite(values[key]) or values[key] > 1e4:
            raise LensFileError(f"{source}: {key} must be a finite value <= 1e4, got {values[key]}")
    if values["learnable_bound_waves"] < 0:
        raise LensFileError(f"{source}: learnable_bound_waves must be >= 0 (waves), got "
                            f"{values['learnable_bound_waves']}")
    terms = {}
    for index, entry in values["zernike_waves"].items():
        where = f"{source}: zernike_waves.{index}"
        if not index.isdigit() or not 1 <= int(index) <= 36:
            raise LensFileError(f"{where}: keys must be Noll indices 1..36")
        if not isinstance(entry, dict) or set(entry) - set(FIELD_TERMS):
            raise LensFileError(f"{where}: must be an object with keys among {', '.join(FIELD_TERMS)}")
        terms[int(index)] = tuple(float(_typed(entry.get(t, 0.0), float, f"{where}.{t}")) for t in FIELD_TERMS)
        if not all(math.isfinite(v) and abs(v) <= 100 for v in terms[int(index)]):
            raise LensFileError(f"{where}: coefficients must be finite waves of magnitude <= 100")
    values["zernike_waves"] = dict(sorted(terms.items()))
    return LensSpec(**values)


def lens_path(name_or_path: str | Path) -> Path:
    """A lens name from configs/lenses/ or a path to a JSON file."""
    path = Path(name_or_path)
    if path.suffix == ".json" or path.exists():
        return path
    packaged = CONFIG_DIR / "lenses" / f"{name_or_path}.json"
    if packaged.is_file():
        return Path(str(packaged))
    names = sorted(p.name[:-5] for p in (CONFIG_DIR / "lenses").iterdir() if p.name.endswith(".json"))
    raise LensFileError(f"lens {str(name_or_path)!r}: no such file or packaged lens; packaged: {', '.join(names)}")


def read_lens_spec(name_or_path: str | Path) -> LensSpec:
    """Read and validate a lens file (a packaged name or a path); every failure is a one-line `LensFileError`
    naming the file."""
    path = lens_path(name_or_path)
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as error:
        raise LensFileError(f"{located(path)}: cannot read: {error.strerror}") from None
    except UnicodeDecodeError:
        raise LensFileError(f"{path}: not UTF-8 text") from None
    except (ValueError, RecursionError) as error:  # JSONDecodeError, 5000-digit numbers, deep nesting
        first_line = str(error).splitlines()[0][:200] if str(error) else ""
        raise LensFileError(f"{path}: invalid JSON: {first_line or 'too deeply nested'}") from None
    return parse_lens(data, str(path))


def pupil_psf(
    coefficients: torch.Tensor, noll: list[int], azimuth: torch.Tensor, pupil_samples: float, zero_padding: float,
    pupil_radius: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """|FFT{P exp(i 2 pi W)}|^2 on an M x M grid, M = round(D * Q), centred at M // 2, each summing to 1.

    Args:
        coefficients: [N, J] Zernike coefficients (waves) for N field points, on the pupil in use.
        noll: the J Noll indices.
        azimuth: [N] field azimuth (radians); the pupil frame is rotated to it.
        pupil_samples: D, samples across the pupil diameter the grid is sized for (need not be an integer).
        zero_padding: Q = M / D; image-plane samples are lambda * F#_grid / Q apart.
        pupil_radius: r in (0, 1]: the pupil in use as a fraction of that diameter (a stopped-down aperture,
            F# = F#_grid / r), with an edge one sample wide so that r takes gradients; None: the hard unit pupil.
    """
    size = int(round(pupil_samples * zero_padding))
    dtype = coefficients.dtype
    axis = (torch.arange(size, dtype=dtype, device=coefficients.device) - size // 2) / (pupil_samples / 2)
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    rho = torch.sqrt(x * x + y * y)
    if isinstance(pupil_radius, torch.Tensor):
        pupil_radius = pupil_radius.to(dtype)
    if pupil_radius is None:
        aperture = (rho <= 1.0).to(dtype)
    else:  # antialiased edge: the fraction of a sample inside the radius, linear in r
        aperture = ((pupil_radius - rho) * (pupil_samples / 2) + 0.5).clamp(0.0, 1.0)
        rho = rho / pupil_radius
    theta = torch.atan2(y, x)[None] - azimuth.to(dtype)[:, None, None]
    rho_clamped = rho.clamp(max=1.0)[None]
    wavefront = torch.zeros(coefficients.shape[0], size, size, dtype=dtype, device=coefficients.device)
    for column, j in enumerate(noll):
        wavefront = wavefront + coefficients[:, column, None, None] * zernike(j, rho_clamped, theta)
    field = aperture * torch.exp(1j * 2 * math.pi * wavefront)
    spectrum = torch.fft.fftshift(torch.fft.fft2(torch.fft.ifftshift(field, dim=(-2, -1))), dim=(-2, -1))
    intensity = spectrum.real**2 + spectrum.imag**2
    return intensity / intensity.sum(dim=(-2, -1), keepdim=True)


class Lens(nn.Module):
    """A lens from a JSON file; `psf_grid()` renders its PSFs at the sensor pixel pitch, differentiably.

    Learnable Zernike coefficients are bounded: c = c_file + bound * tanh(p), p initialised at 0.
    """

    def __init__(self, spec: LensSpec, learnable: bool = False):
        super().__init__()
        self.spec = spec
        self.noll = list(spec.zernike_waves)
        table = torch.tensor([spec.zernike_waves[j] for j in self.noll], dtype=torch.float64).reshape(-1, 3)
        self.register_buffer("base_coefficients", table)
        self.offset = nn.Parameter(torch.zeros_like(table), requires_grad=learnable)
        if spec.max_energy_outside is not None:  # K chosen from the energy the kernel may leave out
            spec.psf_kernel_size = self.kernel_size_for(spec.max_energy_outside, max_size=ENERGY_WINDOW)

    def extra_repr(self) -> str:
        spec = self.spec
        return (f"{spec.name!r}, f={spec.focal_length_mm:g} mm, f/{spec.f_number:g}, {spec.diagonal_fov_deg:g} deg, "
                f"pitch {spec.pixel_pitch_um:g} um, K={spec.psf_kernel_size}, grid={spec.psf_grid[0]}x"
                f"{spec.psf_grid[1]}, learnable={self.offset.requires_grad}")

    @classmethod
    def from_json(cls, path: str | Path, learnable: bool = False) -> "Lens":
        return cls(read_lens_spec(path), learnable=learnable)

    def coefficients(self) -> torch.Tensor:
        """[J, 3] (constant, linear, quadratic) field-dependence coefficients in waves."""
        return self.base_coefficients + self.spec.learnable_bound_waves * torch.tanh(self.offset)

    def field_points(self, grid: tuple[int, int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised field height h [Gy*Gx] and azimuth [Gy*Gx] of the grid nodes.

        The nodes cover the whole field, edges and corners included (node n at n / (G - 1) of each axis; the
        convention of `warpsense.ops.psf.node_axis`), so the corner PSF is rendered at h = 1; G = 1 is on axis.
        Computed once per grid and device (read-only tensors: a training step renders the grid every time)."""
        grid_y, grid_x = grid or self.spec.psf_grid
        device = self.base_coefficients.device
        return _kept(_grid_points, grid_y, grid_x, float(self.spec.aspect_ratio), device)

    def field_coefficients(self, field_height: torch.Tensor) -> torch.Tensor:
        """[N, J] Zernike coefficients at normalised field heights [N]."""
        coefficients = self.coefficients()
        powers = torch.stack([torch.ones_like(field_height), field_height, field_height**2], dim=1)
        return powers.to(coefficients.dtype) @ coefficients.T

    def wavelength_coefficients(self, coefficients: torch.Tensor, field_height: torch.Tensor,
                                channel: int) -> tuple[torch.Tensor, list[int]]:
        """Zernike coefficients [N, J'] in waves at the channel's wavelength, and their Noll indices: the reference
        coefficients scaled by lambda_ref / lambda, plus the channel's axial colour (Noll 4) and lateral colour
        (Noll 2: a radial tilt of 4 a lambda F# um for a coefficient of a waves)."""
        spec = self.spec
        wavelength = spec.wavelengths_um[channel]
        scale = spec.reference_wavelength_um / wavelength
        waves, noll = coefficients * scale, list(self.noll)
        half_diagonal_um = spec.sensor_diagonal_mm * 500.0
        # decided on the lens file's numbers, not on device values: rendering stays free of host reads (CUDA graphs)
        extra = {}
        if spec.axial_color_waves[channel] != 0:
            extra[4] = spec.axial_color_waves[channel] * scale * torch.ones_like(field_height)
        if spec.lateral_color[channel] != 0:
            extra[2] = spec.lateral_color[channel] * half_diagonal_um * field_height / (4 * wavelength * spec.f_number)
        for index, column in extra.items():
            column = column.to(waves.dtype)[:, None]
            if index in noll:
                position = noll.index(index)
                waves = torch.cat([waves[:, :position], waves[:, position : position + 1] + column,
                                   waves[:, position + 1 :]], dim=1)
            else:
                waves, noll = torch.cat([waves, column], dim=1), noll + [index]
        return waves, noll

    def energy_outside(self, kernel_size: int | None = None, grid: tuple[int, int] | None = None,
                       reference_size: int | None = None) -> torch.Tensor:
        """[3, Gy, Gx] fraction of each node PSF's energy that falls outside the K x K kernel (K = ``kernel_size``,
        default the lens's), measured on a rendering ``reference_size`` pixels wide (default 4 K + 1). psf_grid
        renormalises the K window, so this is the light the kernel moves from the tail into the core."""
        size = kernel_size or self.spec.psf_kernel_size
        wide = reference_size or 4 * size + 1
        start = (wide - size) // 2
        with torch.no_grad():
            psf = self.psf_grid(grid, kernel_size=wide)
        inside = psf[..., start : start + size, start : start + size].sum(dim=(-2, -1))
        return 1 - inside / psf.sum(dim=(-2, -1))

    def kernel_size_for(self, energy_outside: float, grid: tuple[int, int] | None = None,
                        max_size: int = 63) -> int:
        """The smallest odd K whose window leaves at most ``energy_outside`` of every node's energy outside
        (rendered once at ``max_size``); ``max_size`` if none does."""
        with torch.no_grad():
            psf = self.psf_grid(grid, kernel_size=max_size)
        total = psf.sum(dim=(-2, -1))
        for size in range(1, max_size + 1, 2):
            start = (max_size - size) // 2
            inside = psf[..., start : start + size, start : start + size].sum(dim=(-2, -1))
            if bool((1 - inside / total <= energy_outside).all()):
                return size
        return max_size

    def pixel_integration_error(self, oversampling: int, reference: int = 15,
                                grid: tuple[int, int] | None = None) -> float:
        """Largest L1 distance (a fraction of the unit energy) between node PSFs integrated over each pixel with
        ``oversampling`` x ``oversampling`` samples and with ``reference`` x ``reference`` (the midpoint rule
        converges as O(1 / oversampling^2))."""
        with torch.no_grad():
            coarse = self.psf_grid(grid, oversampling=oversampling)
            fine = self.psf_grid(grid, oversampling=reference)
        return float((coarse - fine).abs().sum(dim=(-2, -1)).max())

    def psf_at(
        self, field_height: torch.Tensor, azimuth: torch.Tensor, sample_pitch_um: float | None = None,
        kernel_size: int | None = None, oversampling: int | None = None,
        f_number: torch.Tensor | float | None = None, grid_f_number: float | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> torch.Tensor:
        """[3, N, K, K] PSFs at N field points, integrated over pixels of ``sample_pitch_um`` (default: the
        sensor pitch) from an ``oversampling``-times finer diffraction sampling, each summing to 1.

        ``f_number`` (a float or a scalar tensor that takes gradients) renders the lens stopped down or opened up
        from the file's F#0: the pupil radius scales by F#0 / F# (diffraction grows with F#), and each wavefront term
        of radial order n by (F#0 / F#)^n (an aberration of the pupil's edge, seen on a smaller pupil). The FFT grid
        is sized for ``grid_f_number`` (default: ``f_number`` when a float, else the file's), which must be <= every
        F# rendered on it; the pupil in use is a fraction grid_F# / F# of the grid's.

        Each channel is rendered by `render_pixels` (the pupil's support only, one basis shared by the nodes, the
        pixels as two matrix products: the numbers of `pupil_psf` + `integrate_pixels` at a fraction of the work).
        The pupil FFT is computed in ``dtype`` (float32: complex64 transforms, about twice as fast as float64 on a CPU
        and accurate to ~1e-6 of the energy, far below the K-window and grid errors; gradchecks use float64). Its size
        is rounded up to a 5-smooth number (`fast_fft_size`) by sampling the pupil slightly more finely, which
        keeps the image-plane spacing lambda F# / Q exact: sizes such as 239 (prime) or 265 (5 x 53) would run
        through Bluestein's algorithm at several times the cost."""
        spec = self.spec
        pitch = sample_pitch_um or spec.pixel_pitch_um
        size = kernel_size or spec.psf_kernel_size
        factor = oversampling or spec.oversampling
        # as the lens file's psf_kernel_size: an even K rendered the PSF half a pixel off its kernel's centre
        if isinstance(size, bool) or not isinstance(size, int) or size < 1 or size % 2 == 0:
            raise ValueError(f"Lens.psf_at: kernel_size must be an odd int >= 1 (the PSF centred on the middle "
                             f"pixel), got {size!r}")
        coefficients = self.field_coefficients(field_height).to(dtype)
        stopped = f_number is not None
        if not stopped:
            grid_f_number = spec.f_number
        elif grid_f_number is None:
            grid_f_number = spec.f_number if isinstance(f_number, torch.Tensor) else float(f_number)
        per_wavelength = []
        for channel, wavelength in enumerate(spec.wavelengths_um):
            # sample spacing lambda F# / Q = pitch / factor  ->  Q = lambda F# factor / pitch
            padding = wavelength * grid_f_number * factor / pitch
            waves, noll = self.wavelength_coefficients(coefficients, field_height, channel)
            radius = None
            if stopped:
                ratio = spec.f_number / f_number  # pupil radius relative to the file's
                # powers of a device scalar: no host-to-device copy (the step may be captured in a CUDA graph)
                ratio = torch.as_tensor(ratio, dtype=waves.dtype)
                if noll:
                    waves = waves * torch.stack([ratio ** noll_to_nm(j)[0] for j in noll])
                radius = grid_f_number / f_number
            samples = fast_fft_size(round(pupil_samples_for(spec.pupil_samples, padding, size, factor) * padding))
            per_wavelength.append(render_pixels(waves, noll, azimuth, samples / padding, padding, size, factor, radius))
        psf = torch.stack(per_wavelength)
        return psf / psf.sum(dim=(-2, -1), keepdim=True)

    def forward(self, field_height: torch.Tensor, azimuth: torch.Tensor, **options) -> torch.Tensor:
        """Same as `psf_at` (so `torch.func.functional_call` can swap the coefficients)."""
        return self.psf_at(field_height, azimuth, **options)

    # rendered eagerly under torch.compile: inductor (torch 2.11) cannot lower its complex pupil FFTs; the grid is
    # small (a few ms per step), the image-sized work is in psf_conv
    @torch.compiler.disable
    def psf_grid(self, grid: tuple[int, int] | None = None, **options) -> torch.Tensor:
        """[3, Gy, Gx, K, K] PSFs at the grid nodes (corners included, `field_points`), each summing to 1 (float64).
        ``options`` (kernel_size, oversampling, sample_pitch_um) go to `psf_at`."""
        grid_y, grid_x = grid or self.spec.psf_grid
        if not all(isinstance(g, int) and not isinstance(g, bool) and g >= 1 for g in (grid_y, grid_x)):
            raise ValueError(f"Lens.psf_grid: grid must be (Gy, Gx) with ints >= 1, got {grid!r}")
        height, azimuth = self.field_points((grid_y, grid_x))
        psf = self.psf_at(height, azimuth, **options)
        size = psf.shape[-1]
        return psf.reshape(3, grid_y, grid_x, size, size)


def render_pixels(
    coefficients: torch.Tensor, noll: list[int], azimuth: torch.Tensor, pupil_samples: float, zero_padding: float,
    size: int, factor: int, pupil_radius: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """``integrate_pixels(pupil_psf(...), size, factor)`` at the cost it needs: [N, K, K] pixel-integrated PSFs
    (not normalised: `Lens.psf_at` normalises the K x K window), the same numbers to rounding (tested in float64).

    Three identities make it cheap, so that a learnable lens's rendering in each training step is a few passes over
    the M x M grid instead of ~30 forward and ~60 backward (each node's wavefront, rolls, transforms):

    - The wavefront is built on the pupil's support only (~D + 5 samples wide against M = D Q): the aperture is
      zero beyond it, and ``fft2(..., s=(M, M))`` zero-pads.
    - The field azimuth rotates coefficients, not images: Z_j(rho, theta - a) for a cosine/sine pair of azimuthal
      order m mixes the pair's unrotated images by cos(m a) and sin(m a), so the N nodes' wavefronts are one
      [N, B] x [B, S^2] product with B basis images shared by all nodes.
    - |DFT|^2 does not change under a circular shift of the input or of the output: no ifftshift of the pupil and
      no fftshift of the intensity, and the pixel centres are read at (k - K // 2) * factor mod M. The box filter of
      `integrate_pixels` (multiplying the spectrum by sinc) is a circular convolution with b = IDFT(sinc), so the
      K x K pixels are B I B^T with B[k, x] = b[(c_k - x) mod M]: two matrix products read the intensity once.

    The aperture, basis images and B depend on the geometry alone and are kept between calls (`_pupil_basis`,
    `_box_matrix`), except for a ``pupil_radius`` tensor (a learnable f-number), whose gradient runs through them.
    """
    samples = int(round(pupil_samples * zero_padding))
    dtype, device = coefficients.dtype, coefficients.device
    orders = {}  # (n, |m|) -> {+1: cosine column, -1: sine column}, in the order of first appearance
    for column, j in enumerate(noll):
        n, m = noll_to_nm(j)
        orders.setdefault((n, abs(m)), {})[1 if m >= 0 else -1] = column
    geometry = (samples, float(pupil_samples), tuple(orders), dtype, device)
    if isinstance(pupil_radius, torch.Tensor):
        aperture, images = _pupil_basis(*geometry, pupil_radius.to(dtype))
    else:
        aperture, images = _kept(_cached_pupil_basis, *geometry, pupil_radius)
    weights = _basis_weights(coefficients, azimuth.to(dtype), orders)
    width = aperture.shape[-1]
    wavefront = (weights @ images).reshape(-1, width, width)
    field = aperture * torch.exp(1j * 2 * math.pi * wavefront)
    spectrum = torch.fft.fft2(field, s=(samples, samples))
    intensity = torch.view_as_real(spectrum).square().sum(dim=-1)  # [N, M, M], zero frequency at index 0
    box = _kept(_box_matrix, samples, factor, size, dtype, device)
    return box @ intensity @ box.T


# The geometry caches below are unbounded on purpose: a captured CUDA graph holds their tensors' addresses, and an
# entry evicted after a capture would free memory the graph still reads. A process meets a handful of geometries
# (the accuracy suite's sweeps a few dozen, each at most a few MB).
@functools.cache
def _grid_points(grid_y: int, grid_x: int, aspect: float, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """`Lens.field_points` of a Gy x Gx grid on a frame of ``aspect`` (width / height)."""
    half_w, half_h = aspect / 2, 0.5

    def axis(nodes, half):
        if nodes == 1:
            return torch.zeros(1, dtype=torch.float64, device=device)
        return (torch.arange(nodes, dtype=torch.float64, device=device) / (nodes - 1) - 0.5) * 2 * half

    with torch.inference_mode(False), torch.no_grad():
        y, x = torch.meshgrid(axis(grid_y, half_h), axis(grid_x, half_w), indexing="ij")
        height = torch.sqrt(x * x + y * y) / math.hypot(half_w, half_h)
        return height.reshape(-1), torch.atan2(y, x).reshape(-1)


def _kept(cached, *key):
    """``cached(*key)`` (a `functools.cache` of geometry tensors), but computed afresh while a CUDA graph is being
    captured: kernels are recorded then, not run, so a tensor first made during capture holds its values only inside
    that graph's replays."""
    device = next(item for item in key if isinstance(item, torch.device))
    if device.type == "cuda" and torch.cuda.is_current_stream_capturing():
        return cached.__wrapped__(*key)
    return cached(*key)


def _pupil_basis(samples: int, pupil_samples: float, orders: tuple, dtype: torch.dtype, device: torch.device,
                 pupil_radius: torch.Tensor | float | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The aperture [S, S] on the pupil's support and the unrotated basis images [B, S * S] of the (n, |m|)
    ``orders`` (one image for m = 0, a cosine and a sine image otherwise), Noll-normalised as `zernike`."""
    # the support: the aperture (its antialiased edge included) is zero beyond rho = r + 1 / D, r <= 1 but for a
    # float radius given above 1; within the M x M grid's indices -M // 2 .. M - 1 - M // 2 about its centre
    extent = pupil_radius if isinstance(pupil_radius, float) and pupil_radius > 1 else 1.0
    reach = math.ceil(extent * pupil_samples / 2) + 2
    low, high = max(-reach, -(samples // 2)), min(reach, samples - 1 - samples // 2)
    axis = torch.arange(low, high + 1, dtype=dtype, device=device) / (pupil_samples / 2)
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    rho = torch.sqrt(x * x + y * y)
    if pupil_radius is None:
        aperture = (rho <= 1.0).to(dtype)
    else:  # antialiased edge, as in pupil_psf
        aperture = ((pupil_radius - rho) * (pupil_samples / 2) + 0.5).clamp(0.0, 1.0)
        rho = rho / pupil_radius
    theta = torch.atan2(y, x)
    rho = rho.clamp(max=1.0)
    # in the order of `_basis_weights`: the m = 0 images, the pairs' cosine images, then their sine images
    round_, cosines, sines = [], [], []
    for n, m in orders:
        radial = radial_polynomial(n, m, rho)
        if m == 0:
            round_.append(zernike_nm(n, 0, rho, theta, radial))
        else:
            cosines.append(zernike_nm(n, m, rho, theta, radial))
            sines.append(zernike_nm(n, -m, rho, theta, radial))
    images = round_ + cosines + sines
    images = torch.stack(images).flatten(1) if images else aperture.new_zeros(0, aperture.numel())
    return aperture, images


def _basis_weights(coefficients: torch.Tensor, azimuth: torch.Tensor, orders: dict) -> torch.Tensor:
    """[N, B] weights of `_pupil_basis`'s images at each node: the m = 0 coefficients as they are, and each
    cosine/sine pair of order m rotated by the node's azimuth a, c cos(m (t - a)) + s sin(m (t - a)) =
    (c cos ma - s sin ma) cos mt + (c sin ma + s cos ma) sin mt; a term without its partner has a zero partner.
    All pairs at once (a few kernels, not a few per pair: a training step launches them on every rendering)."""
    count = coefficients.shape[0]
    round_ = [coefficients[:, columns[1]] for (_, m), columns in orders.items() if m == 0]
    blocks = [torch.stack(round_, dim=1)] if round_ else []
    pairs = [(m, columns) for (_, m), columns in orders.items() if m != 0]
    if pairs:
        zero = coefficients.new_zeros(count)
        cosine = torch.stack([coefficients[:, columns[1]] if 1 in columns else zero for _, columns in pairs], dim=1)
        sine = torch.stack([coefficients[:, columns[-1]] if -1 in columns else zero for _, columns in pairs], dim=1)
        orders_m = [m for m, _ in pairs]
        angle = azimuth[:, None] * torch.arange(1, max(orders_m) + 1, dtype=azimuth.dtype, device=azimuth.device)
        every_cos, every_sin = torch.cos(angle), torch.sin(angle)  # [N, max m]: column k - 1 is order k
        turn_cos = torch.stack([every_cos[:, m - 1] for m in orders_m], dim=1)
        turn_sin = torch.stack([every_sin[:, m - 1] for m in orders_m], dim=1)
        blocks += [cosine * turn_cos - sine * turn_sin, cosine * turn_sin + sine * turn_cos]
    return torch.cat(blocks, dim=1) if blocks else coefficients.new_zeros(count, 0)


@functools.cache
def _cached_pupil_basis(*geometry) -> tuple[torch.Tensor, torch.Tensor]:
    """`_pupil_basis` for a geometry without gradients, computed once: plain tensors even when first asked for
    under inference mode (evaluation), so that training may use them later."""
    with torch.inference_mode(False), torch.no_grad():
        return _pupil_basis(*geometry)


@functools.cache
def _box_matrix(samples: int, factor: int, size: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """B [K, M]: row k is b = IDFT(sinc(f)), the box of one pixel band-limited to the M-point grid (``factor``
    samples per pixel), centred at pixel k's centre (k - K // 2) * factor mod M."""
    with torch.inference_mode(False), torch.no_grad():
        frequency = torch.fft.fftfreq(samples, d=1.0 / factor, dtype=dtype, device=device)  # cycles per pixel
        box = torch.fft.ifft(torch.sinc(frequency).to(torch.promote_types(dtype, torch.complex64))).real
        centres = (torch.arange(size, device=device) - size // 2) * factor
        rows = torch.arange(samples, device=device)
        return box[(centres[:, None] - rows[None, :]) % samples]


def fast_fft_size(n: int) -> int:
    """The smallest 5-smooth integer (2^a 3^b 5^c) >= n: an FFT size that runs as radix-2/3/5 passes."""
    size = max(int(n), 1)
    while True:
        rest = size
        for prime in (2, 3, 5):
            while rest % prime == 0:
                rest //= prime
        if rest == 1:
            return size
        size += 1


def pupil_samples_for(pupil_samples: int, zero_padding: float, kernel_size: int, factor: int) -> int:
    """Samples across the pupil for a K x K kernel: the lens's D, raised where its image-plane window is too small.

    The FFT's image plane spans D * lambda * F# (M = D * Q samples lambda F# / Q apart), whatever the padding Q, so a
    kernel wider than that window needs a larger D; raising Q instead would shrink the sample spacing below
    pitch / factor and magnify the PSF. Needs M >= K * factor + 2 (`integrate_pixels`)."""
    return max(pupil_samples, math.ceil((kernel_size * factor + 2) / zero_padding))


def integrate_pixels(fine: torch.Tensor, size: int, factor: int) -> torch.Tensor:
    """Integrate a centred fine PSF [N, M, M] (``factor`` samples per pixel) over square pixels: [N, K, K].

    The intensity PSF is band-limited (cutoff 1 / (lambda F#)), so once the fine grid samples it at Nyquist or finer
    the box filter of a pixel is exact in the frequency domain: multiply the spectrum by sinc(f * pitch) along each
    axis, transform back and read the pixel centres (the fine grid's centre sample M // 2 is the centre of the
    middle pixel). The block sum of ``factor`` x ``factor`` samples (the midpoint rule) would converge only as
    O(1 / factor^2). The caller sizes M >= K * factor + 2."""
    samples = fine.shape[-1]
    frequency_row = torch.fft.fftfreq(samples, d=1.0 / factor, dtype=fine.dtype, device=fine.device)  # cycles/pixel
    frequency_col = torch.fft.rfftfreq(samples, d=1.0 / factor, dtype=fine.dtype, device=fine.device)
    box = torch.sinc(frequency_row)[:, None] * torch.sinc(frequency_col)[None, :]
    integrated = torch.fft.irfft2(torch.fft.rfft2(fine) * box, s=(samples, samples))
    centres = samples // 2 + (torch.arange(size, device=fine.device) - size // 2) * factor
    return integrated[:, centres][:, :, centres]
