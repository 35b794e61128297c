"""The run state and the stage runner of :func:`ffrecon.pipeline.run`.

:class:`RunState` is frozen: the run's inputs and a mapping from each stage's name to its result, filled as
the run goes (typed accessors, ``state.colmap``, for the stages of :data:`ffrecon.stages.STAGES`). A
:class:`Stage` declares the results it reads (its ``reads``) and sees the state only through a
:class:`StateView` of them: reading anything else raises :class:`UndeclaredRead`. :class:`StagePlan` derives
the stage's resume key from the keys of those reads (and of the user's files it names), so no key is threaded
by hand and none can go stale: a stage whose reads and options are unchanged is reused (:mod:`ffrecon.resume`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ffrecon.capture import Capture
from ffrecon.concurrency import CoreShare, run_beside
from ffrecon.export.stage import ExportsResult
from ffrecon.final_cameras import FinalCameras
from ffrecon.models.stage import FeedForwardResult
from ffrecon.options import RunOptions
from ffrecon.resume import StageRunner, file_key, stage_key
from ffrecon.sfm.compare.comparisons import ComparisonsResult
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.crosscheck.matching import ColmapMatches
from ffrecon.sfm.crosscheck.run import ColmapResult
from ffrecon.sfm.refine.options import RefineResult
from ffrecon.sfm.verify.verdicts import EvidenceResult
from ffrecon.splat.result import SplatResult
from ffrecon.types import ONE_VIEW, Prediction, Skipped

log = logging.getLogger("ffrecon")


class UndeclaredRead(LookupError):
    """A stage read a result of the run state that its ``reads`` do not name: a defect of the stage's
    declaration (its resume key would miss that result), never of the user's input."""


class StageResults:
    """Typed access to the stages' results, each read through :meth:`result`, and what is derived from them.

    Shared by :class:`RunState` (every result) and :class:`StateView` (those one stage declared), so a
    derived property reads only what the stage that asks for it declared."""

    def result(self, name: str) -> object:
        """The result of stage ``name``: None before it ran (or when not asked for), a :class:`Skipped` when it
        did not run."""
        raise NotImplementedError

    def __getitem__(self, name: str) -> object:
        return self.result(name)

    @property
    def capture(self) -> Capture | None:
        return self.result("capture")

    @property
    def feedforward(self) -> FeedForwardResult | Skipped | None:
        return self.result("feedforward")

    @property
    def colmap(self) -> ColmapResult | Skipped | None:
        return self.result("colmap")

    @property
    def colmap_matching(self) -> ColmapMatches | Skipped | None:  # the cross-check's SIFT and matches
        return self.result("colmap_matching")

    @property
    def sift(self) -> Path | Skipped | None:  # quick mode's SIFT database, extracted beside the inference
        return self.result("sift")

    @property
    def gates(self) -> GatesResult | Skipped | None:
        return self.result("gates")

    @property
    def refine(self) -> RefineResult | Skipped | None:
        return self.result("refine")

    @property
    def evidence(self) -> EvidenceResult | Skipped | None:  # the final cameras judged (with a model)
        return self.result("evidence")

    @property
    def comparisons(self) -> ComparisonsResult | Skipped | None:
        return self.result("comparisons")

    @property
    def final(self) -> FinalCameras | Skipped | None:
        return self.result("final")

    @property
    def splat(self) -> SplatResult | Skipped | None:
        return self.result("splat")

    @property
    def seed_comparison(self) -> SplatResult | Skipped | None:  # --compare-seeds; None: not asked
        return self.result("seed_comparison")

    @property
    def exports(self) -> ExportsResult | Skipped | None:
        return self.result("exports")

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
class RunState(StageResults):
    """What a run knows so far: its inputs, and each stage's result once it has run, keyed by the stage's name
    in run order (absent before it ran or when not asked for; a :class:`Skipped` when it did not run)."""

    source: Path  # the photos or the video
    model: Path | None  # the ONNX model, None without one
    work: Path  # the run folder every stage writes under
    results: dict[str, object] = field(default_factory=dict)

    def result(self, name: str) -> object:
        return self.results.get(name)

    def with_result(self, name: str, result: object) -> RunState:
        return dataclasses.replace(self, results={**self.results, name: result})


