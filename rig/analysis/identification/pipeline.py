"""The identification's vocabulary: what a stage is, and what it says.

A fit is two pipelines of stages:

- the staged identification (`staged.PIPELINE`): each stage reads the runs of its own experiments, solves
  one MODEL.md equation by least squares and hands its answer (`dynamics_stage.Solved`: values, σ,
  notes) to the book, which believes or holds each parameter (`staged.StageEstimate`);
- `identify`'s steps: a starting point (the staged stages' estimates, or what plain runs' columns
  determine), the joint refinement on trajectories with its held-out choice, then validation and report.

A new staged stage is one object with the `Stage` protocol added to `staged.PIPELINE` (its name in
`model.registry.STAGES`, so that the parameters' registry can say which stage determines them).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from model.params import HarmonicDriveModel
from model.run import Run

if TYPE_CHECKING:
    from rig.analysis.identification.staged import Book


@dataclass(frozen=True)
class Note:
    """One sentence a stage says of its data: `stage` tells who, `text` what.

    `str(note)` is the line the report and `--json` carry: the staged identification's stages name
    themselves there ("friction-velocity: …"); `identify`'s own steps (`named=False`) do not."""

    stage: str
    text: str
    named: bool = True

    def __str__(self) -> str:
        return f"{self.stage}: {self.text}" if self.named else self.text


def note_lines(notes: Sequence[Note]) -> list[str]:
    """The notes as the report and `--json` print them."""
    return [str(note) for note in notes]


class Stage(Protocol):
    """One stage of the staged identification."""

    @property
    def name(self) -> str:
        """Its name in `model.registry.STAGES`: the `stage` of the rows it estimates, its notes' prefix."""
        ...

    @property
    def experiments(self) -> tuple[str, ...]:
        """The experiments (`run.meta["experiment"]`) whose runs it reads; none: every run."""
        ...

    def gives(self, model: HarmonicDriveModel) -> list[str]:
        """The parameters it estimates for this model (those it cannot determine are held, with why)."""
        ...

    def run(self, runs: Sequence[Run], book: Book) -> None:
        """Solve on the runs and hand the answer to the book (`Book.accept`), which keeps the model."""
        ...
