"""What a run returns: the final :class:`~ffrecon.state.RunState` with the run's record, a :class:`RunResults`.

Each stage's result is keyed by the stage's name (typed accessors such as ``results.splat`` for the stages of
:data:`ffrecon.stages.STAGES`); a stage that did not run holds a :class:`Skipped` naming why, never a missing
key. The report (``report.json``, ``report.html``) and the command-line summary are built from these results
alone (:mod:`ffrecon.report.build`), each stage giving its own sections.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass
from pathlib import Path

from ffrecon.errors import GateFailed
from ffrecon.resume import OverlapTiming, StageTiming
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.verify.verdicts import EvidenceResult
from ffrecon.state import Beside, RunState, Stage, each_stage
from ffrecon.types import QUICK_NO_CROSSCHECK, QUICK_STATEMENT, RunMode, Skipped  # noqa: F401 (re-exported)


class Verdict(enum.Enum):
    OK = "ok"
    GATE_FAILED = "gate_failed"


@dataclass(frozen=True, kw_only=True)
class RunResults(RunState):
    """Everything one run produced: the state its stages left (``results``, stage by stage) and the run's record."""

    created: str  # ISO time the run started
    command: str
    timings: tuple[StageTiming, ...]
    forced: bool
    mode: RunMode = RunMode.FULL
    overlaps: tuple[OverlapTiming, ...] = ()  # stages that ran at the same time (their timings overlap)
    stages: tuple[Stage | Beside, ...] = ()  # the stage list that ran: its order, report sections and skips

    @classmethod
    def of(cls, state: RunState, **record) -> RunResults:
        """The final ``state`` with the run's ``record`` (the fields of this class beyond :class:`RunState`'s)."""
        return cls(**{f.name: getattr(state, f.name) for f in dataclasses.fields(RunState)}, **record)

    @property
    def out_dir(self) -> Path:
        """The run folder the results' paths are under."""
        return self.work

    @property
    def skipped(self) -> tuple[Skipped, ...]:
        """The stages that did not run, in run order (those whose skip is routine left out)."""
        results = (self.result(stage.name) for stage in each_stage(self.stages) if stage.listed_skipped)
        return tuple(r for r in results if isinstance(r, Skipped))

    @property
    def gate_results(self) -> tuple[GatesResult, ...]:
        """The gates on COLMAP's model and the capture, then those on the final cameras (those that ran)."""
        evidence = self.evidence.gates if isinstance(self.evidence, EvidenceResult) else None
        return tuple(g for g in (self.gates, evidence) if isinstance(g, GatesResult))

    @property
    def verdict(self) -> Verdict:
        blocked = any(g.blocking for g in self.gate_results)
        return Verdict.GATE_FAILED if blocked else Verdict.OK

    @property
    def exit_code(self) -> int:
        return GateFailed.exit_code if self.verdict is Verdict.GATE_FAILED else 0
