"""The stage adapters of :func:`ffrecon.pipeline.run`: each decides whether its stage can run (else a
typed :class:`~ffrecon.results.Skipped`, saying why), names what the stage reads for its resume key,
and calls the stage's own function through the :class:`~ffrecon.resume.StageRunner`.

Each returns ``(result, key)``; ``key`` goes into the inputs of the stages that read the result.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from ffrecon.capture import Capture
from ffrecon.colmap_io import add_posed_images, is_model_dir, write_reconstruction
from ffrecon.concurrency import CoreShare, run_beside
from ffrecon.errors import InputError
from ffrecon.export.stage import OUTPUTS as EXPORT_OUTPUTS
from ffrecon.export.stage import ExportsResult, FinalCameras, fuse_with_final_cameras, run_exports
from ffrecon.geometry.alignment import umeyama
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.undistort import NO_DISTORTION, opencv_coefficients, undistort_image
from ffrecon.models.runner import cpu_threads
from ffrecon.models.stage import FeedForwardResult, run_feedforward
from ffrecon.results import QUICK_NO_CROSSCHECK, RunMode, Skipped
from ffrecon.resume import StageRunner, file_key
from ffrecon.sfm.compare import compare_poses
from ffrecon.sfm.comparisons import ComparisonsResult, load_references, run_comparisons
from ffrecon.sfm.crosscheck import ColmapResult, run_colmap
from ffrecon.sfm.evidence import CameraStatus, EvidenceResult, FrameVerdict, judge_final_cameras
from ffrecon.sfm.gates import GatesResult, run_gates
from ffrecon.sfm.refine import RefineResult, extract_refine_features, run_refine
from ffrecon.splat.seed import seed_from_reconstruction
from ffrecon.splat.stage import SplatResult, run_splat, run_splat_from_prediction

if TYPE_CHECKING:
    from ffrecon.pipeline import RunOptions

log = logging.getLogger("ffrecon")

# Files and folders each stage writes (relative to the run folder), removed before it runs again.
STAGE_OUTPUTS = {
    "capture": ("images",),
    "feedforward": ("feedforward",),
    "colmap": ("colmap",),
    "gates": (),
    "sift": ("sift",),
    "refine": ("sparse", "refine"),
    "evidence": (),
    "comparisons": (),
    "splat": ("splat.ply", "splat.spz", "splat.sog", "renders", "flythrough.mp4"),
    "seed_comparison": ("seed_comparison",),
    "exports": EXPORT_OUTPUTS,
}
ONE_VIEW = "needs two or more views; this run has one photo (its depth, camera and point cloud are still produced)"


def _skip(stages: StageRunner, stage: str, label: str, reason: str) -> tuple[Skipped, str]:
    """A typed "skipped, because" result; what the stage wrote in an earlier run is removed."""
    log.info("skipping %s: %s", label, reason)
    stages.forget(stage, STAGE_OUTPUTS[stage])
    return Skipped(label, reason), f"skipped:{stage}:{reason}"  # the reason is shown by the stages that read it


def _why_not(capture: Capture, gates, *, enabled: bool = True, flag: str = "") -> str | None:
    """Why a stage after the feed-forward one does not run (one view, a blocking gate, turned off), or None.

    ``gates``: a :class:`GatesResult`, or a tuple of them (and None for those that did not run).
    """
    if len(capture.frames) < 2:
        return ONE_VIEW
    for result in gates if isinstance(gates, tuple) else (gates,):
        if isinstance(result, GatesResult) and result.blocking:
            first = result.failed[0]
            return f"gate '{first.name}' failed: {first.reason}"
    return None if enabled else f"turned off ({flag})"


def pose_stages(capture: Capture, model: Path | None, options: RunOptions, work: Path, stages, inputs) -> tuple:
    """``((feed-forward, key), (COLMAP, key), quick mode's SIFT database or None)``: both read only the capture,
    so with ``options.concurrent`` COLMAP (in quick mode: the refinement's SIFT extraction) runs in a thread
    beside the feed-forward stage (:mod:`ffrecon.concurrency`).

    The feed-forward stage claims one core for its own thread, and while the network runs the rest of the
    cores onnxruntime keeps busy (its intra-op threads on the CPU, fixed when the model loads; none more
    on CUDA). COLMAP's extraction (in up to four batches) and matching take what is left (at least one) at
    the start of each batch or step. Its mapping stays single-threaded.
    """
    if options.mode is RunMode.QUICK:
        return _quick_pose_stages(capture, model, options, work, stages, inputs)
    if not options.concurrent:
        ff = feedforward_stage(capture, model, options, work, stages, inputs)
        return ff, colmap_stage(capture, options, work, stages, inputs), None
    cores = CoreShare()
    with stages.side_by_side() as beside:
        ff, colmap = run_beside(
            lambda: feedforward_stage(capture, model, options, work, stages, inputs, cores=cores),
            lambda: colmap_stage(capture, options, work, beside, inputs, step=cores.step),
            cores,
            label="COLMAP",
        )
    return ff, colmap, None


def _quick_pose_stages(capture: Capture, model: Path | None, options: RunOptions, work: Path, stages, inputs):
    """Quick mode: no COLMAP; the refinement's SIFT is extracted beside the inference (when concurrent) in the
    cores it leaves, as COLMAP's is in the full run. Returns ``(ff, colmap (skipped), sift database or None)``."""
    wanted = options.refine.enabled and len(capture.frames) >= 2 and options.refine.reuse_features_from is None
    if not (options.concurrent and wanted and model is not None):
        ff = feedforward_stage(capture, model, options, work, stages, inputs)
        return ff, colmap_stage(capture, options, work, stages, inputs), None
    cores = CoreShare()
    with stages.side_by_side() as beside:
        ff, (database, _) = run_beside(
            lambda: feedforward_stage(capture, model, options, work, stages, inputs, cores=cores),
            lambda: sift_stage(capture, options, work, beside, inputs, step=cores.step),
            cores,
            label="SIFT extraction",
        )
    return ff, colmap_stage(capture, options, work, stages, inputs), database


def sift_stage(capture: Capture, options: RunOptions, work: Path, stages: StageRunner, inputs, *, step=None):
    """Quick mode's SIFT for the refinement (:func:`~ffrecon.sfm.refine.extract_refine_features`), in
    ``work/sift``; ``step()`` gives the threads to use (the cores the inference leaves)."""

    def extract() -> Path:
        db_path = work / "sift" / "database.db"
        return extract_refine_features(capture.image_dir, capture.names, options.refine.sift, db_path, threads=step)

    return stages.run("sift", extract, options=options.refine.sift, inputs=inputs, outputs=STAGE_OUTPUTS["sift"])


def feedforward_stage(
    capture: Capture, model: Path | None, options: RunOptions, work: Path, stages, inputs, *, cores=None
) -> tuple:
    """``cores``: a :class:`CoreShare` the stage claims its CPU threads in while it runs (None: alone)."""
    if model is None:
        if len(capture.frames) < 2:
            raise InputError("one photo and no model: nothing can place a camera", "pass --model, or more photos")
        if not options.colmap.enabled:
            raise InputError(
                "no model and --no-colmap: nothing would make the cameras", "pass --model or drop --no-colmap"
            )
        reason = "no model given (--model): the cameras come from COLMAP and the splat is seeded from its points"
        return _skip(stages, "feedforward", "feed-forward", reason)

    def infer() -> FeedForwardResult:
        if cores is None:
            return run_feedforward(capture, model, options.feedforward, work)
        # One core for the stage's own thread throughout (reading, decoding, fusing, writing), and the rest
        # of onnxruntime's threads only while the network runs: with a small or simulated network most of
        # the stage is that one thread, and COLMAP's extraction (asking per batch) takes the other core.
        extra = cpu_threads(options.feedforward.threads) - 1
        with cores.claim(1):
            return run_feedforward(
                capture, model, options.feedforward, work, while_inferring=lambda: cores.claim(extra)
            )

    return stages.run(
        "feedforward",
        infer,
        options=options.feedforward,
        inputs=[*inputs, file_key(model)],
        outputs=STAGE_OUTPUTS["feedforward"],
    )


def _focal_prior(capture: Capture) -> list[float | None]:
    """Per-image focal prior for COLMAP: EXIF where known, else None (COLMAP's own guess).

    Never the model's focal: the cross-check must stay independent evidence of the model's cameras.
    """
    return [f.focal_prior_px for f in capture.frames]


def colmap_stage(capture, options: RunOptions, work: Path, stages: StageRunner, inputs, *, step=None) -> tuple:
    """``step``: see :func:`~ffrecon.sfm.crosscheck.run_colmap` (the cores left beside the feed-forward stage)."""
    if options.mode is RunMode.QUICK and len(capture.frames) >= 2:
        return _skip(stages, "colmap", "colmap cross-check", QUICK_NO_CROSSCHECK)
    if reason := _why_not(capture, None, enabled=options.colmap.enabled, flag="--no-colmap"):
        return _skip(stages, "colmap", "colmap cross-check", reason)
    return stages.run(
        "colmap",
        lambda: run_colmap(
            capture.image_dir,
            capture.names,
            options.colmap,
            work / "colmap",
            focal_prior_px=_focal_prior(capture),
            step=step,
        ),
        options=options.colmap,
        inputs=inputs,
        outputs=STAGE_OUTPUTS["colmap"],
    )


def gates_stage(capture: Capture, ff, colmap, options: RunOptions, stages: StageRunner, inputs) -> tuple:
    if reason := _why_not(capture, None):
        return _skip(stages, "gates", "gates", reason)

    def check() -> GatesResult:
        colmap_result = colmap if isinstance(colmap, ColmapResult) else None
        quality = capture.quality
        prediction = ff.prediction if isinstance(ff, FeedForwardResult) else None
        return run_gates(
            colmap=colmap_result,
            prediction=prediction,
            quality=quality,
            options=options.gates,
            force=options.force,
            witness=prediction is not None,  # with a model, the final cameras are judged on evidence instead
            colmap_skipped=colmap.reason if isinstance(colmap, Skipped) else "",
        )

    return stages.run("gates", check, options=(options.gates, options.force), inputs=inputs)


def refine_stage(capture, ff, colmap, gates, options: RunOptions, work, stages, inputs, sift=None) -> tuple:
    """``sift``: quick mode's SIFT database extracted beside the inference (None: COLMAP's, or extract here)."""
    if reason := _why_not(capture, gates, enabled=options.refine.enabled, flag="--no-refine"):
        return _skip(stages, "refine", "refinement", reason)
    if isinstance(ff, Skipped):
        return _skip(stages, "refine", "refinement", "needs a model's cameras to refine; COLMAP's are final")
    refine_options = options.refine
    if isinstance(colmap, ColmapResult) and refine_options.reuse_features_from is None:  # SIFT once, used twice
        refine_options = dataclasses.replace(refine_options, reuse_features_from=colmap.database_path)
    elif sift is not None and refine_options.reuse_features_from is None:
        refine_options = dataclasses.replace(refine_options, reuse_features_from=Path(sift))
    return stages.run(
        "refine",
        lambda: run_refine(capture.image_dir, ff.prediction, refine_options, work),
        options=options.refine,
        inputs=inputs,
        outputs=STAGE_OUTPUTS["refine"],
    )


def comparisons_stage(capture, ff, colmap, refine, options: RunOptions, stages: StageRunner, inputs):
    if reason := _why_not(capture, None):
        return _skip(stages, "comparisons", "pose comparison", reason)
    names = capture.names
    estimates = {}
    if isinstance(ff, FeedForwardResult):
        estimates["feed-forward"] = (ff.prediction.cam_from_world, np.ones(len(names), bool))
    if isinstance(colmap, ColmapResult) and colmap.num_registered >= 2:
        estimates["COLMAP"] = (colmap.cam_from_world, colmap.registered)
    if isinstance(refine, RefineResult):
        estimates["refined"] = (refine.cam_from_world, refine.registered)

    def compare() -> ComparisonsResult:
        return run_comparisons(names, estimates, load_references(options.ground_truth, options.reference, names))

    refs = [file_key(p) for p in (options.ground_truth, options.reference) if p is not None]
    if len(estimates) < 2 and not refs:
        if "feed-forward" not in estimates:
            reason = "no model, and no ground truth or --reference: COLMAP's cameras are the only ones"
        else:
            state = "did not run" if isinstance(colmap, Skipped) else "registered fewer than two images"
            reason = f"no reference cameras: the COLMAP cross-check {state} and no ground truth or --reference"
        return _skip(stages, "comparisons", "pose comparison", reason)
    references = (options.ground_truth, options.reference)
    return stages.run("comparisons", compare, options=references, inputs=[*inputs, *refs])


def evidence_stage(capture, ff, colmap, gates, refine, options: RunOptions, stages: StageRunner, inputs) -> tuple:
    if not isinstance(refine, RefineResult):
        return _skip(stages, "evidence", "evidence on the final cameras", f"no refinement ({refine.reason})")
    witness = gates if isinstance(gates, GatesResult) else GatesResult((), options.force)
    colmap_result = colmap if isinstance(colmap, ColmapResult) else None

    def judge() -> EvidenceResult:
        pred = ff.prediction
        args = (capture.names, pred.cam_from_world, refine, colmap_result, witness, options.evidence)
        skipped = colmap.reason if isinstance(colmap, Skipped) else ""
        return judge_final_cameras(*args, force=options.force, colmap_skipped=skipped)

    return stages.run("evidence", judge, options=(options.evidence, options.force), inputs=inputs)


def final_cameras(capture: Capture, ff, colmap, refine, evidence) -> FinalCameras | None:
    """Refined cameras when refinement kept two frames or more; else the model's; else COLMAP's registered
    ones (also when the model was found unsuited)."""
    every = tuple(range(len(capture.frames)))
    unsuited = isinstance(evidence, EvidenceResult) and evidence.model_unsuited
    if not unsuited and isinstance(refine, RefineResult) and refine.registered.sum() >= 2:
        return _refined_final_cameras(capture, colmap, refine, evidence)
    if not unsuited and isinstance(ff, FeedForwardResult):
        pred = ff.prediction
        cams = tuple(pred.cameras)
        return FinalCameras(every, capture.names, pred.cam_from_world, cams, "feed-forward", unconfirmed=every)
    if isinstance(colmap, ColmapResult) and colmap.num_registered >= 2:
        kept = tuple(int(i) for i in np.flatnonzero(colmap.registered))
        names = tuple(capture.names[i] for i in kept)
        cameras = tuple(colmap.cameras[i] for i in kept)
        distortion = tuple(_colmap_lens(colmap, names))
        return FinalCameras(kept, names, colmap.cam_from_world[list(kept)], cameras, "COLMAP", distortion)
    return None


def write_final_model(final: FinalCameras | None, ff, colmap, refine, work: Path) -> Path | None:
    """``work/sparse/0``: every final camera as a COLMAP model, where downstream tools look (docs/contracts.md,
    "Output folder"): the model of the final cameras' source (the refinement's, COLMAP's in a run without a
    model, the model's when the refinement failed or was turned off), plus, posed and without points, the
    final frames that model lacks (a frame the refinement left out keeps the model's camera, unchecked).

    Runs every time (a small model): the refinement's record owns ``sparse`` and removes it whenever it is
    skipped or runs again; the refinement's own model stays in ``refine/model``, which a resumed run reads.
    Returns the folder, or None when there is none.
    """
    if final is None:
        return None
    target = work / "sparse" / "0"
    source = {
        "refined": getattr(refine, "model_path", None),
        "COLMAP": getattr(colmap, "model_path", None),
        "feed-forward": getattr(ff, "sparse_dir", None),
    }
    folder = source.get(final.source)
    if folder is None or not is_model_dir(Path(folder)):
        return None
    rec = pycolmap.Reconstruction(str(folder))
    added = add_posed_images(rec, final.names, final.cam_from_world, final.cameras, final.distortion)
    shutil.rmtree(target, ignore_errors=True)
    write_reconstruction(rec, target)
    log.info(
        "sparse/0: the final cameras (%s, from %s)%s",
        final.source,
        folder,
        f", plus {len(added)} frame(s) it lacks, posed without points: {', '.join(added)}" if added else "",
    )
    return target


def _colmap_lens(colmap: ColmapResult, names) -> list[tuple[float, float, float, float]]:
    """OpenCV (k1, k2, p1, p2) of COLMAP's camera of each of ``names`` (registered images)."""
    by_name = {im.name: im for im in colmap.reconstruction.images.values()}
    return [opencv_coefficients(colmap.reconstruction.cameras[by_name[n].camera_id]) for n in names]


def _refined_final_cameras(capture: Capture, colmap, refine: RefineResult, evidence) -> FinalCameras:
    """The refined cameras; frames the refinement left out but COLMAP registered (evidence: COLMAP only)
    take COLMAP's pose, moved into the refined frame by a Sim(3) fit over the frames both hold, and its lens."""
    poses, cameras = refine.cam_from_world.copy(), list(refine.cameras)
    distortion = list(refine.distortion or [NO_DISTORTION] * len(poses))
    per_image = evidence.per_image if isinstance(evidence, EvidenceResult) else ()
    colmap_only = [
        k
        for k, e in enumerate(per_image)
        if e.status in (CameraStatus.COLMAP_ONLY, CameraStatus.CORRECTED) and not refine.registered[k]
    ]
    if colmap_only:
        both = refine.registered & colmap.registered
        sim = umeyama(camera_centers(colmap.cam_from_world[both]), camera_centers(refine.cam_from_world[both]))
        lenses = _colmap_lens(colmap, [capture.names[k] for k in colmap_only])
        for k, lens in zip(colmap_only, lenses):
            poses[k] = sim.transform_cam_from_world(colmap.cam_from_world[k : k + 1])[0]
            cameras[k] = colmap.cameras[k]
            distortion[k] = lens
        log.info(
            "%d frames not refined take COLMAP's poses: %s", len(colmap_only), [capture.names[k] for k in colmap_only]
        )
    kept = [k for k in range(len(poses)) if not per_image or per_image[k].status.kept]
    if len(kept) < len(poses):
        left_out = [capture.names[k] for k in range(len(poses)) if k not in kept]
        log.info("frames left out, contradicted by the evidence: %s", left_out)
    lens = tuple(distortion[k] for k in kept) if any(d != NO_DISTORTION for d in distortion) else None
    names = tuple(capture.names[k] for k in kept)
    unconfirmed = tuple(
        p for p, k in enumerate(kept) if per_image and per_image[k].verdict is not FrameVerdict.CONFIRMED
    )
    cams = tuple(cameras[k] for k in kept)
    return FinalCameras(tuple(kept), names, poses[kept], cams, "refined", lens, unconfirmed=unconfirmed)


def splat_stage(capture, ff, colmap, final, verdicts: tuple, options: RunOptions, work, stages, inputs) -> tuple:
    if reason := _why_not(capture, verdicts, enabled=options.splat.enabled, flag="--no-splat"):
        return _skip(stages, "splat", "splat", reason)
    if final is None:
        return _skip(stages, "splat", "splat", "no cameras: COLMAP registered fewer than two images")

    def splat() -> SplatResult:
        images = capture.read_images(list(final.indices))
        cameras = final.cameras
        if final.distortion is not None:  # the rasteriser is a pinhole camera: train on undistorted photos
            pairs = [undistort_image(im, c, d) for im, c, d in zip(images, cameras, final.distortion)]
            images, cameras = [p[0] for p in pairs], tuple(p[1] for p in pairs)
        if final.source != "COLMAP":
            args = (ff.prediction.subset(final.indices), images, final.cam_from_world, cameras, options.splat, work)
            return run_splat_from_prediction(*args, unconfirmed=final.unconfirmed)
        xyz, rgb = seed_from_reconstruction(colmap.reconstruction)  # COLMAP's cameras: its points
        args = (images, final.names, final.cam_from_world, cameras, xyz, rgb, options.splat, work)
        return run_splat(*args)

    return stages.run("splat", splat, options=options.splat, inputs=inputs, outputs=STAGE_OUTPUTS["splat"])


CURVE_EVERY = 20  # iterations between held-out scores when the two seeds are compared


def with_curves(options: RunOptions) -> RunOptions:
    """With --compare-seeds both splats score their held-out views at least every ``CURVE_EVERY`` iterations
    as they train (for the plot that compares them; the default curve is sparser)."""
    splat = options.splat
    if not splat.compare_seeds or 0 < splat.curve_every <= CURVE_EVERY:
        return options
    return dataclasses.replace(options, splat=dataclasses.replace(splat, curve_every=CURVE_EVERY))


def seed_comparison_stage(capture, colmap, final, splat, options: RunOptions, work, stages, inputs):
    """The same splat trained from COLMAP's points (moved into the final cameras' frame), same budget.

    None when not asked for (``--compare-seeds``); Skipped when it cannot run.
    """
    if not options.splat.compare_seeds:
        stages.forget("seed_comparison", STAGE_OUTPUTS["seed_comparison"])
        return None
    label = "seed comparison"
    if not isinstance(splat, SplatResult):
        return _skip(stages, "seed_comparison", label, "the splat did not run")[0]
    if final.source == "COLMAP" or not isinstance(colmap, ColmapResult) or colmap.num_registered < 3:
        reason = "needs a model's cameras and a COLMAP model of three images or more (seeds differ only then)"
        return _skip(stages, "seed_comparison", label, reason)[0]

    def train() -> SplatResult:
        full = np.stack([np.eye(3, 4)] * len(capture.frames))
        full[list(final.indices)] = final.cam_from_world
        to_final = compare_poses(colmap.cam_from_world, full, capture.names, colmap.registered).errors.est_to_ref
        xyz, rgb = seed_from_reconstruction(colmap.reconstruction)
        images = capture.read_images(list(final.indices))
        args = (images, final.names, final.cam_from_world, final.cameras, to_final.apply(xyz), rgb)
        return run_splat(*args, options.splat, work / "seed_comparison")

    opts = options.splat
    outputs = STAGE_OUTPUTS["seed_comparison"]
    return stages.run("seed_comparison", train, options=opts, inputs=inputs, outputs=outputs)[0]


def exports_stage(capture, ff, colmap, final, options: RunOptions, work, stages, inputs) -> tuple:
    if final is None:
        reason = "no cameras to export: COLMAP registered fewer than two images and no model was given"
        return _skip(stages, "exports", "exports", reason)

    def export() -> ExportsResult:
        if final.source == "COLMAP":
            points, what = seed_from_reconstruction(colmap.reconstruction), "COLMAP's sparse points"
        elif final.source == "refined":
            fuse = options.feedforward.fuse
            points = fuse_with_final_cameras(ff.prediction, final, capture.read_images, fuse)
            what = "depth maps fused with the refined cameras"
        else:
            points, what = (ff.points_xyz, ff.points_rgb), "depth maps fused with the model's cameras"
        return run_exports(final, points, what, options.exports, work)

    opts = (options.exports, options.feedforward.fuse)
    return stages.run("exports", export, options=opts, inputs=inputs, outputs=STAGE_OUTPUTS["exports"])