class StateView(StageResults):
    """What one stage sees of a :class:`RunState`: the run's inputs (``source``, ``model``, ``work``) and the
    results it declares; reading another result raises :class:`UndeclaredRead`."""

    def __init__(self, state: RunState, stage: str, reads: Sequence[str]) -> None:
        self.source, self.model, self.work = state.source, state.model, state.work
        self._state, self._stage, self._reads = state, stage, tuple(reads)

    def declares(self, name: str) -> bool:
        """Whether the stage declared ``name`` among its reads here (those its options switch on included)."""
        return name in self._reads

    def result(self, name: str) -> object:
        if name not in self._reads:
            raise UndeclaredRead(
                f"stage '{self._stage}' read '{name}' of the run state, which it does not declare (it sees "
                f"{self._reads}): add '{name}' to the Stage's reads (they make its resume key), or to its "
                "skip_reads when only its skip rule reads it"
            )
        return self._state.result(name)


@dataclass(frozen=True)
class Share:
    """A stage's share of the machine: alone (both None), or beside another stage, ``cores`` to claim its
    threads in (the first stage) or ``step`` to ask for threads at the start of each step (the second)."""

    cores: CoreShare | None = None
    step: Callable[[], int] | None = None


PageSection = Callable[[dict, Path], tuple[list[dict], str]]  # (report.json's dict, run folder) -> (rows, html)


def _to_report(result: object) -> object:
    """A result's ``to_report()``; plain data (numbers, strings, lists, dicts of them) as it is."""
    to_report = getattr(result, "to_report", None)
    return result if to_report is None else to_report()


def report_section(result: object, to_report: Callable[[object], object] = _to_report) -> object:
    """A stage's entry in report.json: ``{"skipped": reason}``, None when not asked for, else ``to_report``'s."""
    if result is None:
        return None
    return {"skipped": result.reason} if isinstance(result, Skipped) else to_report(result)


@dataclass(frozen=True)
class Stage:
    """One stage: ``run(view, options, share)`` gives its result; ``skip(view, options)`` says why it does
    not run (or None). ``reads``: the results of earlier stages (and the inputs ``source``, ``model``) its
    result depends on: their keys make its own, and the ``view`` it gets shows only those."""

    name: str  # its record under .ffrecon/stages/, and its key in RunState.results and report.json
    reads: tuple[str, ...]
    run: Callable[[StateView, RunOptions, Share], object]
    options: Callable[[RunOptions], object]  # the options its result depends on
    label: str = ""  # how the report names it when skipped
    skip: Callable[[StateView, RunOptions], str | None] = lambda state, options: None
    # Results only ``skip`` reads besides ``reads``: they decide whether it runs, not what it makes, so they
    # are not in its key (a skipped stage's key is its reason).
    skip_reads: tuple[str, ...] = ()
    files: Callable[[StateView, RunOptions], Sequence[Path | None]] = lambda state, options: ()  # user files read
    outputs: tuple[str, ...] = ()  # files and folders it writes (relative to the run folder)
    recorded: bool = True  # False: cheap, runs every time (no record, not timed)
    asked: Callable[[RunOptions], bool] = lambda options: True  # False: not run, its result stays None
    check: Callable[[object, RunOptions], None] = lambda result, options: None  # raises to stop the run
    # Results of stages beside it that it reads too when the options (and the capture) ask for them: then
    # those run first, not beside it, and their keys make its own.
    after: Callable[[StateView, RunOptions], tuple[str, ...]] = lambda state, options: ()
    # report.json: its entries (key -> data) from the run's results (a RunResults); None: its one entry,
    # ``{name: report_section(result)}``.
    report: Callable[[RunState], dict[str, object]] | None = None
    page: tuple[tuple[str, PageSection], ...] = ()  # report.html: (title, section) in page order
    listed_skipped: bool = True  # False: a skip is routine, not listed among the skipped stages

    def all_reads(self, state: RunState, options: RunOptions) -> tuple[str, ...]:
        return self.reads + self.after(StateView(state, self.name, self.reads), options)

    def view(self, state: RunState, options: RunOptions) -> StateView:
        """What ``run`` and ``files`` see: the declared reads, those the options switch on included."""
        return StateView(state, self.name, self.all_reads(state, options))

    def skip_view(self, state: RunState) -> StateView:
        return StateView(state, self.name, self.reads + self.skip_reads)

    def entries(self, results: RunState) -> dict[str, object]:
        """Its entries in report.json."""
        if self.report is not None:
            return self.report(results)
        return {self.name: report_section(results.result(self.name))}


