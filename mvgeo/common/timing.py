"""Per-stage wall-clock timing for reports (`with timer.stage("align"): ...`)."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

_log = logging.getLogger(__name__)


@dataclass
class StageTimer:
    """Accumulates seconds per named stage, in first-seen order."""

    seconds: dict[str, float] = field(default_factory=dict)

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            elapsed = time.perf_counter() - start
            self.seconds[name] = self.seconds.get(name, 0.0) + elapsed
            _log.debug("stage %s: %.2f s", name, elapsed)

    def as_dict(self) -> dict[str, float]:
        """Stage name -> seconds, plus `total`."""
        out = {k: round(v, 4) for k, v in self.seconds.items()}
        out["total"] = round(sum(self.seconds.values()), 4)
        return out
