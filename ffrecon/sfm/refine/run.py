"""Bundle adjustment seeded by the feed-forward cameras.

Only the pairs that the feed-forward geometry says overlap are matched (SIFT, COLMAP's verification);
tracks are triangulated with the feed-forward cameras, then refined by bundle adjustment in two
passes: a coarse pass with tolerances wide enough for feed-forward pose errors and a robust loss, then
a fresh triangulation with the coarse result and COLMAP's usual tolerances. Frames that end up
with too few features, matches or observations, or held to the others only by weak links or links
the model contradicts (``sfm/refine/links.py``), are flagged and kept out; the rest are refined.
The result is expressed in the prediction's world frame (Sim(3)-aligned to its camera centres).
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.capture import Capture
from ffrecon.colmap_io import cam_from_world_by_name, cameras_by_name, write_reconstruction
from ffrecon.geometry.alignment import Sim3
from ffrecon.geometry.overlap import overlap_graph
from ffrecon.geometry.undistort import NO_DISTORTION, opencv_coefficients
from ffrecon.sfm.crosscheck.matching import ColmapMatches
from ffrecon.sfm.features import (
    CameraModel,
    SiftOptions,
    colmap_log_level,
    create_database,
    extract_sift,
    feature_stats,
)
from ffrecon.sfm.refine.adjust import _adjust_with_dense
from ffrecon.sfm.refine.carry import carry_left_out
from ffrecon.sfm.refine.components import lost_frames, parts, place_parts
from ffrecon.sfm.refine.guided import GuidanceStats
from ffrecon.sfm.refine.matching import (
    _check_inputs,
    _guide,
    _match_unguided,
    _on_lookalikes,
    _prepare_database,
    _reuse_matches,
    _screen,
)
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions, RefineResult, RefineStatus
from ffrecon.sfm.refine.passes import sim3_to_ff_frame
from ffrecon.sfm.refine.rigidity import rotation_spread_deg
from ffrecon.sfm.refine.screen import Suspect, reseeded
from ffrecon.timing import StageTimer
from ffrecon.types import Prediction, RunMode, Skipped

logger = logging.getLogger("ffrecon.sfm")


def extract_refine_features(
    capture: Capture, sift: SiftOptions, out_dir: Path, threads: Callable[[], int] | None = None
) -> Path:
    """SIFT of the capture's photos (and masks) into a fresh COLMAP database, ``out_dir/sift/database.db``, for the
    refinement to reuse (:attr:`RefineInputs.reuse_features_from`); returns its path. ``threads``: see
    :func:`extract_sift`.

    Quick mode runs it beside the feed-forward inference, the part COLMAP's extraction plays in the full
    run: the features depend only on the photos, so they need not wait for the cameras.
    """
    db_path = Path(out_dir) / "sift" / "database.db"
    db_path.parent.mkdir(parents=True, exist_ok=True)
    image_dir, names = capture.image_dir, list(capture.names)
    create_database(db_path, image_dir, names, camera_model=CameraModel.PINHOLE, single_camera=False)
    extract_sift(db_path, image_dir, names, sift, threads=threads, mask_dir=capture.mask_dir)
    return db_path


def run_refine(inputs: RefineInputs, prediction: Prediction, options: RefineOptions, out_dir: Path) -> RefineResult:
    """Refine the feed-forward cameras; writes the refined model to ``out_dir/refine/model`` (work files beside it;
    the run's ``sparse/0``, the final cameras, is written from it by the pipeline).

    Args:
        inputs: the images (and masks), SIFT to reuse, frames whose poses stay fixed, the overlap graph.
        prediction: feed-forward cameras (cam_from_world, OpenCV) and depth, original-photo pixels.
    Returns:
        :class:`RefineResult` with poses in the prediction's world frame. Weak frames are flagged, not
        fatal; with fewer than two usable frames the status is FAILED and the feed-forward cameras
        are returned unrefined (nothing is written).
    """
    image_dir, out_dir, fixed, graph = Path(inputs.image_dir), Path(out_dir), inputs.fixed, inputs.graph
    _check_inputs(image_dir, prediction)
    names = tuple(prediction.names)
    timer = StageTimer()
    work = out_dir / "refine"
    db_path = work / "database.db"
    pycolmap.set_random_seed(options.seed)
    with timer.stage("pair_selection"):
        if graph is None or graph.options != options.overlap or len(graph.overlap) != len(prediction):
            graph = overlap_graph(prediction, options.overlap)
    image_ids, cameras, colmap_cameras, copied = _prepare_database(
        image_dir, prediction, options, db_path, timer, inputs.mask_dir, inputs.reuse_features_from
    )
    pairs = [(names[i], names[j]) for i, j in graph.pairs]
    with timer.stage("matching"):
        reused = _reuse_matches(db_path, graph, names, copied, options, inputs.reuse_features_from)
        verified = _match_unguided(db_path, pairs, reused, options, work / "pairs.txt")
    with timer.stage("screening"):
        screened = tuple(s for s in _screen(db_path, prediction, verified, options) if names[s.index] not in fixed)
        start = reseeded(prediction, screened)
    with timer.stage("matching"):
        guidance = _guide(db_path, start, pairs, verified, options, work / "pairs.txt", unscreened=prediction)
    screened, start = _screen_undone_on_lookalikes(screened, start, prediction, guidance)
    options = _on_lookalikes(options, guidance)
    stats = feature_stats(db_path, names)
    flagged, rec, summary, dense, relocalized, stats = _adjust_with_dense(
        image_dir, start, graph, image_ids, (cameras, colmap_cameras), db_path, stats, options, timer, fixed
    )
    refined_names = {img.name for img in rec.images.values() if img.has_pose} if summary is not None else set()
    provenance = dict(
        database_path=db_path,
        flagged=tuple(flagged),
        num_pairs=len({frozenset(p) for p in pairs + reused}),
        features=stats,
        guidance=guidance,
        screened=screened,
        dense=dense,
        relocalized=relocalized,
        bundle=summary,
        overlap_reach=tuple(np.where(np.eye(len(names), dtype=bool), 0.0, graph.reach()).max(axis=1).tolist()),
    )
    if len(refined_names) < 2:
        logger.warning("refinement failed: %d usable frames; keeping the feed-forward cameras", len(refined_names))
        return _unrefined_result(prediction, timings=timer.freeze(), **provenance)
    model_dir = out_dir / "refine" / "model"
    with timer.stage("export"):
        ff_from_refined, several = _to_ff_frame(rec, prediction)
        provenance["flagged"] += tuple(lost_frames(rec, prediction.names, prediction.cam_from_world))
        if rec.num_reg_images() < 2:
            logger.warning(
                "refinement failed: fewer than two frames kept their position; keeping the feed-forward cameras"
            )
            return _unrefined_result(prediction, timings=timer.freeze(), **provenance)
        _write_model(rec, image_dir, model_dir)
    provenance.update(_shape(rec, names, several, timer))
    result = _refined_result(rec, prediction, ff_from_refined, model_dir, timings=timer.freeze(), **provenance)
    _log_refined(result)
    return result


def _screen_undone_on_lookalikes(
    screened: tuple[Suspect, ...], start: Prediction, prediction: Prediction, guidance: GuidanceStats | None
) -> tuple[tuple[Suspect, ...], Prediction]:
    """``(screened, start)``, or no suspect and the model's cameras on look-alike surfaces.

    The screen's pairs are SIFT's, unfiltered, and on look-alike surfaces two of them agreeing on a pattern's period
    off is no evidence against the model: on the repeated-tile object (held-out seed 264, 50-90 deg apart) two of
    frame 3's seven pairs put it 86 deg from the model's rotation (1.1 deg from the truth, the others within 3), the
    adjustment started there, and the frame was left out in every run. The matches are then guided by the model's
    cameras (:func:`ffrecon.sfm.refine.matching._guide`'s ``unscreened``), and the screened frames start from them."""
    if not (screened and guidance is not None and guidance.lookalike):
        return screened, start
    logger.warning(
        "look-alike surfaces: the verified pairs that put %s far from the model's rotation are not trusted; starting "
        "from the model's cameras",
        ", ".join(prediction.names[s.index] for s in screened),
    )
    return (), prediction


def _shape(rec: pycolmap.Reconstruction, names: tuple[str, ...], several: bool, timer: StageTimer) -> dict:
    """The refined model's parts placed each by the model, without the frames lost since (a one-part model was
    placed as one), and how firmly its matches hold each frame's rotation (:mod:`ffrecon.sfm.refine.rigidity`)."""
    held = parts(rec) if several else []
    with timer.stage("rigidity"):
        spread = rotation_spread_deg(rec, names)
    return {
        "parts": tuple(tuple(rec.image(i).name for i in p) for p in held) if len(held) > 1 else (),
        "rotation_spread_deg": spread,
    }


def _log_refined(result: RefineResult) -> None:
    logger.info(
        "refined %d/%d frames, %d points, %.2f px reprojection error (%.1f s)",
        int(result.registered.sum()),
        len(result.names),
        len(result.points_xyz),
        result.mean_reprojection_error_px,
        result.timings.total_s,
    )


def _to_ff_frame(rec: pycolmap.Reconstruction, prediction: Prediction) -> tuple[Sim3, bool]:
    """Move ``rec`` into the prediction's world frame; returns ``ff_from_refined``, the similarity that moved it
    (the largest part's, when parts that share no point are placed each by its own:
    :mod:`ffrecon.sfm.refine.components`), and whether there were several parts."""
    placed = place_parts(rec, prediction.names, prediction.cam_from_world)
    if placed:
        return placed[0], True
    return sim3_to_ff_frame(rec, prediction.names, prediction.cam_from_world), False


def _write_model(rec: pycolmap.Reconstruction, image_dir: Path, model_dir: Path) -> None:
    """Colour ``rec``'s points from the photos and write it to ``model_dir``."""
    with colmap_log_level():
        rec.extract_colors_for_all_images(str(image_dir))
    shutil.rmtree(model_dir, ignore_errors=True)
    write_reconstruction(rec, model_dir)


def _unrefined_result(prediction: Prediction, **provenance) -> RefineResult:
    """The FAILED result: the feed-forward cameras, unrefined, and no points or model."""
    n = len(prediction.names)
    return RefineResult(
        status=RefineStatus.FAILED,
        names=tuple(prediction.names),
        cam_from_world=prediction.cam_from_world.copy(),
        registered=np.zeros(n, bool),
        cameras=tuple(prediction.cameras),
        distortion=None,
        points_xyz=np.zeros((0, 3)),
        points_rgb=np.zeros((0, 3), np.uint8),
        mean_reprojection_error_px=float("nan"),
        ff_from_refined=Sim3.identity(),
        model_path=None,
        observations=None,
        reconstruction=None,
        **provenance,
    )


def _refined_result(
    rec: pycolmap.Reconstruction, prediction: Prediction, ff_from_refined: Sim3, model_dir: Path, **provenance
) -> RefineResult:
    """The refined model ``rec`` (already in the prediction's world frame) read back by image name.

    Frames that ``rec`` does not hold keep their feed-forward camera, and the feed-forward pose carried along
    with the refined frames near them where that predicts the refined frames better (:mod:`.carry`).
    """
    names = tuple(prediction.names)
    cam_from_world, registered = cam_from_world_by_name(rec, names)
    cam_from_world, carry = carry_left_out(prediction.cam_from_world, cam_from_world, registered)
    if carry is not None and carry.carried:
        logger.info(
            "%d frame(s) not refined carried along with their refined neighbours (%s correction): %s",
            len(carry.carried),
            carry.scheme,
            ", ".join(names[k] for k in carry.carried),
        )
    refined_cams = tuple(c if r else p for c, r, p in zip(cameras_by_name(rec, names), registered, prediction.cameras))
    by_name = {image.name: image for image in rec.images.values() if image.has_pose}
    coefficients = tuple(
        opencv_coefficients(rec.cameras[by_name[n].camera_id]) if n in by_name else NO_DISTORTION for n in names
    )
    points = rec.points3D
    xyz = np.array([p.xyz for p in points.values()], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points.values()], dtype=np.uint8).reshape(-1, 3)
    rec.update_point_3d_errors()
    for weak in provenance["flagged"]:
        logger.warning("weak frame %s", weak.describe())
    return RefineResult(
        status=RefineStatus.SUCCESS if registered.all() else RefineStatus.PARTIAL,
        names=names,
        cam_from_world=cam_from_world,
        registered=registered,
        cameras=refined_cams,
        distortion=coefficients if any(c != NO_DISTORTION for c in coefficients) else None,
        points_xyz=xyz,
        points_rgb=rgb,
        mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
        ff_from_refined=ff_from_refined,
        model_path=model_dir,
        observations=np.array([by_name[n].num_points3D if n in by_name else 0 for n in names], int),
        reconstruction=rec,
        carry=carry,
        **provenance,
    )


def sift_beside_skip_reason(
    mode: RunMode, concurrent: bool, model: Path | None, options: RefineOptions, views: int
) -> str | None:
    """Why the refinement's SIFT is not extracted ahead, beside the inference (only quick mode runs it there,
    when ``concurrent``, and when the refinement will run on a model's cameras and extracts its own), or None."""
    wanted = options.enabled and model is not None and views >= 2
    if mode is RunMode.QUICK and concurrent and wanted:
        return None
    return "extracted by the refinement itself (only quick mode extracts it beside the inference)"


def refine_skip_reason(prediction: Prediction | None) -> str | None:
    """Why the refinement does not run for want of a model's cameras, or None."""
    return "needs a model's cameras to refine; COLMAP's are final" if prediction is None else None


def run_refine_reusing(
    capture: Capture,
    prediction: Prediction,
    colmap: ColmapMatches | Skipped,
    sift: Path | Skipped,
    options: RefineOptions,
    out_dir: Path,
) -> RefineResult:
    """:func:`run_refine` on a capture's photos (and masks), reusing SIFT already extracted: the COLMAP
    cross-check's database (SIFT once, used twice), else quick mode's ``sift`` extracted beside the inference,
    else none (the refinement extracts its own). Intrinsics the user
    gave to hold fixed (``--intrinsics``; the prediction holds them) the adjustment keeps as they are
    (pinhole, focal fixed)."""
    fixed_intrinsics = bool(capture.known_cameras) and capture.intrinsics_fixed
    given = frozenset(n for n, p in zip(capture.names, capture.known_poses) if p is not None)
    if given and not capture.poses_fixed:  # the prediction holds the given poses: priors keep the centres near
        bundle = dataclasses.replace(options.bundle, use_pose_priors=True, prior_position_std=options.given_pose_std)
        options = dataclasses.replace(options, bundle=bundle)
    if fixed_intrinsics:
        bundle = dataclasses.replace(options.bundle, refine_focal_length=False, refine_principal_point=False)
        options = dataclasses.replace(options, bundle=bundle, square_pixels=False)
    reused = colmap.database_path if isinstance(colmap, ColmapMatches) else sift if isinstance(sift, Path) else None
    inputs = RefineInputs(
        capture.image_dir,
        capture.mask_dir,
        reuse_features_from=reused,
        fixed=given if capture.poses_fixed else frozenset(),
        graph=colmap.model_overlap if isinstance(colmap, ColmapMatches) else None,  # the same prediction's
    )
    return run_refine(inputs, prediction, options, out_dir)
