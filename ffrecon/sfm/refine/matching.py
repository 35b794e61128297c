"""The refinement's steps before the adjustment: the database seeded with the feed-forward cameras, SIFT
(extracted or reused), matching of the overlapping pairs, screening of the model's rotations, guided matching.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.colmap_io import pinhole_to_colmap, reconstruction_from_cameras
from ffrecon.errors import InputError
from ffrecon.geometry.overlap import OverlapGraph
from ffrecon.sfm.features import (
    CameraModel,
    FeatureStats,
    copy_features,
    copy_verified_matches,
    create_database,
    extract_sift,
    match_pairs,
    set_database_cameras,
    verify_pairs,
    write_pairs,
)
from ffrecon.sfm.refine.guided import GuidanceStats, MatchGuidance, filter_matches, guided_matches
from ffrecon.sfm.refine.options import RefineOptions, WeakFrame, WeakReason
from ffrecon.sfm.refine.screen import Suspect, drop_contradicting_pairs, screen_rotations
from ffrecon.timing import StageTimer
from ffrecon.types import PinholeCamera, Prediction
from ffrecon.validate import validate_prediction

logger = logging.getLogger("ffrecon.sfm")


def _check_inputs(image_dir: Path, prediction: Prediction) -> None:
    missing = [n for n in prediction.names if not (Path(image_dir) / n).is_file()]
    if missing:
        raise InputError(
            f"{len(missing)} images of the prediction are not in {image_dir}, e.g. {missing[0]}",
            "pass the folder the model read",
        )
    if len(prediction) < 2:
        raise InputError(f"refinement needs at least two images, got {len(prediction)}", "add images")
    validate_prediction(prediction, allow_empty_depth=True)


def _shared_camera(prediction: Prediction) -> PinholeCamera | None:
    """Median intrinsics if every frame has the same image size, else None."""
    sizes = {(c.width, c.height) for c in prediction.cameras}
    if len(sizes) != 1:
        return None
    w, h = sizes.pop()
    k = np.median([[c.fx, c.fy, c.cx, c.cy] for c in prediction.cameras], axis=0)
    return PinholeCamera(w, h, float(k[0]), float(k[1]), float(k[2]), float(k[3]))


def _weak_by_features(stats: FeatureStats, options: RefineOptions) -> list[WeakFrame]:
    out = []
    for name, kps, matches in zip(stats.names, stats.num_keypoints, stats.num_inlier_matches):
        if kps < options.min_features:
            out.append(WeakFrame(name, WeakReason.FEW_FEATURES, int(kps), options.min_features))
        elif matches < options.min_matches:
            out.append(WeakFrame(name, WeakReason.FEW_MATCHES, int(matches), options.min_matches))
    return out


def _colmap_camera(camera: PinholeCamera, camera_id: int, square_pixels: bool) -> pycolmap.Camera:
    """PINHOLE, or SIMPLE_RADIAL (one focal length, radial term starting at 0) when pixels are square.

    With fx and fy both free, an orbit of cameras looking at a common point leaves the focal lengths
    and a common tilt of all cameras nearly undetermined; one focal length removes that freedom. The
    radial term is refined only in the fine pass (:class:`~ffrecon.sfm.refine.bundle.BundleOptions`).
    """
    if not square_pixels:
        return pinhole_to_colmap(camera, camera_id)
    focal = float(np.sqrt(camera.fx * camera.fy))
    return pycolmap.Camera(
        model="SIMPLE_RADIAL",
        width=camera.width,
        height=camera.height,
        params=[focal, camera.cx, camera.cy, 0.0],
        camera_id=camera_id,
    )


def _prepare_database(
    image_dir: Path,
    prediction: Prediction,
    options: RefineOptions,
    db_path: Path,
    timer: StageTimer,
    mask_dir: Path | None = None,
    reuse_features_from: Path | None = None,
) -> tuple[dict[str, int], list[PinholeCamera], dict[str, pycolmap.Camera], list[str]]:
    """Database with the feed-forward cameras and SIFT of every image.

    Returns the database image id of each name, the feed-forward camera used for each frame, the
    COLMAP camera of each name (as written to the database) and the names whose SIFT was reused.
    """
    names = prediction.names
    shared = _shared_camera(prediction) if options.single_camera else None
    cameras = [shared] * len(names) if shared is not None else list(prediction.cameras)
    image_ids = create_database(
        db_path,
        image_dir,
        names,
        camera_model=CameraModel.PINHOLE,
        single_camera=shared is not None,
        focal_prior_px=[c.fx for c in cameras],
    )
    db = pycolmap.Database.open(str(db_path))
    camera_of = {image.name: image.camera_id for image in db.read_all_images()}
    db.close()
    colmap_cameras = {
        camera_of[n]: _colmap_camera(c, camera_of[n], options.square_pixels) for n, c in zip(names, cameras)
    }
    set_database_cameras(db_path, list(colmap_cameras.values()))
    with timer.stage("feature_extraction"):
        copied = copy_features(reuse_features_from, db_path, names) if reuse_features_from else []
        if len(copied) < len(names):
            extract_sift(db_path, image_dir, [n for n in names if n not in copied], options.sift, mask_dir=mask_dir)
    if copied:
        logger.info("reused SIFT features of %d images from %s", len(copied), reuse_features_from)
    return image_ids, cameras, {n: colmap_cameras[camera_of[n]] for n in names}, copied


def _initial_model(
    prediction: Prediction,
    image_ids: dict[str, int],
    cameras: list[PinholeCamera],
    colmap_cameras: dict[str, pycolmap.Camera],
    shared: bool,
) -> pycolmap.Reconstruction:
    """The feed-forward cameras as a model whose image and camera ids equal the database's."""
    names = prediction.names
    order = sorted(range(len(names)), key=lambda k: image_ids[names[k]])
    rec = reconstruction_from_cameras(
        [names[k] for k in order],
        prediction.cam_from_world[order],
        [cameras[k] for k in order],
        share_identical_cameras=shared,
    )
    for image in rec.images.values():
        camera = colmap_cameras[image.name]
        if image_ids[image.name] != image.image_id or camera.camera_id != image.camera_id:
            raise RuntimeError(f"model and database disagree on the ids of {image.name}")
        rec.cameras[image.camera_id] = camera
    return rec


