"""Colour filter array stage C (eq. 4 of the paper, docs/references.md): filters, layouts, learnable responses, the
temperature's annealing, hard export."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from warpsense.camera.stage import SensorArguments, Stage
from warpsense.choices import CFA_FILTERS, CFA_LAYOUTS, CFA_MODES
from warpsense.config import CFAConfig
from warpsense.ops.cfa import cfa_mosaic

FILTERS = {"R": (1.0, 0.0, 0.0), "G": (0.0, 1.0, 0.0), "B": (0.0, 0.0, 1.0), "C": (1.0, 1.0, 1.0),
           "Y": (1.0, 1.0, 0.0)}
"""Filter transmittances per band (R, G, B), each in [0, 1]: C (clear) passes all three bands (RCCC / RCCB automotive
sensors), Y (yellow) passes red and green (RYYB phone sensors). In a flat white field a clear pixel collects 3x the
light of a green one and a yellow pixel 2x."""
assert tuple(FILTERS) == tuple(CFA_FILTERS)

UNDECIDED = "?"
"""The letter of a site whose candidates tie (`CFA.hard_letters` with ``undecided``): no filter chosen yet."""

UNDECIDED_COLOUR = (0.5, 0.5, 0.5)
"""How plots draw an undecided site."""


def text_colour(background) -> str:
    """Black or white, whichever reads on ``background`` (RGB in [0, 1]): by its luma (ITU-R BT.601 weights), so
    that a letter on a green or yellow filter is black and one on red or blue is white."""
    red, green, blue = background[:3]
    return "black" if 0.299 * red + 0.587 * green + 0.114 * blue > 0.45 else "white"


def layout_letters(pattern: str, tile: int) -> list[list[str]]:
    """T x T filter letters of a 2x2 layout tiled (and cropped) to a T x T tile."""
    if pattern not in CFA_LAYOUTS:
        raise KeyError(f"unknown CFA layout {pattern!r}; valid layouts: {', '.join(CFA_LAYOUTS)}")
    rows = CFA_LAYOUTS[pattern]
    return [[rows[y % 2][x % 2] for x in range(tile)] for y in range(tile)]


def letters_to_phi(letters: list[list[str]]) -> torch.Tensor:
    """[T, T, 3] responses of a layout given as rows of letters (`FILTERS`), e.g. [["R", "G"], ["G", "B"]] (any
    rows x columns: [1, K, 3] for one row of K candidates).

    Raises:
        TypeError: one string: a flat "RGGB", as `LearnedCamera.cfa_layout` spells a layout, would be read as four
            rows of one letter ([4, 1, 3]); `layout_letters` gives the rows.
        ValueError: rows of different lengths.
        KeyError: a letter that is not a filter, naming the filters.
    """
    if isinstance(letters, str):
        raise TypeError(f"letters_to_phi: letters must be rows of letters (e.g. [['R', 'G'], ['G', 'B']]), got the "
                        f"string {letters!r} (layout_letters({letters!r}, 2) gives its rows)")
    rows = [list(row) for row in letters]
    if len({len(row) for row in rows}) > 1:
        raise ValueError(f"letters_to_phi: rows of letters must be equally long, got {letters!r}")
    unknown = sorted({letter for row in rows for letter in row} - set(FILTERS), key=str)
    if unknown:
        raise KeyError(f"letters_to_phi: unknown filter letter {unknown[0]!r}; filters: {', '.join(FILTERS)}")
    return torch.tensor([[FILTERS[letter] for letter in row] for row in rows], dtype=torch.float32)


def check_candidates(candidates: str, pattern: str, mode: str) -> str | None:
    """Why ``candidates`` (filter letters a learned CFA chooses among) cannot start at ``pattern`` in ``mode``, or
    None."""
    unknown = sorted(set(candidates) - set(FILTERS))
    if unknown:
        return f"unknown filter letter {unknown[0]!r}; filters: {', '.join(FILTERS)}"
    if len(set(candidates)) != len(candidates) or len(candidates) < 2:
        return f"needs at least two different letters, got {candidates!r}"
    missing = sorted(set("".join(CFA_LAYOUTS[pattern])) - set(candidates))
    if mode in ("softmax", "gumbel") and missing:
        return f"the layout {pattern} uses {missing[0]!r}, which is not a candidate ({candidates})"
    return None


def annealed_temperature(schedule, epoch: int, start: float, end: float) -> float:
    """The softmax / gumbel temperature at ``epoch`` (0-based) of ``schedule`` (a `warpsense.train.schedule.Schedule`):
    ``start`` through warm-up, then geometric annealing through the joint phase that reaches ``end`` at the last
    epoch (a joint phase of one epoch is at ``end``)."""
    if not schedule.is_joint(epoch):
        return start
    joint_epochs = schedule.epochs - schedule.warmup_epochs
    if joint_epochs <= 1:
        return end
    progress = min(epoch - schedule.warmup_epochs, joint_epochs - 1) / (joint_epochs - 1)
    return start * (end / start) ** progress


class CFA(Stage):
    """Learnable colour filter array producing phi [T, T, 3] and the RAW mosaic.

    Modes:
        softmax: phi[site] = sum_k softmax(logits[site] / temperature)_k * filter_k over the candidate filters (a
            learned choice of filter per site, annealed towards one-hot; `hard_letters()` exports the argmax).
        gumbel: an exploring choice (Jang et al. 2017, "Categorical reparameterization with Gumbel-softmax"): in
            training each site takes the one-hot filter argmax(logits / temperature + Gumbel noise) in the forward
            pass and the gradient of softmax(logits / temperature + noise) in the backward pass (straight-through),
            a new draw every step: at temperature 1 a site's filter is drawn with probability softmax(logits), so
            filters the start does not favour are tried, and as the temperature anneals the draws commit to the
            argmax, which eval uses. Start it uniform (``init_logit = 0``) or at a layout.
        free: phi[site] = sigmoid(raw[site]): any transmittance in [0, 1] per band, initialised at the layout.
        fixed: phi is the layout, not learnable.
    """

    config_section = "cfa"
    takes, gives = "rgb", "raw"

    def __init__(self, pattern: str = CFAConfig.pattern, tile: int = CFAConfig.tile, mode: str = CFAConfig.mode,
                 init_logit: float = CFAConfig.init_logit, temperature_start: float = CFAConfig.temperature_start,
                 temperature_end: float = CFAConfig.temperature_end, candidates: str = CFAConfig.candidates):
        """Args:
            pattern, tile: the layout the responses start at (a `CFA_LAYOUTS` name) tiled to T x T.
            mode: a `CFA_MODES` name (see the class docstring).
            init_logit: softmax and gumbel modes: the starting logit of each site's layout filter (the others 0).
            temperature_start, temperature_end: softmax / gumbel temperature through warm-up and at the last epoch
                (`on_epoch` anneals geometrically between them through the joint phase: `annealed_temperature`).
            candidates: the filter letters (`FILTERS`) a softmax or gumbel CFA chooses among, in logit order.
        """
        super().__init__()
        if mode not in CFA_MODES:
            raise KeyError(f"unknown CFA mode {mode!r}; valid modes: {', '.join(CFA_MODES)}")
        if tile < 1:
            raise ValueError(f"CFA tile must be >= 1, got {tile}")
        letters = layout_letters(pattern, tile)
        problem = check_candidates(candidates, pattern, mode)
        if problem:
            raise ValueError(f"CFA candidates: {problem}")
        self.mode = mode
        self.tile = tile
        self.filter_names = tuple(candidates)
        self.temperature_plan = (float(temperature_start), float(temperature_end))
        self.register_buffer("candidates", letters_to_phi([list(self.filter_names)])[0])  # [K, 3]
        self.register_buffer("temperature", torch.tensor(float(temperature_start)))
        if mode in ("softmax", "gumbel"):
            index = torch.tensor([[self.filter_names.index(letter) for letter in row] for row in letters])
            self.logits = nn.Parameter(F.one_hot(index, len(self.filter_names)).float() * init_logit)
        elif mode == "free":
            self.responses = nn.Parameter(torch.logit(letters_to_phi(letters).clamp(1e-3, 1 - 1e-3)))
        else:
            self.register_buffer("fixed_phi", letters_to_phi(letters))

    @classmethod
    def check_section(cls, section, where: str) -> None:
        problem = check_candidates(section.candidates, section.pattern, section.mode)
        if problem:
            raise ValueError(f"{where}: cfa.candidates: {problem}")

    def summary(self) -> dict:
        """The exported layout (letters row by row, e.g. "RGGB"), the layout as chosen so far ("cfa_choice": "?"
        where a site's top candidates tie, as they all do at a uniform start, whose export is only the argmax's
        first candidate), the responses phi [T, T, 3] in use (a gumbel CFA: its exported layout's) and the
        temperature."""
        phi = self.hard_phi() if self.mode == "gumbel" else self.phi()
        return {"cfa_layout": "".join("".join(row) for row in self.hard_letters()),
                "cfa_choice": "".join("".join(row) for row in self.hard_letters(undecided=UNDECIDED)),
                "cfa_phi": phi.detach().cpu().tolist(), "temperature": float(self.temperature)}

    def on_epoch(self, schedule, epoch: int) -> None:
        """Anneal the temperature along the plan (`annealed_temperature`)."""
        self.temperature.fill_(annealed_temperature(schedule, epoch, *self.temperature_plan))

    def fuse(self, arguments: SensorArguments) -> bool:
        arguments.phi = self.phi()
        return True

    def phi(self) -> torch.Tensor:
        """[T, T, 3] current spectral responses (a gumbel CFA in training: a new draw per call)."""
        if self.mode == "softmax":
            return torch.softmax(self.logits / self.temperature, dim=-1) @ self.candidates
        if self.mode == "gumbel":
            if not self.training:
                return self.hard_phi()
            uniform = torch.rand_like(self.logits).clamp(1e-10, 1 - 1e-7)
            soft = torch.softmax(self.logits / self.temperature - torch.log(-torch.log(uniform)), dim=-1)
            hard = F.one_hot(soft.argmax(dim=-1), soft.shape[-1]).to(soft.dtype)
            return (hard - soft.detach() + soft) @ self.candidates
        if self.mode == "free":
            return torch.sigmoid(self.responses)
        return self.fixed_phi

    def hard_letters(self, undecided: str | None = None) -> list[list[str]]:
        """The exported layout: argmax filter per site (softmax, gumbel), nearest candidate by cosine (free), or
        fixed.

        Args:
            undecided: if given, the letter for a site whose top two logits are equal (softmax, gumbel), where the
                argmax names the first of the tied candidates as if it had been chosen.
        """
        if self.mode in ("softmax", "gumbel"):
            index = self.logits.argmax(dim=-1)
        else:
            phi = self.phi().detach()
            cosine = F.normalize(phi, dim=-1) @ F.normalize(self.candidates, dim=-1).T
            index = cosine.argmax(dim=-1)
        letters = [[self.filter_names[int(k)] for k in row] for row in index]
        if undecided is not None and self.mode in ("softmax", "gumbel"):
            top = self.logits.detach().topk(2, dim=-1).values
            for y, x in (top[..., 0] == top[..., 1]).nonzero().tolist():
                letters[y][x] = undecided
        return letters

    def choice_weights(self) -> torch.Tensor | None:
        """[T, T] the weight of each site's exported filter in the responses in use (softmax: its softmax
        probability at the current temperature), or None for modes without a choice among candidates."""
        if self.mode != "softmax":
            return None
        return torch.softmax(self.logits.detach() / self.temperature, dim=-1).amax(dim=-1)

    def hard_phi(self) -> torch.Tensor:
        return letters_to_phi(self.hard_letters()).to(self.candidates.device)

    def forward(self, image: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 3, H, W] -> RAW [B, 1, H, W]."""
        return cfa_mosaic(image, self.phi())

    def draw(self, axis) -> None:
        """Each site as the colour of its responses in use, over a strip in its exported filter's colour with the
        exported letter (and, for a softmax CFA, that filter's weight in the mix): a site still mixing its
        candidates shows a colour unlike its letter's, and the strip and weight say so instead of contradicting it.
        """
        from matplotlib.patches import Rectangle

        phi = self.phi().detach().cpu().numpy()
        axis.imshow((phi / max(float(phi.max()), 1e-6)).clip(0, 1), interpolation="nearest")
        weights = self.choice_weights()
        for y, row in enumerate(self.hard_letters(undecided=UNDECIDED)):
            for x, letter in enumerate(row):
                colour = FILTERS.get(letter, UNDECIDED_COLOUR)
                axis.add_patch(Rectangle((x - 0.5, y + 0.1), 1.0, 0.4, facecolor=colour, edgecolor="0.3", lw=0.5))
                text = letter if weights is None else f"{letter} {float(weights[y, x]):.0%}"
                axis.text(x, y + 0.3, text, ha="center", va="center", fontsize=11, color=text_colour(colour))
        axis.set_title("CFA: responses in use (colours);\nexported filter per site (strips)", fontsize=10)
