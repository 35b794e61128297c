"""The refinement's adjustment loop: triangulation and bundle adjustment of the feed-forward cameras, with dense
evidence for the frames SIFT leaves short and a second chance for the frames the first adjustment left out.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pycolmap

from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.sfm.features import colmap_log_level, feature_stats
from ffrecon.sfm.refine.components import hold_apart
from ffrecon.sfm.refine.dense import add_dense_evidence, short_frames
from ffrecon.sfm.refine.links import LinkOptions, judge_links
from ffrecon.sfm.refine.matching import _initial_model, _weak_by_features
from ffrecon.sfm.refine.options import RefineOptions, WeakFrame, WeakReason
from ffrecon.sfm.refine.passes import refine_tracks
from ffrecon.sfm.refine.relocalize import reach_matrix, relocalize, with_poses
from ffrecon.types import Prediction

logger = logging.getLogger("ffrecon.sfm")


def _adjust_with_dense(image_dir, prediction, graph, image_ids, camera_sets, db_path, stats, options, timer, fixed):
    """Bundle adjustment with dense evidence: first for the frames SIFT leaves short of matches; then,
    once, for the frames the adjustment still left out (too few observations): those placed again
    from their neighbours' renderings get dense evidence from that pose, the others (not short the
    first time) from the model's, and a second adjustment starts from those poses. A capture SIFT
    handles well runs neither. Returns ``(flagged, rec, summary, dense, relocalized, stats)``."""
    names = tuple(prediction.names)
    cameras, colmap_cameras = camera_sets
    dense = None
    short = short_frames(names, stats.num_inlier_matches, options.dense) if options.dense.enabled else []
    if short:
        with timer.stage("dense_evidence"):
            dense = add_dense_evidence(db_path, image_dir, prediction, short, graph.reach(), options.dense)
        stats = feature_stats(db_path, names)
    flagged, rec, summary = _adjust(
        prediction, image_ids, cameras, colmap_cameras, db_path, stats, dense, options, timer, fixed
    )
    if not (options.dense.enabled and flagged):
        return flagged, rec, summary, dense, (), stats
    with timer.stage("dense_evidence"):
        left = [w for w in flagged if w.name not in fixed]  # given poses are not placed again
        start, more, found = _second_chance(image_dir, prediction, graph, rec, db_path, left, short, options)
    if more is None:
        return flagged, rec, summary, dense, found, stats
    dense = more if dense is None else dense.merged(more)
    stats = feature_stats(db_path, names)
    # The links are judged against the model's cameras, not the relocalised ones: a frame relocalised onto a
    # wrong link agrees with it (room seed 216: frame 4 placed by the 11-deg-wrong link 3-4 it then confirmed)
    flagged, rec, summary = _adjust(
        start, image_ids, cameras, colmap_cameras, db_path, stats, dense, options, timer, fixed, model=prediction
    )
    return flagged, rec, summary, dense, found, stats


def _second_chance(image_dir, prediction, graph, rec, db_path, flagged, short, options: RefineOptions):
    """Dense evidence for the frames the first adjustment left out: ``(prediction to start the second
    adjustment from, DenseStats or None when nothing was added, relocalised frames)``."""
    names = tuple(prediction.names)
    left = [names.index(w.name) for w in flagged]
    placed = _model_poses_kept(rec, prediction, options.relocalize.max_source_change_deg)
    found = tuple(relocalize(image_dir, prediction, left, placed, options.relocalize))
    moved = {r.index for r in found}
    retry = [k for k in left if k not in set(short) and k not in moved]
    passes = []
    if retry:
        passes.append(add_dense_evidence(db_path, image_dir, prediction, retry, graph.reach(), options.dense))
    start = with_poses(prediction, found)
    if found:
        reach = reach_matrix(len(names), found)
        passes.append(add_dense_evidence(db_path, image_dir, start, sorted(moved), reach, options.dense))
    if not passes:
        return start, None, found
    more = passes[0] if len(passes) == 1 else passes[0].merged(passes[1])
    return start, more, found


def _model_poses_kept(rec: pycolmap.Reconstruction, prediction: Prediction, max_change_deg: float) -> list[int]:
    """Indices of the frames the adjustment registered within ``max_change_deg`` of the model's rotation
    (after the best common world rotation): their model pose and depth can be rendered from. A frame
    registered again far from its model pose (a correction) would render the model's error."""
    names = tuple(prediction.names)
    index = sorted(names.index(im.name) for im in rec.images.values() if im.has_pose)
    if len(index) < 2:
        return []
    by_name = {im.name: im for im in rec.images.values()}
    refined = np.stack([by_name[names[k]].cam_from_world().matrix()[:, :3] for k in index])
    change = aligned_rotation_errors_deg(refined, prediction.cam_from_world[index, :, :3])
    return [k for k, c in zip(index, change) if c <= max_change_deg]


