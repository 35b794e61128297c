"""The options of a run: one options object per stage (:class:`RunOptions`), and the quick preset.

Defaults live in the stages' option classes alone; the command line only overrides what it is given.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ffrecon.capture import CaptureOptions
from ffrecon.export.stage import ExportOptions
from ffrecon.models.stage import FeedForwardOptions
from ffrecon.sfm.crosscheck.gate_types import GateOptions
from ffrecon.sfm.crosscheck.options import ColmapOptions
from ffrecon.sfm.refine.options import RefineOptions
from ffrecon.sfm.verify.verdicts import EvidenceOptions
from ffrecon.splat.options import SplatOptions
from ffrecon.types import RunMode


@dataclass(frozen=True, kw_only=True)
class RunOptions:
    """What to run, one options object per stage; a stage is turned off by its ``enabled`` field.

    Presets: ``RunOptions()`` (the full run) and :meth:`RunOptions.quick` (``--quick``).
    """

    mode: RunMode = RunMode.FULL  # QUICK: no COLMAP reconstruction (see RunOptions.quick)
    concurrent: bool = True  # run the feed-forward stage and the COLMAP cross-check at the same time
    capture: CaptureOptions = field(default_factory=CaptureOptions)
    feedforward: FeedForwardOptions = field(default_factory=FeedForwardOptions)
    colmap: ColmapOptions = field(default_factory=ColmapOptions)
    gates: GateOptions = field(default_factory=GateOptions)
    refine: RefineOptions = field(default_factory=RefineOptions)
    splat: SplatOptions = field(default_factory=SplatOptions)
    evidence: EvidenceOptions = field(default_factory=EvidenceOptions)
    exports: ExportOptions = field(default_factory=ExportOptions)
    force: bool = False  # go on past failed gates
    overwrite: bool = False  # replace results already in OUT
    resume: bool = False  # reuse the finished stages of OUT (and of an interrupted run) whose inputs are unchanged
    fresh: bool = False  # recompute every stage, ignoring those an interrupted run finished
    ground_truth: Path | None = None  # a synthetic scene folder (ground_truth.json) to score against
    reference: Path | None = None  # a reference COLMAP model to score against
    command: str = ""  # the command line, recorded in the report

    @classmethod
    def quick(cls, **overrides) -> RunOptions:
        """Quick mode (``ffrecon run --quick``): the model's cameras, refined by bundle adjustment, without
        an independent COLMAP reconstruction. Needs a model.

        No incremental or global mapper runs. The refinement extracts SIFT on the frames itself (lighter
        settings: :meth:`RefineOptions.quick`), matches only the pairs the feed-forward cameras and depth
        say overlap, checks those matches against the feed-forward geometry (re-matching guided by it
        when many disagree), triangulates with the feed-forward cameras and bundle-adjusts; then the
        splat. The report says that nothing independent checked the cameras; the gates that need COLMAP
        are skipped. ``overrides`` replace fields of the preset.
        """
        preset = {"mode": RunMode.QUICK, "colmap": ColmapOptions(enabled=False), "refine": RefineOptions.quick()}
        return cls(**{**preset, **overrides})