def _reuse_matches(
    db_path: Path,
    graph: OverlapGraph,
    names: tuple[str, ...],
    copied: list[str],
    options: RefineOptions,
    reuse_features_from: Path | None,
) -> list[tuple[str, str]]:
    """The cross-check's verified matches of the pairs that the feed-forward geometry says overlap at all.

    They cost nothing to reuse, so every such pair is taken, not only the best few per image that
    :func:`overlap_graph` picks for fresh matching: the refinement sees as many constraints as COLMAP did.
    """
    if reuse_features_from is None or not copied:
        return []
    reused_images = set(copied)
    score = graph.score()
    overlapping = [
        (names[i], names[j])
        for i in range(len(names))
        for j in range(i + 1, len(names))
        if score[i, j] >= options.overlap.min_any_overlap and {names[i], names[j]} <= reused_images
    ]
    reused = copy_verified_matches(reuse_features_from, db_path, overlapping)
    logger.info("reused the cross-check's verified matches of %d overlapping pairs", len(reused))
    return reused


def _match_unguided(
    db_path: Path, pairs: list[tuple[str, str]], reused: list[tuple[str, str]], options: RefineOptions, pairs_path: Path
) -> list[tuple[str, str]]:
    """COLMAP's matching and verification of ``pairs`` not among ``reused`` (verified already); none when
    the matching is to be guided from the start. Returns the pairs verified."""
    if options.guidance.mode is MatchGuidance.GUIDED:
        return []
    done = {frozenset(p) for p in reused}
    fresh = [p for p in pairs if frozenset(p) not in done]
    if fresh:
        match_pairs(db_path, fresh, options.sift, pairs_path)
    return list(reused) + fresh


