"""Writing dense correspondences into COLMAP's database (:mod:`ffrecon.sfm.refine.dense`): new keypoints after
SIFT's, and inlier matches added to a pair's two-view geometry."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pycolmap


class Keypoints:
    """New keypoints per image, appended after the ones in the database (SIFT's) when written."""

    def __init__(
        self, db: pycolmap.Database, views: Callable[[int], tuple[np.ndarray, np.ndarray]], image_index: dict[int, int]
    ) -> None:
        self.db, self.views, self.image_index = db, views, image_index
        self.added: dict[int, list[np.ndarray]] = {}
        self.count: dict[int, int] = {}
        self.corner_ids: dict[int, dict[int, int]] = {}  # per image: corner index -> keypoint index

    def corners(self, image_id: int, corner: np.ndarray) -> np.ndarray:
        """Keypoint indices of corners of an image (``corner``: indices into its corners), added once each."""
        known = self.corner_ids.setdefault(image_id, {})
        fresh = [int(c) for c in dict.fromkeys(corner.tolist()) if c not in known]
        if fresh:
            xy = self.views(self.image_index[image_id])[1][fresh].astype(np.float64) + 0.5  # COLMAP's rule
            known.update(zip(fresh, self.add(image_id, xy).tolist()))
        return np.array([known[int(c)] for c in corner], np.uint32)

    def add(self, image_id: int, xy: np.ndarray) -> np.ndarray:
        """Queue ``[M, 2]`` keypoints (COLMAP's rule) of an image; returns their future indices."""
        if image_id not in self.count:
            self.count[image_id] = self.db.num_keypoints_for_image(image_id)
        first = self.count[image_id]
        self.added.setdefault(image_id, []).append(np.asarray(xy, np.float64))
        self.count[image_id] += len(xy)
        return np.arange(first, first + len(xy), dtype=np.uint32)

    def write(self) -> None:
        for image_id, chunks in self.added.items():
            xy = np.concatenate(chunks).astype(np.float32)
            rows = np.zeros((len(xy), 6), np.float32)
            rows[:, :2], rows[:, 2], rows[:, 5] = xy, 1.0, 1.0  # an identity affine shape: no scale or orientation
            if self.db.exists_keypoints(image_id):
                old = np.asarray(self.db.read_keypoints(image_id), np.float32).reshape(-1, 6)
                self.db.update_keypoints(image_id, np.concatenate([old, rows]))
            else:
                self.db.write_keypoints(image_id, rows)


# The configurations whose inlier matches COLMAP's correspondence graph uses (database_cache.cc); the others
# (undefined, degenerate, watermark, multiple) are ignored when the mapper loads the database.
_USED_CONFIGS = frozenset(
    getattr(pycolmap.TwoViewGeometryConfiguration, name)
    for name in ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")
)


def add_matches(db: pycolmap.Database, id_i: int, id_j: int, matches: np.ndarray) -> None:
    """Add ``[M, 2]`` verified matches (indices of i's and j's keypoints) to the pair's two-view geometry."""
    if id_i > id_j:  # COLMAP stores a pair once, smaller image id first
        id_i, id_j, matches = id_j, id_i, matches[:, ::-1]
    matches = np.ascontiguousarray(matches, dtype=np.uint32)
    if db.exists_two_view_geometry(id_i, id_j):
        geometry = db.read_two_view_geometry(id_i, id_j)
        old = np.asarray(geometry.inlier_matches, np.uint32).reshape(-1, 2)
        if geometry.config not in _USED_CONFIGS:
            # SIFT's verification failed here (degenerate: too few inliers). COLMAP's correspondence graph
            # ignores such a pair whatever its matches, so the dense ones would never reach the adjustment:
            # they were verified by the essential matrix above, and the pair is now calibrated.
            geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            old = old[:0]
        geometry.inlier_matches = np.ascontiguousarray(np.concatenate([old, matches]), dtype=np.uint32)
        db.update_two_view_geometry(id_i, id_j, geometry)
        return
    geometry = pycolmap.TwoViewGeometry()
    geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    geometry.inlier_matches = matches
    if not db.exists_matches(id_i, id_j):
        db.write_matches(id_i, id_j, matches)
    db.write_two_view_geometry(id_i, id_j, geometry)