def _adjust(
    prediction,
    image_ids,
    cameras,
    colmap_cameras,
    db_path,
    stats,
    dense,
    options: RefineOptions,
    timer,
    fixed=(),
    model: Prediction | None = None,
):
    """Triangulate and bundle-adjust the feed-forward cameras on the database's matches: ``(flagged, rec, summary)``
    (summary None when fewer than two frames were usable). ``model``: the cameras the links are judged against
    (default: ``prediction``'s)."""
    flagged = _weak_by_features(stats, options)
    shared = len({c.camera_id for c in colmap_cameras.values()}) == 1
    rec = _initial_model(prediction, image_ids, cameras, colmap_cameras, shared)
    usable = set(prediction.names) - {w.name for w in flagged}
    summary = None
    # Two-view tracks count where they are all there is: dense evidence added, or a pair of photos (every
    # track of two frames is a two-view one; the Middlebury pair triangulated nothing without this).
    pairwise = dense is not None or len(usable) < 3
    bundle = dataclasses.replace(options.bundle, ignore_two_view_tracks=False) if pairwise else options.bundle
    bundle = dataclasses.replace(bundle, robust_fine=True) if dense is not None else bundle
    with timer.stage("triangulation_and_bundle_adjustment"), colmap_log_level():
        if len(usable) >= 2:
            obs = options.min_observations
            rec, summary, weak = refine_tracks(rec, db_path, usable, bundle, min_observations=obs, fixed=fixed)
            flagged += [WeakFrame(n, WeakReason.FEW_OBSERVATIONS, k, options.min_observations) for n, k in weak]
            # Links are checked where dense evidence made the model a chain of two-view links; given poses are the truth
            flagged += _detach(rec, model or prediction, options.links) if dense is not None and not fixed else []
    return flagged, rec, summary


def _detach(rec: pycolmap.Reconstruction, prediction: Prediction, options: LinkOptions) -> list[WeakFrame]:
    """Deregister the frames outside the largest group of trusted links, or hold apart groups none of which is
    the largest by far (:func:`~ffrecon.sfm.refine.links.judge_links`)."""
    verdict = judge_links(rec, prediction.names, prediction.cam_from_world, options)
    for name, _ in verdict.detached:
        rec.deregister_frame(rec.find_image_with_name(name).frame_id)
    if verdict.detached:
        names = [n for n, _ in verdict.detached]
        logger.warning("frames held by weak links or links the model contradicts, left out: %s", names)
    if verdict.split:
        deleted = hold_apart(rec, verdict.split)
        logger.warning(
            "groups of frames joined only by weak links or links the model contradicts, each placed by the model "
            "(%d shared points dropped): %s",
            deleted,
            "; ".join(", ".join(g) for g in verdict.split),
        )
    return [WeakFrame(n, WeakReason.WEAK_LINK, k, options.min_shared_points) for n, k in verdict.detached]
