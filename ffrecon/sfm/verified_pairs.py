"""What COLMAP's verified pairs say about chosen images: shared matches and parallax.

A failed registration is explained by the images COLMAP left out (see
:func:`ffrecon.sfm.crosscheck.registration.diagnose_registration`): how many verified matches each shares with its
best neighbours, and how much parallax those pairs have. COLMAP's database keeps each verified
pair's inlier matches and its geometry, but not its triangulation angle (pycolmap 4.x has
``TwoViewGeometry.tri_angle``, yet a geometry read back from the database says -1), so it is
measured here: the pair's calibrated relative pose from an essential matrix fitted to its verified
inliers with the database cameras (the EXIF focal prior, or COLMAP's guess of 1.2 x the longest
side), then COLMAP's own ``estimate_two_view_geometry_pose``, which triangulates the inliers with
the cheirality check and fills ``tri_angle`` with their median triangulation angle, as COLMAP does
for its initial pair. The essential matrix is fitted afresh rather than read from the database
because most pairs of a forward walk are stored as UNCALIBRATED (a fundamental matrix only), and
decomposing that through the cameras scatters: on six lund photos without EXIF, the pairs with 100 or
more matches measure 0.04 to 5.5 degrees that way, 0.7 to 1.6 with a fitted essential matrix, and 0.8
to 2.1 in the model COLMAP builds from all 29 photos with the EXIF focal length.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

# Configurations COLMAP's mappers use as edges; DEGENERATE, WATERMARK and MULTIPLE pairs are not.
_USABLE = frozenset(
    {
        pycolmap.TwoViewGeometryConfiguration.CALIBRATED,
        pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED,
        pycolmap.TwoViewGeometryConfiguration.PLANAR,
        pycolmap.TwoViewGeometryConfiguration.PANORAMIC,
        pycolmap.TwoViewGeometryConfiguration.PLANAR_OR_PANORAMIC,
    }
)
_MIN_POSE_INLIERS = 8  # fewer verified matches give no trustworthy relative pose


@dataclass(frozen=True)
class ImagePairs:
    """The best verified pairs of one image with any other image, most inlier matches first."""

    name: str
    num_inliers: np.ndarray = field(repr=False)  # [P] int, verified inlier matches with each neighbour
    tri_angle_deg: np.ndarray = field(repr=False)  # [P] float64, median triangulation angle; nan: no pose

    @property
    def best_inliers(self) -> int:
        """Verified matches shared with the best neighbour (0 without any verified pair).

        >>> ImagePairs("a.jpg", np.array([158, 71]), np.array([11.7, 22.0])).best_inliers
        158
        """
        return int(self.num_inliers[0]) if len(self.num_inliers) else 0


def read_image_pairs(
    db_path: Path, names: Sequence[str], *, max_pairs: int = 5, max_images: int = 50
) -> tuple[ImagePairs, ...]:
    """The ``max_pairs`` best verified pairs of each of ``names``, with their triangulation angles.

    Bounded: at most ``max_images`` of ``names`` (evenly spread, in their order) and ``max_pairs``
    relative poses each. A name the database lacks gets no pairs. Raises ``FileNotFoundError`` when
    the database is gone.
    """
    if not Path(db_path).is_file():
        raise FileNotFoundError(f"no COLMAP database at {db_path}")
    names = list(names)
    if len(names) > max_images:
        names = [names[k] for k in np.linspace(0, len(names) - 1, max_images).round().astype(int)]
    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        neighbours = _neighbours(db)
        keypoints: dict[int, np.ndarray] = {}
        angles: dict[tuple[int, int], float | None] = {}  # per pair, shared by both of its images
        out = []
        for name in names:
            image_id = ids.get(name)
            rows = []
            for count, other in neighbours.get(image_id, []):
                key = (min(image_id, other), max(image_id, other))
                if key not in angles:
                    angles[key] = _tri_angle_deg(db, key, keypoints)
                if angles[key] is not None:
                    rows.append((count, angles[key]))
                if len(rows) == max_pairs:
                    break
            out.append(
                ImagePairs(name, np.array([r[0] for r in rows], int), np.array([r[1] for r in rows], np.float64))
            )
    finally:
        db.close()
    return tuple(out)


def _neighbours(db: pycolmap.Database) -> dict[int, list[tuple[int, int]]]:
    """``{image id: [(verified inlier matches, other image id)]}``, most matches first (then by id)."""
    pair_ids, counts = db.read_two_view_geometry_num_inliers()
    neighbours: dict[int, list[tuple[int, int]]] = {}
    for pair_id, count in zip(pair_ids, counts):
        if count > 0:
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            neighbours.setdefault(a, []).append((int(count), b))
            neighbours.setdefault(b, []).append((int(count), a))
    for pairs in neighbours.values():
        pairs.sort(key=lambda pair: (-pair[0], pair[1]))
    return neighbours


def _tri_angle_deg(db: pycolmap.Database, ids: tuple[int, int], keypoints: dict[int, np.ndarray]) -> float | None:
    """Median triangulation angle (degrees) of the pair's verified inliers; nan without a relative pose.

    None when the pair is no edge of COLMAP's graph (degenerate, watermark, several motions).
    """
    geometry = db.read_two_view_geometry(*ids)
    if geometry.config not in _USABLE:
        return None
    calibrated = _relative_pose(db, ids, geometry, keypoints)
    if calibrated is None or calibrated.tri_angle < 0:
        return float("nan")
    return float(np.degrees(calibrated.tri_angle))


def _relative_pose(
    db: pycolmap.Database,
    ids: tuple[int, int],
    geometry: pycolmap.TwoViewGeometry,
    keypoints: dict[int, np.ndarray],
    min_trials: int | None = None,
    max_matches: int | None = None,
) -> pycolmap.TwoViewGeometry | None:
    """The pair's calibrated relative pose (``cam2_from_cam1``, ``tri_angle``) from its verified inliers, or
    None. ``min_trials``: RANSAC's minimum number of trials (None: pycolmap's 1000); ``max_matches``: at most
    this many of the inliers, evenly spaced in the database's order (None: all)."""
    matches = np.asarray(geometry.inlier_matches)
    if len(matches) < _MIN_POSE_INLIERS:
        return None
    if max_matches is not None and len(matches) > max_matches:
        matches = matches[np.linspace(0, len(matches) - 1, max_matches).round().astype(int)]
    for image_id in ids:
        if image_id not in keypoints:
            keypoints[image_id] = np.asarray(db.read_keypoints(image_id))[:, :2].astype(np.float64)
    cameras = [db.read_camera(db.read_image(image_id).camera_id) for image_id in ids]
    points1, points2 = keypoints[ids[0]][matches[:, 0]], keypoints[ids[1]][matches[:, 1]]
    ransac = pycolmap.RANSACOptions()
    ransac.random_seed = 0
    if min_trials is not None:
        ransac.min_num_trials = min_trials
    essential = pycolmap.estimate_essential_matrix(points1, points2, cameras[0], cameras[1], ransac)
    if essential is None:
        return None
    inliers = np.flatnonzero(np.asarray(essential["inlier_mask"], bool)).astype(np.uint32)
    calibrated = pycolmap.TwoViewGeometry()
    calibrated.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    calibrated.E = essential["E"]
    calibrated.inlier_matches = np.stack([inliers, inliers], axis=1)
    if not pycolmap.estimate_two_view_geometry_pose(cameras[0], points1, cameras[1], points2, calibrated):
        return None
    return calibrated


