"""The refinement's passes over a model (:func:`refine_tracks`): a coarse pass with tolerances wide enough for
the model's pose errors, then fine passes with COLMAP's usual ones, each triangulating and adjusting with
:class:`ffrecon.sfm.refine.bundle._Adjuster`; and the similarity back into the model's world frame.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Collection, Sequence
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.colmap_io import cam_from_world_by_name
from ffrecon.geometry.alignment import Sim3, camera_sim3
from ffrecon.geometry.rotations import matrix_to_quat_xyzw
from ffrecon.sfm.refine.bundle import (
    BundleOptions,
    BundleSummary,
    _Adjuster,
    _diverged,
    _mapper_options,
    _summary,
    _tri_options,
)
from ffrecon.sfm.refine.lens import LensTrial, distortion_may_pay, distortion_pays

logger = logging.getLogger("ffrecon.sfm")


def _rounds(
    mapper: pycolmap.IncrementalMapper,
    rec: pycolmap.Reconstruction,
    adjust: _Adjuster,
    options: BundleOptions,
    tri: pycolmap.IncrementalTriangulatorOptions,
    mapper_options: pycolmap.IncrementalMapperOptions,
    loss: pycolmap.LossFunctionType,
    max_refinements: int,
    function_tolerance: float,
    max_iterations: int | None = None,
    end_adjusted: bool = True,
) -> None:
    """Rounds of (bundle adjustment, track completion and merging, filtering) until fewer than
    ``max_refinement_change`` of the observations change; ending adjusted if asked and the rounds ran out."""
    mapper.complete_and_merge_tracks(tri)
    mapper.retriangulate(tri)
    changed = 1
    for _ in range(max_refinements):
        num_obs = max(rec.compute_num_observations(), 1)
        mapper.observation_manager.filter_observations_with_negative_depth()
        if not adjust(rec, loss, function_tolerance=function_tolerance, max_iterations=max_iterations):
            return
        changed = mapper.complete_and_merge_tracks(tri) + mapper.filter_points(mapper_options)
        if changed / num_obs < options.max_refinement_change:
            break  # converged, as COLMAP's global refinement stops: the last small change is not adjusted again
    else:
        if changed and end_adjusted:  # the rounds ran out while the model still changed: adjust once more
            adjust(rec, loss, function_tolerance=function_tolerance, max_iterations=max_iterations)


def _pass(
    cache: pycolmap.DatabaseCache,
    rec: pycolmap.Reconstruction,
    adjust: _Adjuster,
    options: BundleOptions,
    *,
    angle_deg: float,
    reproj_px: float,
    loss: pycolmap.LossFunctionType,
    max_refinements: int,
    function_tolerance: float,
    max_iterations: int | None = None,
    register: Collection[int] = (),
    end_adjusted: bool = True,
) -> tuple[pycolmap.IncrementalMapper, list[int]]:
    """Triangulate every registered image from scratch, refine; then try to register ``register``.

    Images in ``register`` (unregistered) are registered by absolute pose against the refined points,
    as COLMAP registers its next images; returns the mapper and the ids that registered.
    """
    rec.delete_all_points2D_and_points3D()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    tri = _tri_options(angle_deg, reproj_px, options)
    mapper_options = _mapper_options(reproj_px, options)
    for image_id in sorted(rec.reg_image_ids()):
        mapper.triangulate_image(tri, image_id)
    _rounds(
        mapper,
        rec,
        adjust,
        options,
        tri,
        mapper_options,
        loss,
        max_refinements,
        function_tolerance,
        max_iterations,
        end_adjusted,
    )
    added = []
    for image_id in sorted(register):
        # An image with no correspondence at all is not in the database cache: nothing to register it on.
        known = cache.exists_image(image_id) and cache.correspondence_graph.exists_image(image_id)
        if known and rec.num_reg_images() >= 2 and mapper.register_next_image(mapper_options, image_id):
            mapper.triangulate_image(tri, image_id)
            added.append(image_id)
    if added:
        _rounds(mapper, rec, adjust, options, tri, mapper_options, loss, max_refinements, function_tolerance)
    return mapper, added


def refine_tracks(
    rec: pycolmap.Reconstruction,
    db_path: Path,
    usable: Collection[str],
    options: BundleOptions,
    *,
    min_observations: int,
    fixed: Collection[str] = (),
) -> tuple[pycolmap.Reconstruction, BundleSummary | None, list[tuple[str, int]]]:
    """Triangulate and bundle-adjust ``rec`` (image ids equal to the database's).

    Frames not in ``usable`` are deregistered first. Frames that the coarse pass leaves with fewer
    than ``min_observations`` points (a feed-forward pose too wrong for its tolerances) are taken
    out and registered again by absolute pose after the fine pass; frames still below
    ``min_observations`` at the end are deregistered and flagged. With ``options.refine_distortion``
    the fine pass runs again with the radial term free, and the lens model that pays is kept, unless freeing
    the term on the pinhole pass's solution shows it cannot pay (:func:`ffrecon.sfm.refine.lens.distortion_may_pay`).
    Returns ``(rec, summary, [(name, observations) of the weak frames])`` (``rec`` may be a new
    object); the summary is None if no adjustment ran. ``fixed``: frames whose poses (given ones) every
    adjustment holds constant and that are never registered again.
    """
    cache = _database_cache(db_path)
    names = {image.image_id: image.name for image in rec.images.values()}
    for image in list(rec.images.values()):
        if image.name not in usable and image.has_pose:
            rec.deregister_frame(image.frame_id)
    adjust = _adjuster_for(rec, options, frozenset(i for i, n in names.items() if n in set(fixed)))
    retry = _coarse_pass(cache, rec, adjust, options, min_observations)
    radial = any(camera.model.name == "SIMPLE_RADIAL" for camera in rec.cameras.values())
    trial = pycolmap.Reconstruction(rec) if options.refine_distortion and radial else None
    weak = _fine_pass(cache, rec, adjust, options, retry, min_observations, names)
    if (why := _diverged(rec, options.max_reproj_error_px)) is not None:
        logger.warning("the bundle adjustment diverged (%s): no frame is refined", why)
        return rec, None, weak
    if trial is None:
        return rec, _summary(adjust), weak
    adjust_k = copy.copy(adjust)
    adjust_k.refine_distortion = True
    probe = copy.copy(adjust_k)
    probe.whole_after_thin = False  # on a long capture the thinned solve is enough to tell the gain
    if not distortion_may_pay(rec, probe, options.min_distortion_px, options.min_distortion_gain):
        return rec, _summary(adjust, LensTrial.PROBED), weak
    weak_k = _fine_pass(cache, trial, adjust_k, options, retry, min_observations, names)
    broken = _diverged(trial, options.max_reproj_error_px)
    if broken is None and distortion_pays(rec, trial, options.min_distortion_px, options.min_distortion_gain):
        return trial, _summary(adjust_k, LensTrial.KEPT), weak_k
    return rec, _summary(adjust, LensTrial.REJECTED), weak


def _fine_pass(
    cache: pycolmap.DatabaseCache,
    rec: pycolmap.Reconstruction,
    adjust: _Adjuster,
    options: BundleOptions,
    retry: list[int],
    min_observations: int,
    names: dict[int, str],
) -> list[tuple[str, int]]:
    """Fresh tracks from the coarse cameras, COLMAP's tolerances, converged to the end; the weak frames."""
    mapper, added = _pass(
        cache,
        rec,
        adjust,
        options,
        angle_deg=0.0,
        reproj_px=options.max_reproj_error_px,
        loss=_fine_loss(options),
        max_refinements=options.max_refinements,
        function_tolerance=options.fine_function_tolerance,
        register=retry,
    )
    if added:
        logger.info("registered %d frames again whose feed-forward pose was far off", len(added))
    weak = [(names[i], 0) for i in retry if i not in added]
    weak += _deregister_weak_frames(rec, mapper, min_observations)
    if len(weak) > len(retry) - len(added) and rec.num_reg_images() >= 2:
        adjust(rec, _fine_loss(options))
    mapper.end_reconstruction(False)
    return weak


def _fine_loss(options: BundleOptions) -> pycolmap.LossFunctionType:
    return pycolmap.LossFunctionType.CAUCHY if options.robust_fine else pycolmap.LossFunctionType.TRIVIAL


def _coarse_pass(
    cache: pycolmap.DatabaseCache,
    rec: pycolmap.Reconstruction,
    adjust: _Adjuster,
    options: BundleOptions,
    min_observations: int,
) -> list[int]:
    """Tolerances wide enough for the feed-forward errors, a robust loss, loose convergence.

    It does not end adjusted (the fine pass triangulates afresh anyway). Returns the ids of the
    frames left with fewer than ``min_observations`` points, which are deregistered.
    """
    adjust.whole_after_thin = False
    mapper, _ = _pass(
        cache,
        rec,
        adjust,
        options,
        angle_deg=options.coarse_error_deg,
        reproj_px=_coarse_reproj_px(rec, options),
        loss=pycolmap.LossFunctionType.CAUCHY,
        max_refinements=options.coarse_refinements,
        function_tolerance=options.coarse_function_tolerance,
        max_iterations=options.coarse_max_iterations,
        end_adjusted=False,
    )
    adjust.whole_after_thin = True
    retry = [
        i for i in rec.reg_image_ids() if rec.image(i).num_points3D < min_observations and i not in adjust.constant
    ]
    for image_id in retry:
        mapper.observation_manager.deregister_frame(rec.image(image_id).frame_id)
    mapper.end_reconstruction(False)
    logger.debug(
        "coarse pass: %d points, %d observations, %d frames to register again",
        rec.num_points3D(),
        rec.compute_num_observations(),
        len(retry),
    )
    return retry


def _database_cache(db_path: Path) -> pycolmap.DatabaseCache:
    """The database's images, cameras and correspondence graph (every matched pair kept)."""
    cache_options = pycolmap.DatabaseCacheOptions()
    cache_options.min_num_matches = 1
    db = pycolmap.Database.open(str(db_path))
    try:
        return pycolmap.DatabaseCache.create(db, cache_options)
    finally:
        db.close()


def _adjuster_for(
    rec: pycolmap.Reconstruction, options: BundleOptions, constant: frozenset[int] = frozenset()
) -> _Adjuster:
    """The bundle adjuster for ``rec``: position priors at the current (feed-forward) camera centres when
    ``options.use_pose_priors`` and there are three or more frames, with a std relative to their extent;
    ``constant`` image ids keep their poses (then no priors)."""
    centers = {i: rec.image(i).projection_center() for i in rec.reg_image_ids()}
    if constant or not (options.use_pose_priors and len(centers) >= 3):
        return _Adjuster(options, None, 0.0, constant)
    pts = np.array(list(centers.values()))
    prior_std = options.prior_position_std * float(np.linalg.norm(pts.max(0) - pts.min(0)))
    return _Adjuster(options, centers, prior_std)


def _coarse_reproj_px(rec: pycolmap.Reconstruction, options: BundleOptions) -> float:
    """The reprojection error (pixels, at the mean focal length) of a ``coarse_error_deg`` pose error."""
    focal = float(np.mean([rec.camera(rec.image(i).camera_id).mean_focal_length() for i in rec.reg_image_ids()]))
    return focal * np.tan(np.radians(options.coarse_error_deg))


def _deregister_weak_frames(
    rec: pycolmap.Reconstruction, mapper: pycolmap.IncrementalMapper, min_observations: int
) -> list[tuple[str, int]]:
    """Deregister the frames that see fewer than ``min_observations`` points; ``[(name, observations)]``."""
    weak = []
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        if image.num_points3D < min_observations:
            weak.append((image.name, int(image.num_points3D)))
            mapper.observation_manager.deregister_frame(image.frame_id)
    return weak


def sim3_to_ff_frame(rec: pycolmap.Reconstruction, names: Sequence[str], ff_cam_from_world: np.ndarray) -> Sim3:
    """Move ``rec`` (in place) into the feed-forward world frame; returns ``ff_from_refined``.

    :func:`~ffrecon.geometry.alignment.camera_sim3` over the refined frames: a fit to the camera centres or
    to their orientations, each robust to a badly predicted frame, whichever holds the rotation better
    (orientations where the centres lie on a line or near a plane). On lund's every 4th photo the centre
    fit had turned the whole refined model 99 degrees about the walk; on the wide-baseline scene (seed 15,
    frame 1 25 deg off, centres within 0.15 of a plane 3.5 across) it tilted it 12-15 degrees, and every
    well refined frame was then called a correction; on a furnished room photographed from its middle
    (centres bunched, not flat) 9.5 degrees, and six of eight well refined frames were called corrections.
    """
    cam_from_world, registered = cam_from_world_by_name(rec, names)
    if registered.sum() < 2:
        return Sim3.identity()
    sim = camera_sim3(cam_from_world[registered], ff_cam_from_world[registered])
    quat = matrix_to_quat_xyzw(sim.rotation)
    rec.transform(pycolmap.Sim3d(sim.scale, pycolmap.Rotation3d(quat), sim.translation))
    return sim
