"""`TrainingRestart`: one training run the divergence guard abandoned (`denoise.n2v.optimise_unet`).

Kept free of torch so that readers of recorded stage summaries (`eval.pipeline.summaries`) can parse it
without loading the network code.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

__all__ = ["TrainingRestart"]


@dataclass(frozen=True)
class TrainingRestart:
    """A training run abandoned as diverging and started again from its initial weights at half the rate.

    Attributes:
        step: the step the `denoise.n2v.DivergenceGuard` found the run diverging at.
        lr: the run's peak learning rate (the next run's is half of it).
    """

    step: int
    lr: float

    def to_json(self) -> dict[str, object]:
        """``{"step": int, "lr": float}`` (a stage summary's ``training_restarts`` entry)."""
        return {"step": int(self.step), "lr": float(self.lr)}

    @classmethod
    def from_json(cls, data: Mapping[str, object]) -> TrainingRestart:
        """The record `to_json` wrote.

        Raises:
            KeyError: ``step`` or ``lr`` is missing.
        """
        return cls(step=int(data["step"]), lr=float(data["lr"]))
