"""run(...) chains the stages: Capture -> Pose (feed-forward and COLMAP, side by side) -> gates -> Refine
-> comparisons -> Splat -> Export/Report, each a typed call returning a frozen result (:class:`RunResults`).

Every stage writes under the staging folder (see :mod:`ffrecon.workspace`); OUT is replaced only
when the run ends with a report, so failures never destroy earlier results. Finished stages are
recorded and reused when the run is resumed (:mod:`ffrecon.resume`).
"""

from __future__ import annotations

import datetime as dt
import logging
from dataclasses import dataclass, field
from pathlib import Path

from ffrecon.capture import CaptureOptions, run_capture
from ffrecon.errors import InputError, Interrupted
from ffrecon.export.stage import ExportOptions
from ffrecon.models.stage import FeedForwardOptions
from ffrecon.report.build import write_report
from ffrecon.results import RunMode, RunResults, Verdict
from ffrecon.resume import StageRunner, file_key, rebase_paths
from ffrecon.sfm.comparisons import check_references
from ffrecon.sfm.crosscheck import ColmapOptions
from ffrecon.sfm.evidence import EvidenceOptions, EvidenceResult
from ffrecon.sfm.gates import GateOptions
from ffrecon.sfm.refine import RefineOptions
from ffrecon.splat.stage import SplatOptions, check_splat_memory
from ffrecon.stages import (
    STAGE_OUTPUTS,
    comparisons_stage,
    evidence_stage,
    exports_stage,
    final_cameras,
    gates_stage,
    pose_stages,
    refine_stage,
    seed_comparison_stage,
    splat_stage,
    with_curves,
    write_final_model,
)
from ffrecon.workspace import staged_output

log = logging.getLogger("ffrecon")


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


def run(source: Path, out_dir: Path, model: Path | None, options: RunOptions | None = None) -> RunResults:
    """Reconstruct ``source`` (folder of photos or a video) with ``model`` into ``out_dir``.

    Without a model (None) the cameras come from COLMAP and the splat is seeded from its points.

    Raises :class:`~ffrecon.errors.Interrupted` on Ctrl-C (KeyboardInterrupt), naming the stages
    kept for ``--resume``; other :class:`~ffrecon.errors.FFReconError` for unusable input.
    """
    options = options or RunOptions()
    check_run_options(model, options)
    created = dt.datetime.now().isoformat(timespec="seconds")
    flags = {"overwrite": options.overwrite, "resume": options.resume, "fresh": options.fresh}
    with staged_output(Path(out_dir), Path(source), **flags) as staging:
        work = staging.path
        stages = StageRunner(work, reuse=not options.fresh)
        try:
            results = _run_stages(Path(source), model and Path(model), options, work, stages, created)
        except KeyboardInterrupt:
            resume = options.command or "the same command"
            raise Interrupted(stages.current, stages.finished, str(work), _resume_command(resume)) from None
        # A rejected run does not replace earlier good results: it stays where it was built (said in a warning).
        kept_aside = staging.keeps_earlier(results.verdict is Verdict.GATE_FAILED)
        results = rebase_paths(results, work, work if kept_aside else staging.out_dir)  # where the files end up
        write_report(results, work)
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
    source: Path, model: Path | None, options: RunOptions, work: Path, stages: StageRunner, created: str
) -> RunResults:
    """The whole run: one typed call per stage (those that cannot or should not run are Skipped)."""
    capture, k_capture = stages.run(
        "capture",
        lambda: run_capture(source, options.capture, work),
        options=options.capture,
        inputs=[file_key(source)],
        outputs=STAGE_OUTPUTS["capture"],
    )
    if options.splat.enabled:  # a splat that cannot fit in memory at all is refused now, not after the poses
        check_splat_memory([f.size_wh for f in capture.frames], options.splat, when=" (planned)")
    (ff, k_ff), (colmap, k_colmap), sift = pose_stages(capture, model, options, work, stages, [k_capture])
    gates, k_gates = gates_stage(capture, ff, colmap, options, stages, [k_capture, k_ff, k_colmap])
    k_pose = [k_capture, k_ff, k_colmap]
    refine, k_refine = refine_stage(capture, ff, colmap, gates, options, work, stages, k_pose, sift)
    evidence, k_evidence = evidence_stage(
        capture, ff, colmap, gates, refine, options, stages, [k_ff, k_colmap, k_gates, k_refine]
    )
    verdicts = (gates, evidence.gates if isinstance(evidence, EvidenceResult) else None)
    comparisons, _ = comparisons_stage(
        capture, ff, colmap, refine, options, stages, [k_capture, k_ff, k_colmap, k_refine]
    )
    final = final_cameras(capture, ff, colmap, refine, evidence)
    write_final_model(final, ff, colmap, refine, work)
    final_keys = [k_capture, k_ff, k_colmap, k_refine, k_evidence]  # the final cameras depend on these
    options = with_curves(options)
    splat, _ = splat_stage(capture, ff, colmap, final, verdicts, options, work, stages, final_keys)
    seeds = seed_comparison_stage(capture, colmap, final, splat, options, work, stages, final_keys)
    exports, _ = exports_stage(capture, ff, colmap, final, options, work, stages, final_keys)
    return RunResults(
        out_dir=work,
        created=created,
        command=options.command,
        capture=capture,
        feedforward=ff,
        colmap=colmap,
        gates=gates,
        comparisons=comparisons,
        refine=refine,
        evidence=evidence,
        splat=splat,
        seed_comparison=seeds,
        exports=exports,
        timings=tuple(stages.timings),
        forced=options.force,
        mode=options.mode,
        overlaps=tuple(stages.overlaps),
    )
