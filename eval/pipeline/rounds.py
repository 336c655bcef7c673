"""`RoundResult`: what one round of the pipeline produced. Its own module because the runner
(`eval.pipeline.run`) creates it and the report (`eval.pipeline.report`) reads it, and the runner
calls the report: neither may import the other's types back."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from eval.pipeline.stage import StageResult

__all__ = ["RoundResult", "StoppedRound"]


@dataclass(frozen=True)
class RoundResult:
    """One round's stages, by stage name (`denoise` or `select`+`refine`, `align`, `splat`, `render`)."""

    index: int
    dir: Path
    stages: dict[str, StageResult]


@dataclass(frozen=True)
class StoppedRound:
    """A round the loop stopped after its refine stage (`PipelineConfig.stop_when_unrefined`): the guard
    kept the previous round's network, so the round would only splat again a subset of the previous
    round's own photos. The previous round's reconstruction is the result.

    Attributes:
        index: the round's number.
        dir: its folder (holding `selection.json` and the refine stage's outputs).
        stages: the stages it ran (`select`, `refine`).
        reason: why it stopped, in words (with the guard's losses).
    """

    index: int
    dir: Path
    stages: dict[str, StageResult]
    reason: str
