"""run(...) chains the stages: Capture -> Pose (feed-forward and COLMAP, side by side) -> gates -> Refine
-> comparisons -> Splat -> Export/Report, each a typed call returning a frozen result (:class:`RunResults`).

Every stage writes under the staging folder (see :mod:`ffrecon.workspace`); OUT is replaced only
when the run ends with a report, so failures never destroy earlier results. Finished stages are
recorded and reused when the run is resumed (:mod:`ffrecon.resume`).
"""

from __future__ import annotations

import datetime as dt
import logging
from pathlib import Path

from ffrecon.concurrency import blas_threads
from ffrecon.errors import InputError, Interrupted
from ffrecon.options import RunOptions
from ffrecon.report.build import write_report
from ffrecon.results import RunResults, Verdict
from ffrecon.resume import StageRunner, rebase_paths
from ffrecon.sfm.compare.comparisons import check_references
from ffrecon.stages import STAGES
from ffrecon.state import Beside, RunState, Stage, StagePlan
from ffrecon.timing import Clock
from ffrecon.types import RunMode
from ffrecon.workspace import staged_output

__all__ = ["RunOptions", "check_run_options", "run"]  # RunOptions lives in ffrecon.options; imported from here too

log = logging.getLogger("ffrecon")

StageList = tuple[Stage | Beside, ...]


def run(
    source: Path,
    out_dir: Path,
    model: Path | None,
    options: RunOptions | None = None,
    *,
    stages: StageList = STAGES,
    started: Clock | None = None,
) -> RunResults:
    """Reconstruct ``source`` (folder of photos or a video) with ``model`` into ``out_dir``.

    Without a model (None) the cameras come from COLMAP and the splat is seeded from its points. ``stages``:
    the stage list to run (:data:`ffrecon.stages.STAGES`; a test may run a copy with a stage added).
    ``started``: when the caller's work began (the command line passes the process's start), else this call;
    report.json's timings hold "startup", from then to the first stage, and "report", from the last stage to
    report.json's write (:func:`~ffrecon.report.build.write_report`).

    Raises :class:`~ffrecon.errors.Interrupted` on Ctrl-C (KeyboardInterrupt), naming the stages
    kept for ``--resume``; other :class:`~ffrecon.errors.FFReconError` for unusable input.
    """
    started = started or Clock.now("run() called")
    options = options or RunOptions()
    check_run_options(model, options)
    created = dt.datetime.now().isoformat(timespec="seconds")
    flags = {"overwrite": options.overwrite, "resume": options.resume, "fresh": options.fresh}
    # numpy's matrix products in a run are tall and thin: faster on one BLAS thread (ffrecon.concurrency.blas_threads)
    with blas_threads(1), staged_output(Path(out_dir), Path(source), **flags) as staging:
        work = staging.path
        runner = StageRunner(work, reuse=not options.fresh)
        try:
            results, startup = _run_stages(
                Path(source), model and Path(model), options, runner, created, stages, started
            )
        except KeyboardInterrupt:
            resume = options.command or "the same command"
            raise Interrupted(runner.current, runner.finished, str(work), _resume_command(resume)) from None
        stages_ended = Clock.now("last stage ended")
        # A rejected run does not replace earlier good results: it stays where it was built (said in a warning).
        kept_aside = staging.keeps_earlier(results.verdict is Verdict.GATE_FAILED)
        results = rebase_paths(results, work, work if kept_aside else staging.out_dir)  # where the files end up
        write_report(results, work, startup=(*startup, started.origin), report_started=stages_ended)
        staging.verdict = results.verdict.value
    return results


def check_run_options(model: Path | None, options: RunOptions) -> None:
    """Raise :class:`~ffrecon.errors.InputError` for options that cannot make a run (before any work)."""
    if options.mode is RunMode.QUICK and model is None:
        raise InputError(
            "quick mode (--quick) refines a model's cameras, and no model was given",
            "pass --model MODEL.onnx (docs/models.md lists the models ffrecon runs), "
            "or drop --quick: without a model COLMAP makes the cameras",
        )
    if options.mode is RunMode.QUICK and not options.refine.enabled:
        raise InputError(
            "quick mode (--quick) is the model's cameras refined by bundle adjustment; --no-refine leaves none of it",
            "drop --no-refine, or drop --quick and pass --no-colmap --no-refine for the model's cameras alone",
        )
    check_references(options.ground_truth, options.reference)


def _resume_command(command: str) -> str:
    return command if "--resume" in command.split() else f"{command} --resume"


def _run_stages(
    source: Path,
    model: Path | None,
    options: RunOptions,
    runner: StageRunner,
    created: str,
    stages: StageList,
    started: Clock,
) -> tuple[RunResults, tuple[float, float]]:
    """The whole run: the stages in order, each reading the state so far; the final state is the results. With
    them the wall and CPU seconds from ``started`` to the first stage (the interpreter, imports, the folder's lock,
    the inputs' keys)."""
    plan = StagePlan(runner, options)
    plan.inputs_key("source", source)
    plan.inputs_key("model", model)
    state = RunState(source, model, runner.run_dir)
    startup = started.since()
    for step in stages:
        state = plan.run(state, step)
    return RunResults.of(
        state,
        created=created,
        command=options.command,
        timings=tuple(runner.timings),
        forced=options.force,
        mode=options.mode,
        overlaps=tuple(runner.overlaps),
        stages=tuple(stages),
    ), startup