@dataclass(frozen=True)
class Beside:
    """Stages that read only what came before them: when two of them run, they run side by side (with
    ``RunOptions.concurrent``), the first claiming its threads, the second taking the cores it leaves."""

    stages: tuple[Stage, ...]


def each_stage(steps: Sequence[Stage | Beside]) -> Iterator[Stage]:
    """The stages of a stage list in run order (those side by side in their listed order)."""
    for step in steps:
        yield from step.stages if isinstance(step, Beside) else (step,)


class StagePlan:
    """Runs stages on a :class:`RunState` through a :class:`StageRunner`, deriving each stage's key."""

    def __init__(self, runner: StageRunner, options: RunOptions) -> None:
        self.runner = runner
        self.options = options
        self.keys: dict[str, str] = {}

    def run(self, state: RunState, step: Stage | Beside) -> RunState:
        pending = []
        for stage in each_stage((step,)):
            if not stage.asked(self.options):
                self.runner.forget(stage.name, stage.outputs)
                self.keys[stage.name] = "not asked"
            elif reason := stage.skip(stage.skip_view(state), self.options):
                state = self._skipped(state, stage, reason)
            else:
                pending.append(stage)
        if (
            len(pending) == 2
            and self.options.concurrent
            and pending[0].name not in pending[1].all_reads(state, self.options)
        ):
            return self._beside(state, *pending)
        for stage in pending:
            state = self._set(state, stage, *self._result(state, stage, self.runner, Share()))
        return state

    def _key_inputs(self, state: RunState, stage: Stage) -> list[str]:
        view = stage.view(state, self.options)
        files = [file_key(p, self.runner.hashes) for p in stage.files(view, self.options) if p is not None]
        return [self.keys[name] for name in stage.all_reads(state, self.options)] + files

    def _result(self, state: RunState, stage: Stage, runner: StageRunner, share: Share) -> tuple[object, str]:
        inputs, options = self._key_inputs(state, stage), stage.options(self.options)
        view = stage.view(state, self.options)
        if not stage.recorded:
            return stage.run(view, self.options, share), stage_key(stage.name, options, inputs)
        fn = lambda: stage.run(view, self.options, share)  # noqa: E731
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
        return state.with_result(stage.name, result)

    def _skipped(self, state: RunState, stage: Stage, reason: str) -> RunState:
        """A typed "skipped, because" result; what the stage wrote in an earlier run is removed."""
        log.info("skipping %s: %s", stage.label, reason)
        self.runner.forget(stage.name, stage.outputs)
        key = f"skipped:{stage.name}:{reason}"  # the reason is shown by the stages that read it
        return self._set(state, stage, Skipped(stage.label, reason), key)

    def inputs_key(self, name: str, value: Path | None) -> None:
        """Set the key of a user input (``source``, ``model``) that stages read."""
        self.keys[name] = "none" if value is None else file_key(value, self.runner.hashes)
