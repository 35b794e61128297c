"""The run state and the stage runner of :func:`ffrecon.pipeline.run`.

:class:`RunState` is frozen and typed: one field per stage result, filled as the run goes. A
:class:`Stage` declares the fields it reads (its ``reads``); :class:`StagePlan` derives the stage's
resume key from the keys of those fields (and of the user's files it names), so no key is threaded by
hand: a stage whose reads and options are unchanged is reused (:mod:`ffrecon.resume`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ffrecon.capture import Capture
from ffrecon.concurrency import CoreShare, run_beside
from ffrecon.export.stage import ExportsResult
from ffrecon.final_cameras import FinalCameras
from ffrecon.models.stage import FeedForwardResult
from ffrecon.options import RunOptions
from ffrecon.resume import StageRunner, file_key, stage_key
from ffrecon.sfm.comparisons import ComparisonsResult
from ffrecon.sfm.crosscheck import ColmapResult
from ffrecon.sfm.evidence import EvidenceResult
from ffrecon.sfm.gates import GatesResult
from ffrecon.sfm.refine import RefineResult
from ffrecon.splat.stage import SplatResult
from ffrecon.types import ONE_VIEW, Prediction, Skipped

log = logging.getLogger("ffrecon")


@dataclass(frozen=True)
class RunState:
    """What a run knows so far: its inputs, and each stage's result once it has run (None before; a
    :class:`Skipped` when it did not run)."""

    source: Path  # the photos or the video
    model: Path | None  # the ONNX model, None without one
    work: Path  # the run folder every stage writes under
    capture: Capture | None = None
    feedforward: FeedForwardResult | Skipped | None = None
    colmap: ColmapResult | Skipped | None = None
    sift: Path | Skipped | None = None  # quick mode's SIFT database, extracted beside the inference
    gates: GatesResult | Skipped | None = None
    refine: RefineResult | Skipped | None = None
    evidence: EvidenceResult | Skipped | None = None
    comparisons: ComparisonsResult | Skipped | None = None
    final: FinalCameras | Skipped | None = None
    splat: SplatResult | Skipped | None = None
    seed_comparison: SplatResult | Skipped | None = None  # None: not asked for (--compare-seeds)
    exports: ExportsResult | Skipped | None = None

    @property
    def views(self) -> int:
        """The number of frames captured."""
        return len(self.capture.frames)

    @property
    def model_poses(self) -> np.ndarray | None:
        """The model's own poses (those it gave where the user's replaced them), None without a model."""
        if not isinstance(self.feedforward, FeedForwardResult):
            return None
        own = self.feedforward.model_poses
        return self.feedforward.prediction.cam_from_world if own is None else own

    def references(self, options: RunOptions) -> bool:
        """Cameras to score the run against were given: ground truth, a reference model or --poses."""
        return bool(options.ground_truth or options.reference or self.capture.known_poses)

    @property
    def prediction(self) -> Prediction | None:
        """The model's prediction, None when the feed-forward stage was skipped."""
        return self.feedforward.prediction if isinstance(self.feedforward, FeedForwardResult) else None

    @property
    def verdicts(self) -> tuple[GatesResult | Skipped | None, ...]:
        """The gates that decide whether the splat runs: the capture's and COLMAP's, then the final cameras'."""
        return (self.gates, self.evidence.gates if isinstance(self.evidence, EvidenceResult) else None)

    def why_not(self, *gates: GatesResult | Skipped | None, enabled: bool = True, flag: str = "") -> str | None:
        """Why a stage that needs two views does not run (one view, a blocking gate among ``gates``, turned off
        by ``flag``), or None."""
        if self.views < 2:
            return ONE_VIEW
        for result in gates:
            if isinstance(result, GatesResult) and result.blocking:
                return f"gate '{result.failed[0].name}' failed: {result.failed[0].reason}"
        return None if enabled else f"turned off ({flag})"


@dataclass(frozen=True)
class Share:
    """A stage's share of the machine: alone (both None), or beside another stage, ``cores`` to claim its
    threads in (the first stage) or ``step`` to ask for threads at the start of each step (the second)."""

    cores: CoreShare | None = None
    step: Callable[[], int] | None = None


