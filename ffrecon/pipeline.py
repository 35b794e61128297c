"""run(...) chains the stages: Capture -> Pose (feed-forward, COLMAP) -> Refine -> Splat -> Export/Report.

Every stage writes under the staging folder (see :mod:`ffrecon.workspace`); OUT is replaced only
when the run ends with a report, so failures never destroy earlier results.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ffrecon import __version__
from ffrecon import report_sections as sections
from ffrecon.capture import Capture, CaptureOptions, run_capture
from ffrecon.errors import GateFailed
from ffrecon.export.nerfstudio import write_transforms
from ffrecon.export.pointcloud import fuse_prediction, write_point_cloud
from ffrecon.export.report import ReportBuilder
from ffrecon.models.stage import FeedForwardOptions, FeedForwardResult, run_feedforward
from ffrecon.workspace import staged_output

log = logging.getLogger("ffrecon")


def _default_colmap():
    from ffrecon.sfm.crosscheck import ColmapOptions

    return ColmapOptions()


def _default_refine():
    from ffrecon.sfm.refine import RefineOptions

    return RefineOptions()


def _default_splat():
    from ffrecon.splat.stage import SplatOptions

    return SplatOptions()


@dataclass(frozen=True, kw_only=True)
class RunOptions:
    """What to run. A stage whose options are None is skipped (and the report says so)."""

    capture: CaptureOptions = field(default_factory=CaptureOptions)
    feedforward: FeedForwardOptions = field(default_factory=FeedForwardOptions)
    colmap: object | None = field(default_factory=_default_colmap)  # sfm.crosscheck.ColmapOptions
    gates: object | None = None  # sfm.gates.GateOptions (None: defaults)
    refine: object | None = field(default_factory=_default_refine)  # sfm.refine.RefineOptions
    splat: object | None = field(default_factory=_default_splat)  # splat.SplatOptions
    force: bool = False  # go on past failed gates
    overwrite: bool = False
    ground_truth: Path | None = None  # a synthetic scene folder (ground_truth.json) to score against
    reference: Path | None = None  # a reference COLMAP model to score against
    command: str = ""  # the command line, recorded in the report


@dataclass(frozen=True)
class RunResult:
    out_dir: Path
    report: dict
    exit_code: int = 0


def _timed(report: ReportBuilder, name: str, fn, *args, **kwargs):
    start = time.perf_counter()
    result = fn(*args, **kwargs)
    report.data["timings"][name] = time.perf_counter() - start
    return result


def _skip(report: ReportBuilder, stage: str, reason: str) -> None:
    log.info("skipping %s: %s", stage, reason)
    report.data["skipped_stages"].append({"stage": stage, "reason": reason})


def _focal_prior(capture: Capture, ff: FeedForwardResult) -> list[float]:
    """Per-image focal prior for COLMAP: EXIF where known, else the feed-forward model's."""
    return [f.focal_prior_px or float(np.sqrt(c.fx * c.fy)) for f, c in zip(capture.frames, ff.prediction.cameras)]


def _splat_seed(capture: Capture, ff: FeedForwardResult, cam_from_world: np.ndarray, cameras, splat_options):
    """Seed points from the feed-forward depth of the training views, placed with the final cameras.

    Refined cameras sit in the feed-forward world at its scale, so each depth map is unprojected with
    its frame's refined pose: points from different frames then agree where the feed-forward poses
    did not. Held-out views are left out so that their PSNR measures new-view rendering.
    """
    import cv2

    from ffrecon.splat.seed import seed_from_prediction
    from ffrecon.splat.stage import split_views

    pred = dataclasses.replace(ff.prediction, cam_from_world=cam_from_world, cameras=tuple(cameras))
    images = [
        f.image if f.image.shape[:2] == d.shape else cv2.resize(f.image, d.shape[::-1], interpolation=cv2.INTER_AREA)
        for f, d in zip(capture.frames, pred.depth)
    ]
    train, _ = split_views(len(pred), splat_options.holdout_every)
    return seed_from_prediction(
        pred, images, max_points=splat_options.max_seed_points, frames=train, seed=splat_options.seed
    )


