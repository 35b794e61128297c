"""Wall-clock time per step, recorded in order: the one timer of ffrecon (pipeline stages, and the
steps inside COLMAP, refinement and the splat)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass, field


@dataclass
class StageTimer:
    """Collects ``(stage, seconds)`` in the order the stages ran.

    >>> timer = StageTimer()
    >>> with timer.stage("work"):
    ...     pass
    >>> timer.freeze().stages[0][0]
    'work'
    """

    _stages: list[tuple[str, float]] = field(default_factory=list)

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self._stages.append((name, time.perf_counter() - start))

    def add(self, name: str, seconds: float) -> None:
        """Record a time measured elsewhere (e.g. the optimiser's own clock, which leaves out callbacks)."""
        self._stages.append((name, float(seconds)))

    def freeze(self) -> "Timings":
        return Timings(tuple(self._stages))


@dataclass(frozen=True)
class Timings:
    """Seconds per stage; a stage that ran twice appears twice."""

    stages: tuple[tuple[str, float], ...] = ()

    @property
    def total_s(self) -> float:
        return float(sum(s for _, s in self.stages))

    def seconds(self, name: str) -> float:
        """Total seconds spent in stages called ``name`` (0 if none)."""
        return float(sum(s for n, s in self.stages if n == name))

    def to_report(self) -> dict:
        out: dict[str, float] = {}
        for name, seconds in self.stages:
            out[name] = round(out.get(name, 0.0) + seconds, 4)
        out["total"] = round(self.total_s, 4)
        return out