@dataclass(frozen=True)
class RelativeRotation:
    """What a verified pair says of its two cameras' relative pose, whatever their poses: the rotation,
    and the direction of the baseline (an essential matrix has no scale)."""

    name1: str
    name2: str
    num_inliers: int  # verified matches the essential matrix kept
    cam2_from_cam1: np.ndarray = field(repr=False)  # [3, 3] float64 rotation
    # [3] float64 unit vector: camera 1's centre as seen from camera 2 (cam2_from_cam1's translation, unit length)
    cam1_centre_in_cam2: np.ndarray = field(repr=False)


def relative_rotations(
    db_path: Path, names: Sequence[str], *, min_inliers: int = 15, max_matches: int | None = None
) -> tuple[RelativeRotation, ...]:
    """The relative rotation of every verified pair that involves one of ``names`` and has at least
    ``min_inliers`` matches in its essential matrix (COLMAP's database, any matcher's matches), fitted to
    at most ``max_matches`` of its verified matches (None: all; the inlier count is then of those).

    The matches were verified already, so nearly all are inliers and RANSAC's confidence is reached in
    a few dozen trials: its minimum is lowered from pycolmap's 1000 to 50 (the trials stay adaptive).
    On the demo's 109 pairs this took the time from 2.0 s to 0.2 s."""
    db = pycolmap.Database.open(str(db_path))
    try:
        id_of = {image.name: image.image_id for image in db.read_all_images()}
        name_of = {v: k for k, v in id_of.items()}
        wanted = {id_of[n] for n in names if n in id_of}
        keypoints: dict[int, np.ndarray] = {}
        out = []
        pair_ids, counts = db.read_two_view_geometry_num_inliers()
        for pair_id, count in zip(pair_ids, counts):
            ids = tuple(int(x) for x in pycolmap.pair_id_to_image_pair(pair_id))
            if count < min_inliers or not wanted & set(ids):
                continue
            geometry = db.read_two_view_geometry(*ids)
            if geometry.config not in _USABLE:
                continue
            pose = _relative_pose(db, ids, geometry, keypoints, min_trials=50, max_matches=max_matches)
            if pose is None or len(pose.inlier_matches) < min_inliers:
                continue
            rotation = np.asarray(pose.cam2_from_cam1.rotation.matrix(), np.float64)
            baseline = np.asarray(pose.cam2_from_cam1.translation, np.float64)
            baseline = baseline / max(float(np.linalg.norm(baseline)), 1e-300)
            out.append(RelativeRotation(name_of[ids[0]], name_of[ids[1]], len(pose.inlier_matches), rotation, baseline))
    finally:
        db.close()
    return tuple(out)