def run(source: Path, out_dir: Path, model: Path, options: RunOptions | None = None) -> RunResult:
    """Reconstruct ``source`` (folder of photos or a video) with ``model`` into ``out_dir``."""
    options = options or RunOptions()
    report = ReportBuilder()
    report.data.update(
        {
            "ffrecon_version": __version__,
            "created": dt.datetime.now().isoformat(timespec="seconds"),
            "command": options.command,
            "skipped_stages": [],
            "timings": {},
            "forced": options.force,
        }
    )
    exit_code = 0
    with staged_output(Path(out_dir), overwrite=options.overwrite) as work:
        capture = _timed(report, "capture", run_capture, Path(source), options.capture, work)
        sections.add_capture(report, capture)
        ff = run_feedforward(capture, Path(model), options.feedforward, work)
        report.data["timings"]["feedforward"] = ff.seconds
        sections.add_feedforward(report, ff)
        truth = sections.load_references(options.ground_truth, options.reference, capture.names)

        final_cam_from_world, final_cameras = ff.prediction.cam_from_world, ff.prediction.cameras
        multi = len(capture.frames) >= 2
        if not multi:
            for stage in ("colmap cross-check", "pose comparison", "refinement", "splat"):
                _skip(
                    report,
                    stage,
                    "needs two or more views; this run has one photo (its depth, camera and point cloud are still produced)",
                )
        colmap = None
        if multi and options.colmap is not None:
            from ffrecon.sfm.crosscheck import run_colmap

            colmap = _timed(
                report,
                "colmap",
                run_colmap,
                capture.image_dir,
                capture.names,
                options.colmap,
                work / "colmap",
                focal_prior_px=_focal_prior(capture, ff),
            )
            sections.add_colmap(report, colmap)
        elif multi:
            _skip(report, "colmap cross-check", "turned off (--no-colmap)")

        if multi:
            verdicts = sections.add_gates(report, capture, ff, colmap, options.gates)
            failed = [v for v in verdicts if v.failed]
            if failed and not options.force:
                for stage in ("refinement", "splat"):
                    _skip(report, stage, f"gate '{failed[0].name}' failed: {failed[0].reason}")
                exit_code = GateFailed.exit_code
        refined = None
        if multi and exit_code == 0 and options.refine is not None:
            from ffrecon.sfm.refine import run_refine

            refine_options = options.refine
            if colmap is not None and refine_options.reuse_features_from is None:  # SIFT once, used twice
                refine_options = dataclasses.replace(refine_options, reuse_features_from=colmap.database_path)
            refined = _timed(report, "refine", run_refine, capture.image_dir, ff.prediction, refine_options, work)
            sections.add_refine(report, refined)
            keep = refined.registered
            if keep.sum() >= 2:
                final_cam_from_world, final_cameras = refined.cam_from_world, refined.cameras
        elif multi and exit_code == 0:
            _skip(report, "refinement", "turned off (--no-refine)")
        sections.add_pose_comparisons(report, capture, ff, colmap, refined, truth)

        if multi and exit_code == 0 and options.splat is not None:
            from ffrecon.splat.stage import run_splat

            seed_xyz, seed_rgb = _splat_seed(capture, ff, final_cam_from_world, final_cameras, options.splat)
            splat = _timed(
                report,
                "splat",
                run_splat,
                [f.image for f in capture.frames],
                capture.names,
                final_cam_from_world,
                final_cameras,
                seed_xyz,
                seed_rgb,
                options.splat,
                work,
            )
            sections.add_splat(report, splat)
        elif multi and exit_code == 0:
            _skip(report, "splat", "turned off (--no-splat)")

        points_xyz, points_rgb = ff.points_xyz, ff.points_rgb
        if refined is not None and final_cam_from_world is refined.cam_from_world:
            # Re-fuse the depth maps with the refined cameras so points.ply agrees with sparse/0.
            final_pred = dataclasses.replace(
                ff.prediction, cam_from_world=final_cam_from_world, cameras=tuple(final_cameras)
            )
            points_xyz, points_rgb = fuse_prediction(
                final_pred, [f.image for f in capture.frames], options.feedforward.fuse
            )
        write_point_cloud(work / "points.ply", points_xyz, points_rgb)
        write_transforms(
            work / "transforms.json",
            [f"images/{n}" for n in capture.names],
            final_cam_from_world,
            final_cameras,
            ply_file_path="points.ply",
        )
        sections.add_outputs(report, work)
        sections.finish_report(report, ok_message=f"{len(capture.frames)} frame(s) reconstructed")
        report.write(work)
    return RunResult(Path(out_dir), report.data, exit_code)
