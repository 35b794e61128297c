"""The stages of :func:`ffrecon.pipeline.run`, declared: what each reads of the :class:`RunState` (it sees only
that, through a :class:`~ffrecon.state.StateView`), when it does not run (a typed :class:`~ffrecon.types.Skipped`,
saying why), the call into its own package, where its decisions live, and its sections of report.json and
report.html. :data:`STAGES` is the one list the run, its resume keys, the results and the report follow
(docs/architecture.md, "How to add a stage")."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ffrecon.capture import Capture, run_capture
from ffrecon.export.stage import OUTPUTS, export_final_cameras
from ffrecon.final_cameras import CameraSource, FinalCameras, final_cameras, require_checked
from ffrecon.models.stage import feedforward_skip_reason, run_feedforward_sharing
from ffrecon.report import sections, stage_html
from ffrecon.report.splat_html import seeds_section, splat_section
from ffrecon.sfm.compare.comparisons import comparison_skip_reason, load_references, pose_estimates, run_comparisons
from ffrecon.sfm.crosscheck.gates import MIN_MASK_USE, gate_before_refinement, gate_poses
from ffrecon.sfm.crosscheck.matching import match_colmap_on, pairs_from_model
from ffrecon.sfm.crosscheck.run import map_colmap
from ffrecon.sfm.refine import run as refine
from ffrecon.sfm.refine.options import key_options
from ffrecon.sfm.verify.evidence import evidence_skip_reason, judge_refined_cameras
from ffrecon.splat.final import seed_comparison_skip_reason, splat_final_cameras, splat_from_colmap_points, with_curves
from ffrecon.splat.outputs import OUTPUTS as SPLAT_OUTPUTS
from ffrecon.splat.seed import no_seed_reason
from ffrecon.state import Beside, Stage, StateView
from ffrecon.types import QUICK_NO_CROSSCHECK, Prediction, RunMode

NO_CAMERAS = "COLMAP registered fewer than two images"


def masked_out(capture: Capture) -> Callable[[], set[str]] | None:
    """The frames whose masks (--masks) keep less than ``MIN_MASK_USE`` of their pixels, read when a gate asks
    (one mask at a time); None without masks."""
    if capture.mask_dir is None:
        return None
    return lambda: {
        name for k, name in enumerate(capture.names) if float(capture.read_masks([k])[0].mean()) < MIN_MASK_USE
    }


def no_depth_reason(prediction: Prediction | None, masks: bool) -> str | None:
    """Why the refinement has nothing to work on: the masks ignore every pixel of every frame (the model's depth
    is cleared there), or None."""
    if prediction is None or not masks or any(np.any(d > 0) for d in prediction.depth):
        return None
    return "no depth left to refine with: the masks (--masks) ignore every pixel of every frame"


def splat_seed_reason(state: StateView) -> str | None:
    """Why the splat has no seed point (the model's depth maps of the final frames hold no confident pixel)."""
    final = state.final
    if not isinstance(final, FinalCameras) or final.source is CameraSource.COLMAP or state.prediction is None:
        return None
    return no_seed_reason(state.prediction, final.indices)


def colmap_skip_reason(state: StateView, options) -> str | None:
    """Why the COLMAP cross-check (its matching and its mapping alike) does not run, or None."""
    return (QUICK_NO_CROSSCHECK if options.mode is RunMode.QUICK and state.views >= 2 else None) or state.why_not(
        enabled=options.colmap.enabled, flag="--no-colmap"
    )


def blocked(state: StateView) -> str | None:
    """The failed gate that stops the run (not forced), or None: after it nothing is exported."""
    return state.why_not(*state.verdicts) if state.views >= 2 else None


def check_splat_fits(capture: Capture, options) -> None:
    """Refuse, before any pose is made, a splat that cannot fit in memory; the splat stage's module (torch and
    the compiled kernels) loads only when the splat is on."""
    if options.splat.enabled:
        from ffrecon.splat.stage import check_splat_fits

        check_splat_fits([f.size_wh for f in capture.frames], options.splat)


CAPTURE = Stage(
    "capture",
    ("source",),
    lambda s, o, c: run_capture(s.source, o.capture, s.work),
    lambda o: o.capture,
    files=lambda s, o: (o.capture.intrinsics, o.capture.masks, o.capture.poses),
    outputs=("images", "masks"),
    check=lambda capture, o: check_splat_fits(capture, o),
    report=sections.capture_entries,
    page=(("Capture", stage_html.capture_section),),
)
FEEDFORWARD = Stage(
    "feedforward",
    ("capture", "model"),
    lambda s, o, c: run_feedforward_sharing(s.capture, s.model, o.feedforward, s.work, c.cores),
    lambda o: o.feedforward,
    label="feed-forward",
    skip=lambda s, o: feedforward_skip_reason(s.model, len(s.capture.frames), colmap=o.colmap.enabled),
    outputs=("feedforward",),
    report=sections.feedforward_entries,
    page=(("Feed-forward cameras and depth", stage_html.feedforward_section),),
)
COLMAP_MATCHING = Stage(
    "colmap_matching",
    ("capture",),
    lambda s, o, c: match_colmap_on(
        s.capture,
        o.colmap,
        s.work / "crosscheck",
        step=c.step,
        prediction=s.prediction if s.declares("feedforward") else None,  # the model's pairs (see ``after``)
    ),
    lambda o: o.colmap,
    files=lambda s, o: (o.colmap.vocab_tree_path,),  # a tree replaced at the same path re-runs the matching
    label="colmap cross-check: matching",
    skip=lambda s, o: colmap_skip_reason(s, o),
    outputs=("crosscheck",),
    # with the model's pairs (--pairing model; long captures by default) it runs after the model, not beside it
    after=lambda s, o: ("feedforward",) if pairs_from_model(o.colmap, s.views, model=s.model is not None) else (),
    listed_skipped=False,  # skipped with the cross-check, which lists it
)
COLMAP = Stage(  # the mapping, beside the refinement: both read the matches, neither the other
    "colmap",
    ("capture", "colmap_matching"),
    lambda s, o, c: map_colmap(s.colmap_matching, s.capture.image_dir, o.colmap, s.work / "crosscheck", step=c.step),
    lambda o: o.colmap,
    label="colmap cross-check",
    skip=lambda s, o: colmap_skip_reason(s, o),
    outputs=("crosscheck/sparse", "crosscheck/mapper"),
)
SIFT = Stage(  # quick mode: the refinement's SIFT, extracted beside the inference as COLMAP's is in the full run
    "sift",
    ("capture",),
    lambda s, o, c: refine.extract_refine_features(s.capture, o.refine.sift, s.work, c.step),
    lambda o: o.refine.sift,
    label="SIFT extraction",
    skip=lambda s, o: refine.sift_beside_skip_reason(o.mode, o.concurrent, s.model, o.refine, s.views),
    outputs=("sift",),
    report=sections.nothing,  # the refinement reports its features
    listed_skipped=False,
)
GATES = Stage(
    "gates",
    ("capture", "feedforward", "colmap"),
    lambda s, o, c: gate_poses(
        s.capture.quality,
        s.prediction,
        s.colmap,
        o.gates,
        force=o.force,
        judged=o.refine.enabled,
        masked_out=masked_out(s.capture),
    ),
    lambda o: (o.gates, o.force) if o.refine.enabled else (o.gates, o.force, "--no-refine"),
    label="gates",
    skip=lambda s, o: s.why_not(),
    report=sections.gates_entries,
    page=(("Verification gates", stage_html.gates_section),),
)
REFINE = Stage(
    "refine",
    ("capture", "feedforward", "colmap_matching", "sift"),
    lambda s, o, c: refine.run_refine_reusing(s.capture, s.prediction, s.colmap_matching, s.sift, o.refine, s.work),
    lambda o: key_options(o.refine),
    label="refinement",
    skip=lambda s, o: (
        s.why_not(enabled=o.refine.enabled, flag="--no-refine")
        or refine.refine_skip_reason(s.prediction)
        or no_depth_reason(s.prediction, masks=s.capture.mask_dir is not None)
        or gate_before_refinement(s.prediction, o.gates, force=o.force, masked_out=masked_out(s.capture))
    ),
    outputs=("sparse", "refine"),
    page=(("Refinement", stage_html.refine_section),),
)
EVIDENCE = Stage(
    "evidence",
    ("capture", "feedforward", "colmap", "gates", "refine"),
    lambda s, o, c: require_checked(
        judge_refined_cameras(
            s.capture.names,
            s.prediction,
            s.colmap,
            s.gates,
            s.refine,
            o.evidence,
            force=o.force,
            photos=lambda k: s.capture.read_images([k])[0],
        ),
        s.colmap,
        s.refine,
    ),
    lambda o: (o.evidence, o.force),
    label="evidence on the final cameras",
    skip=lambda s, o: evidence_skip_reason(s.refine),
    report=sections.evidence_entries,
    page=(("Final cameras: the evidence", stage_html.evidence_section),),
)
COMPARISONS = Stage(
    "comparisons",
    ("capture", "feedforward", "colmap", "refine"),
    lambda s, o, c: run_comparisons(
        s.capture.names,
        pose_estimates(s.model_poses, s.colmap, s.refine),
        load_references(o.ground_truth, o.reference, s.capture.names, s.capture.known_poses),
    ),
    lambda o: (o.ground_truth, o.reference),
    label="pose comparison",
    skip=lambda s, o: s.why_not() or comparison_skip_reason(s.model_poses, s.colmap, s.refine, s.references(o)),
    files=lambda s, o: (o.ground_truth, o.reference),
    report=sections.comparisons_entries,
    page=(("Pose error", stage_html.poses_section),),
)
FINAL = Stage(  # the final cameras and sparse/0: cheap, so made every time from the results they come from
    "final",
    ("capture", "feedforward", "colmap", "refine", "evidence"),
    lambda s, o, c: final_cameras(s.capture.names, s.feedforward, s.colmap, s.refine, s.evidence, s.work),
    lambda o: (),
    recorded=False,
    report=sections.nothing,  # the exports name the cameras they wrote
)
SPLAT = Stage(
    "splat",
    ("capture", "feedforward", "colmap", "gates", "evidence", "final"),
    lambda s, o, c: splat_final_cameras(s.final, s.feedforward, s.colmap, s.capture, with_curves(o.splat), s.work),
    lambda o: with_curves(o.splat),
    label="splat",
    skip=lambda s, o: (
        s.why_not(*s.verdicts, enabled=o.splat.enabled, flag="--no-splat")
        or (None if s.final else f"no cameras: {NO_CAMERAS}")
        or splat_seed_reason(s)
    ),
    outputs=SPLAT_OUTPUTS,
    page=(("Gaussian splat", splat_section),),
)
SEED_COMPARISON = Stage(
    "seed_comparison",
    ("capture", "colmap", "final", "splat"),
    lambda s, o, c: splat_from_colmap_points(s.final, s.colmap, s.capture, with_curves(o.splat), s.work),
    lambda o: with_curves(o.splat),
    label="seed comparison",
    skip=lambda s, o: seed_comparison_skip_reason(s.splat, s.final, s.colmap),
    outputs=("seed_comparison",),
    asked=lambda o: o.splat.compare_seeds,
    page=(("Seeds compared: feed-forward depth vs SfM points", seeds_section),),
    listed_skipped=False,  # its skip is its report entry
)
EXPORTS = Stage(
    "exports",
    ("capture", "feedforward", "colmap", "final"),
    lambda s, o, c: export_final_cameras(
        s.final, s.feedforward, s.colmap, s.capture, o.exports, o.feedforward.fuse, s.work
    ),
    lambda o: (o.exports, o.feedforward.fuse),
    label="exports",
    skip=lambda s, o: blocked(s) or (None if s.final else f"no cameras to export: {NO_CAMERAS} and no model was given"),
    skip_reads=("gates", "evidence"),
    outputs=OUTPUTS,
    report=sections.exports_entries,
)
POSES = Beside((FEEDFORWARD, COLMAP_MATCHING, SIFT))  # each reads only the capture
# COLMAP's mapper (one thread) beside the refinement of the model's cameras on the same matches; the gates then
# judge COLMAP's model, and the evidence the refined cameras
MAPPING = Beside((COLMAP, REFINE))
STAGES = (CAPTURE, POSES, MAPPING, GATES, EVIDENCE, COMPARISONS, FINAL, SPLAT, SEED_COMPARISON, EXPORTS)
