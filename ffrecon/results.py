"""What a run returns: one frozen, typed result per stage, together a :class:`RunResults`.

A stage that did not run holds a :class:`Skipped` naming why, never a missing key. The report
(``report.json``, ``report.html``) and the command-line summary are built from these results alone
(:mod:`ffrecon.report.build`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path

from ffrecon.capture import Capture
from ffrecon.errors import GateFailed
from ffrecon.export.stage import ExportsResult
from ffrecon.models.stage import FeedForwardResult
from ffrecon.resume import OverlapTiming, StageTiming
from ffrecon.sfm.comparisons import ComparisonsResult
from ffrecon.sfm.crosscheck import ColmapResult
from ffrecon.sfm.evidence import EvidenceResult
from ffrecon.sfm.gates import GatesResult
from ffrecon.sfm.refine import RefineResult
from ffrecon.splat.stage import SplatResult
from ffrecon.types import QUICK_NO_CROSSCHECK, QUICK_STATEMENT, RunMode, Skipped  # noqa: F401 (re-exported)


class Verdict(enum.Enum):
    OK = "ok"
    GATE_FAILED = "gate_failed"


@dataclass(frozen=True)
class RunResults:
    """Everything one run produced, stage by stage."""

    out_dir: Path
    created: str  # ISO time the run started
    command: str
    capture: Capture
    feedforward: FeedForwardResult | Skipped  # Skipped when no model was given
    colmap: ColmapResult | Skipped
    gates: GatesResult | Skipped
    comparisons: ComparisonsResult | Skipped
    refine: RefineResult | Skipped
    evidence: EvidenceResult | Skipped  # the final cameras judged (with a model)
    splat: SplatResult | Skipped
    seed_comparison: SplatResult | Skipped | None  # --compare-seeds: the splat from COLMAP's points; None: not asked
    exports: ExportsResult | Skipped
    timings: tuple[StageTiming, ...]
    forced: bool
    mode: RunMode = RunMode.FULL
    overlaps: tuple[OverlapTiming, ...] = ()  # stages that ran at the same time (their timings overlap)

    @property
    def skipped(self) -> tuple[Skipped, ...]:
        stages = (self.feedforward, self.colmap, self.gates, self.refine, self.evidence, self.comparisons, self.splat)
        stages += (self.exports,)
        return tuple(s for s in stages if isinstance(s, Skipped))

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