@dataclass(frozen=True)
class Stage:
    """One stage: ``run(state, options, share)`` gives its result; ``skip(state, options)`` says why it does
    not run (or None). ``reads``: the :class:`RunState` fields it reads, whose keys make its own."""

    name: str  # its record under .ffrecon/stages/, and the RunState field it fills
    reads: tuple[str, ...]
    run: Callable[[RunState, RunOptions, Share], object]
    options: Callable[[RunOptions], object]  # the options its result depends on
    label: str = ""  # how the report names it when skipped
    skip: Callable[[RunState, RunOptions], str | None] = lambda state, options: None
    files: Callable[[RunState, RunOptions], Sequence[Path | None]] = lambda state, options: ()  # user files read
    outputs: tuple[str, ...] = ()  # files and folders it writes (relative to the run folder)
    recorded: bool = True  # False: cheap, runs every time (no record, not timed)
    asked: Callable[[RunOptions], bool] = lambda options: True  # False: not run, the field stays None
    check: Callable[[object, RunOptions], None] = lambda result, options: None  # raises to stop the run
    # Results of stages beside it that it reads too when the options (and the capture) ask for them: then
    # those run first, not beside it, and their keys make its own.
    after: Callable[[RunState, RunOptions], tuple[str, ...]] = lambda state, options: ()

    def all_reads(self, state: RunState, options: RunOptions) -> tuple[str, ...]:
        return self.reads + self.after(state, options)


@dataclass(frozen=True)
class Beside:
    """Stages that read only what came before them: when two of them run, they run side by side (with
    ``RunOptions.concurrent``), the first claiming its threads, the second taking the cores it leaves."""

    stages: tuple[Stage, ...]


class StagePlan:
    """Runs stages on a :class:`RunState` through a :class:`StageRunner`, deriving each stage's key."""

    def __init__(self, runner: StageRunner, options: RunOptions) -> None:
        self.runner = runner
        self.options = options
        self.keys: dict[str, str] = {}

    def run(self, state: RunState, step: Stage | Beside) -> RunState:
        stages = step.stages if isinstance(step, Beside) else (step,)
        pending = []
        for stage in stages:
            if not stage.asked(self.options):
                self.runner.forget(stage.name, stage.outputs)
                self.keys[stage.name] = "not asked"
            elif reason := stage.skip(state, self.options):
                state = self._skipped(state, stage, reason)
            else:
                pending.append(stage)
        if (
            len(pending) == 2
            and self.options.concurrent
            and pending[0].name not in pending[1].after(state, self.options)
        ):
            return self._beside(state, *pending)
        for stage in pending:
            state = self._set(state, stage, *self._result(state, stage, self.runner, Share()))
        return state

    def _key_inputs(self, state: RunState, stage: Stage) -> list[str]:
        files = [file_key(p, self.runner.hashes) for p in stage.files(state, self.options) if p is not None]
        return [self.keys[name] for name in stage.all_reads(state, self.options)] + files

    def _result(self, state: RunState, stage: Stage, runner: StageRunner, share: Share) -> tuple[object, str]:
        inputs, options = self._key_inputs(state, stage), stage.options(self.options)
        if not stage.recorded:
            return stage.run(state, self.options, share), stage_key(stage.name, options, inputs)
        fn = lambda: stage.run(state, self.options, share)  # noqa: E731
        return runner.run(stage.name, fn, options=options, inputs=inputs, outputs=stage.outputs)

    def _beside(self, state: RunState, first: Stage, second: Stage) -> RunState:
        cores = CoreShare()
        with self.runner.side_by_side() as beside:
            one, two = run_beside(
                lambda: self._result(state, first, self.runner, Share(cores=cores)),
                lambda: self._result(state, second, beside, Share(step=cores.step)),
                cores,
                label=second.label,
            )
        return self._set(self._set(state, first, *one), second, *two)

    def _set(self, state: RunState, stage: Stage, result: object, key: str) -> RunState:
        stage.check(result, self.options)
        self.keys[stage.name] = key
        return dataclasses.replace(state, **{stage.name: result})

    def _skipped(self, state: RunState, stage: Stage, reason: str) -> RunState:
        """A typed "skipped, because" result; what the stage wrote in an earlier run is removed."""
        log.info("skipping %s: %s", stage.label, reason)
        self.runner.forget(stage.name, stage.outputs)
        key = f"skipped:{stage.name}:{reason}"  # the reason is shown by the stages that read it
        return self._set(state, stage, Skipped(stage.label, reason), key)

    def inputs_key(self, name: str, value: Path | None) -> None:
        """Set the key of a user input (``source``, ``model``) that stages read."""
        self.keys[name] = "none" if value is None else file_key(value, self.runner.hashes)
