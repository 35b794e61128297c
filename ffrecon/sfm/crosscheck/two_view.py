"""A two-view reconstruction built from COLMAP's verified geometry when its mappers build none.

Two photos taken a step apart while walking forward share hundreds of verified matches, yet COLMAP's
mappers refuse them: the incremental mapper wants a wide initial pair, the global one more views. With
a focal-length prior (EXIF) the relative pose is still well determined by the essential matrix, so
ffrecon estimates it (OpenCV's five-point RANSAC and cheirality check on the verified inliers; COLMAP's
Python API exposes no essential-matrix decomposition for a pair it did not initialise), triangulates
the inliers, and refines the two cameras and the points with pycolmap's bundle adjustment (focal
length fixed: two views cannot tell it from depth). The baseline is of unit length.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ffrecon.checks import check_number
from ffrecon.colmap_io import rigid_from_pose

logger = logging.getLogger("ffrecon.sfm")


@dataclass(frozen=True, kw_only=True)
class TwoViewOptions:
    enabled: bool = True
    min_inliers: int = 100  # verified matches needed (COLMAP's init_min_num_inliers)
    ransac_px: float = 1.0  # essential-matrix RANSAC threshold, pixels
    max_reproj_error_px: float = 4.0  # COLMAP's filter threshold
    min_tri_angle_deg: float = 0.5  # forward motion: small angles are all there is, but not none
    min_points: int = 30
    max_iterations: int = 100  # bundle adjustment

    def __post_init__(self) -> None:
        for name in ("min_inliers", "min_points", "max_iterations"):
            check_number(f"TwoViewOptions.{name}", getattr(self, name), low=0, integer=True)
        for name in ("ransac_px", "max_reproj_error_px"):
            check_number(f"TwoViewOptions.{name}", getattr(self, name), low=0, low_open=True)
        check_number("TwoViewOptions.min_tri_angle_deg", self.min_tri_angle_deg, low=0)


def _keypoints(db: pycolmap.Database, image_id: int) -> np.ndarray:
    return np.asarray(db.read_keypoints(image_id))[:, :2].astype(np.float64)


def _normalised(xy: np.ndarray, camera: pycolmap.Camera) -> np.ndarray:
    """Pixel positions (COLMAP's rule) to normalised image coordinates, through the camera's own model."""
    return np.asarray(camera.cam_from_img(xy), np.float64)


def _triangulate(x1: np.ndarray, x2: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``[M, 3]`` points in camera 1's frame from normalised matches (camera 2 is ``[R | t]``)."""
    h = cv2.triangulatePoints(np.eye(3, 4), np.hstack([R, t.reshape(3, 1)]), x1.T, x2.T)
    return (h[:3] / np.where(np.abs(h[3]) > 1e-12, h[3], 1e-12)).T


def two_view_reconstruction(
    db_path: Path, names: Sequence[str], options: TwoViewOptions = TwoViewOptions()
) -> pycolmap.Reconstruction | None:
    """The two images of ``names`` (database cameras carrying a focal prior), or None with the reason logged.

    Camera and image ids equal the database's; image 1 of the pair (database order) is the world frame.
    """
    if len(names) != 2:
        return None
    db = pycolmap.Database.open(str(db_path))
    try:
        images = sorted((im for im in db.read_all_images() if im.name in names), key=lambda im: im.image_id)
        if len(images) != 2 or not db.exists_two_view_geometry(images[0].image_id, images[1].image_id):
            logger.info("two-view reconstruction: the pair has no verified geometry")
            return None
        ids = [im.image_id for im in images]
        matches = np.asarray(db.read_two_view_geometry(*ids).inlier_matches)
        cameras = [db.read_camera(im.camera_id) for im in images]
        keypoints = [_keypoints(db, i) for i in ids]
    finally:
        db.close()
    if len(matches) < options.min_inliers:
        logger.info("two-view reconstruction: %d verified matches (< %d)", len(matches), options.min_inliers)
        return None
    if not all(c.has_prior_focal_length for c in cameras):
        logger.info("two-view reconstruction: needs a focal-length prior (EXIF) for both photos")
        return None
    xy1, xy2 = keypoints[0][matches[:, 0]], keypoints[1][matches[:, 1]]
    x1, x2 = _normalised(xy1, cameras[0]), _normalised(xy2, cameras[1])
    focal = float(np.mean([c.mean_focal_length() for c in cameras]))
    cv2.setRNGSeed(0)
    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), cv2.RANSAC, 0.999, options.ransac_px / focal)
    if E is None or E.shape != (3, 3):
        logger.info("two-view reconstruction: no essential matrix fits the verified matches")
        return None
    _, R, t, mask = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask)
    xyz = _triangulate(x1, x2, R, t)
    rec = _reconstruction(images, cameras, keypoints, R, t.ravel())
    for k in np.flatnonzero(mask.ravel() > 0):  # RANSAC and cheirality inliers
        track = pycolmap.Track()
        track.add_element(ids[0], int(matches[k, 0]))
        track.add_element(ids[1], int(matches[k, 1]))
        rec.add_point3D(xyz[k], track, np.zeros(3, np.uint8))
    observations = pycolmap.ObservationManager(rec)
    observations.filter_all_points3D(options.max_reproj_error_px, options.min_tri_angle_deg)
    if rec.num_points3D() < options.min_points:
        logger.info("two-view reconstruction: %d points triangulate (< %d)", rec.num_points3D(), options.min_points)
        return None
    _adjust(rec, ids, options)
    observations.filter_all_points3D(options.max_reproj_error_px, options.min_tri_angle_deg)
    rec.update_point_3d_errors()
    logger.info(
        "two-view reconstruction by ffrecon: %d of %d verified matches triangulated, %.2f px",
        rec.num_points3D(),
        len(matches),
        rec.compute_mean_reprojection_error(),
    )
    return rec


def _reconstruction(images, cameras, keypoints, R: np.ndarray, t: np.ndarray) -> pycolmap.Reconstruction:
    rec = pycolmap.Reconstruction()
    for camera in {c.camera_id: c for c in cameras}.values():
        rec.add_camera_with_trivial_rig(camera)
    poses = [rigid_from_pose(np.eye(3, 4)), rigid_from_pose(np.hstack([R, t.reshape(3, 1)]))]
    for image, xy, pose in zip(images, keypoints, poses):
        new = pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id)
        new.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in xy])
        rec.add_image_with_trivial_frame(new, pose)
    return rec


def _adjust(rec: pycolmap.Reconstruction, ids: list[int], options: TwoViewOptions) -> None:
    """Bundle adjustment of the poses and points, focal lengths fixed."""
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = False
    ba.refine_principal_point = False
    ba.refine_extra_params = False
    ba.print_summary = False
    ba.ceres.solver_options.max_num_iterations = options.max_iterations
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in ids:
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(ba, config, rec).solve()
