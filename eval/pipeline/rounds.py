"""`RoundResult`: what one round of the pipeline produced. Its own module because the runner
(`eval.pipeline.run`) creates it and the report (`eval.pipeline.report`) reads it, and the runner
calls the report: neither may import the other's types back."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from eval.pipeline.stage import StageResult

__all__ = ["RoundResult"]


@dataclass(frozen=True)
class RoundResult:
    """One round's stages, by stage name (`denoise` or `select`+`refine`, `align`, `splat`, `render`)."""

    index: int
    dir: Path
    stages: dict[str, StageResult]
