"""Colour filter array stage C (paper eq. 4): layouts, learnable responses, hard export."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from warpsense.camera.stage import SensorArguments, Stage
from warpsense.choices import CFA_LAYOUTS, CFA_MODES
from warpsense.ops.cfa import cfa_mosaic

# Candidate filters as RGB transmissions. "C" (clear) passes all three bands, as on RCCC automotive sensors.
FILTERS = {"R": (1.0, 0.0, 0.0), "G": (0.0, 1.0, 0.0), "B": (0.0, 0.0, 1.0), "C": (1.0, 1.0, 1.0)}
FILTER_NAMES = tuple(FILTERS)


def layout_letters(pattern: str, tile: int) -> list[list[str]]:
    """T x T filter letters of a 2x2 layout tiled (and cropped) to a T x T tile."""
    if pattern not in CFA_LAYOUTS:
        raise KeyError(f"unknown CFA layout {pattern!r}; valid layouts: {', '.join(CFA_LAYOUTS)}")
    rows = CFA_LAYOUTS[pattern]
    return [[rows[y % 2][x % 2] for x in range(tile)] for y in range(tile)]


def letters_to_phi(letters: list[list[str]]) -> torch.Tensor:
    """[T, T, 3] responses of a layout given as letters (R, G, B, C)."""
    return torch.tensor([[FILTERS[letter] for letter in row] for row in letters], dtype=torch.float32)


class CFA(Stage):
    """Learnable colour filter array producing phi [T, T, 3] and the RAW mosaic.

    Modes:
        softmax: phi[site] = sum_k softmax(logits[site] / temperature)_k * filter_k over the candidates R, G, B, C
            (a learned choice of filter per site, annealed towards one-hot; `hard_letters()` exports the argmax).
        free: phi[site] = softplus(raw[site]) (any non-negative response), initialised at the layout.
        fixed: phi is the layout, not learnable.
    """

    config_section = "cfa"
    takes, gives = "rgb", "raw"

    def __init__(self, pattern: str = "RGGB", tile: int = 2, mode: str = "softmax", init_logit: float = 4.0,
                 temperature_start: float = 1.0, temperature_end: float = 1.0):
        """Args:
            pattern, tile: the layout the responses start at (a `CFA_LAYOUTS` name) tiled to T x T.
            mode: a `CFA_MODES` name (see the class docstring).
            init_logit: softmax mode: the starting logit of each site's layout filter (the others 0).
            temperature_start, temperature_end: softmax temperature through warm-up and at the last epoch
                (`on_epoch` anneals geometrically between them through the joint phase).
        """
        super().__init__()
        if mode not in CFA_MODES:
            raise KeyError(f"unknown CFA mode {mode!r}; valid modes: {', '.join(CFA_MODES)}")
        if tile < 1:
            raise ValueError(f"CFA tile must be >= 1, got {tile}")
        self.mode = mode
        self.tile = tile
        self.temperature_plan = (float(temperature_start), float(temperature_end))
        letters = layout_letters(pattern, tile)
        self.register_buffer("candidates", letters_to_phi([list(FILTER_NAMES)])[0])  # [K, 3]
        self.register_buffer("temperature", torch.tensor(float(temperature_start)))
        if mode == "softmax":
            index = torch.tensor([[FILTER_NAMES.index(letter) for letter in row] for row in letters])
            self.logits = nn.Parameter(F.one_hot(index, len(FILTER_NAMES)).float() * init_logit)
        elif mode == "free":
            target = letters_to_phi(letters).clamp_min(1e-3)
            self.responses = nn.Parameter(target + torch.log(-torch.expm1(-target)))  # softplus^-1
        else:
            self.register_buffer("fixed_phi", letters_to_phi(letters))

    @classmethod
    def from_config(cls, section) -> "CFA":
        return cls(section.pattern, section.tile, section.mode, section.init_logit, section.temperature_start,
                   section.temperature_end)

    def summary(self) -> dict:
        """The exported layout (letters row by row, e.g. "RGGB"), the responses phi [T, T, 3] in use and the
        softmax temperature."""
        return {"cfa_layout": "".join("".join(row) for row in self.hard_letters()),
                "cfa_phi": self.phi().detach().cpu().tolist(), "temperature": float(self.temperature)}

    def on_epoch(self, schedule, epoch: int) -> None:
        """Anneal the temperature along the plan (`Schedule.temperature`)."""
        self.temperature.fill_(schedule.temperature(epoch, *self.temperature_plan))

    def fuse(self, arguments: SensorArguments) -> bool:
        arguments.phi = self.phi()
        return True

    def phi(self) -> torch.Tensor:
        """[T, T, 3] current spectral responses."""
        if self.mode == "softmax":
            weights = torch.softmax(self.logits / self.temperature, dim=-1)
            return weights @ self.candidates
        if self.mode == "free":
            return F.softplus(self.responses)
        return self.fixed_phi

    def hard_letters(self) -> list[list[str]]:
        """The exported layout: argmax filter per site (softmax), nearest candidate by cosine (free), or fixed."""
        if self.mode == "softmax":
            index = self.logits.argmax(dim=-1)
        else:
            phi = self.phi().detach()
            cosine = F.normalize(phi, dim=-1) @ F.normalize(self.candidates, dim=-1).T
            index = cosine.argmax(dim=-1)
        return [[FILTER_NAMES[int(k)] for k in row] for row in index]

    def hard_phi(self) -> torch.Tensor:
        return letters_to_phi(self.hard_letters()).to(self.candidates.device)

    def forward(self, image: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 3, H, W] -> RAW [B, 1, H, W]."""
        return cfa_mosaic(image, self.phi())

    def draw(self, axis) -> None:
        """The responses as colours with the exported letters."""
        phi = self.phi().detach().cpu().numpy()
        axis.imshow((phi / max(float(phi.max()), 1e-6)).clip(0, 1), interpolation="nearest")
        for y, row in enumerate(self.hard_letters()):
            for x, letter in enumerate(row):
                axis.text(x, y, letter, ha="center", va="center", color="white", fontsize=14)
        axis.set_title("learned CFA (phi, export letters)")