def _guide(
    db_path: Path,
    prediction: Prediction,
    pairs: list[tuple[str, str]],
    verified: list[tuple[str, str]],
    options: RefineOptions,
    pairs_path: Path,
    unscreened: Prediction | None = None,
) -> GuidanceStats | None:
    """Check the ``verified`` matches against the prediction, or match ``pairs`` again guided by it, as
    ``options.guidance.mode`` says. Matching again on look-alike surfaces, it is guided by ``unscreened`` (the
    model's cameras, before any frame was reseeded from its pairs) where given."""
    mode = options.guidance.mode
    if mode is MatchGuidance.NONE:
        return None
    if mode is not MatchGuidance.GUIDED:
        least = options.sift.min_num_inliers
        stats = filter_matches(db_path, prediction, verified, options.guidance, min_inliers=least)
        if mode is MatchGuidance.FILTER or stats.rejected_share <= options.guidance.auto_max_rejected:
            return stats
        logger.warning(
            "the feed-forward geometry rejects %.0f%% of the verified SIFT matches: look-alike surfaces (repeated "
            "texture?); matching again, guided by the feed-forward geometry",
            100 * stats.rejected_share,
        )
    if mode is not MatchGuidance.GUIDED and unscreened is not None:
        prediction = unscreened
    stats = guided_matches(db_path, prediction, pairs, options.guidance)
    verify_pairs(db_path, write_pairs(pairs_path, pairs), options.sift)
    dropped = drop_contradicting_pairs(db_path, prediction, options.guidance.max_pair_gap_deg, options.screen)
    if dropped:
        logger.warning(
            "look-alike surfaces: %d verified pair(s) turned more than %.0f deg from the model's cameras dropped "
            "(a pattern's period off?): %s",
            len(dropped),
            options.guidance.max_pair_gap_deg,
            ", ".join(f"{prediction.names[g.index1]}-{prediction.names[g.index2]} ({g.gap_deg:.1f})" for g in dropped),
        )
    return dataclasses.replace(stats, dropped_pairs=len(dropped))


def _on_lookalikes(options: RefineOptions, guidance: GuidanceStats | None) -> RefineOptions:
    """The options for the adjustment once the matching is known. On look-alike surfaces (the matching was
    guided) the dense tracking does not move the model's prediction first (``DenseOptions.prealign``) nor writes a
    pair turned further from the model than a guided pair may be (``DenseOptions.max_model_gap_deg``), and:

    - no frame is relocalised. Its renderings are matched by SIFT alone, and a pattern's period off is a pose the
      dense evidence then agrees with: on the repeated-texture room (seed 101, ``--quick``) a frame the model had
      within 3 deg was placed 84 deg off and called corrected;
    - two-view tracks are triangulated and the fine pass is robust (Cauchy), as with dense evidence. Ignoring them
      (COLMAP's default) leaves the few tracks over three frames, where a pair a period off joins the others'
      points wrongly: on the repeated-tile room of seed 204 (``tools/sweep_families.py``, ``--quick``) 459 points
      were left, and frames 0 and 1 ended 4-5 deg off with every one of their own matches right; with the
      two-view tracks, 0.04-0.22 deg.
    """
    if guidance is None or not guidance.lookalike:
        return options
    # nor is the dense tracking's prediction moved by the photos' consensus (sfm/refine/prealign.py): the patches
    # agree on a period as well as on the truth (held-out street seed 327, repeated tiles: the second adjustment,
    # on such tracks, kept no frame and the run failed its gates)
    gap = options.guidance.max_pair_gap_deg
    options = dataclasses.replace(
        options, dense=dataclasses.replace(options.dense, prealign=False, max_model_gap_deg=gap)
    )
    bundle = options.bundle
    if options.guidance.two_view_tracks:
        bundle = dataclasses.replace(bundle, ignore_two_view_tracks=False, robust_fine=True)
    if not options.relocalize.enabled:
        return dataclasses.replace(options, bundle=bundle)
    logger.info("look-alike surfaces: no frame is relocalised from renderings (a pattern's period would place it)")
    relocalize = dataclasses.replace(options.relocalize, enabled=False)
    return dataclasses.replace(options, bundle=bundle, relocalize=relocalize)


def _screen(db_path: Path, prediction: Prediction, verified: list, options: RefineOptions) -> tuple[Suspect, ...]:
    """The frames whose COLMAP-verified pairs (before any filtering by the model) contradict their model
    rotation; nothing to screen when the matching is guided from the start."""
    if not verified:
        return ()
    suspects, _ = screen_rotations(db_path, prediction, options.screen)
    for s in suspects:
        logger.warning(
            "%s: %d of its %d verified pairs put it %.1f deg from the model's rotation; starting the "
            "adjustment from their rotation",
            prediction.names[s.index],
            s.num_agreeing,
            s.num_pairs,
            s.gap_deg,
        )
    return suspects
