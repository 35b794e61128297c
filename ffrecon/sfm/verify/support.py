"""What holds a refined frame in place: a frame hanging on one planar pair is not confirmed by it.

A frame can be refined on enough observations and still be placed by a single pair: almost all of
its 3D points seen in one other frame only. When those points also lie on one plane (a wall), the
pair's relative pose is ambiguous: a homography explains the matches as well as the epipolar
geometry does, and the adjustment settles where it starts. On the wide-baseline scene (seed 7) frame
7 hung on frame 0 by 43 of its 50 observations, 94 % of which a homography explains; it ended 5.4 deg
from the truth with a 0.11 px reprojection error, and BA's own covariance said 0.07 deg: the fit
is tight, the geometry is not determined. (Since dense evidence reaches the pairs SIFT could not verify,
sfm/refine/dense.py, that frame is held by several pairs; seed 5's frame 6 is such a case now.)

COLMAP's rule decides planarity, as its two-view geometry does for every pair: the homography's
inliers over the essential matrix's, above ``max_H_inlier_ratio`` (0.8, pycolmap's default). The RANSAC
threshold is 2 px, not COLMAP's 4: these are the refined model's observations, accurate to a few tenths
of a pixel, and at 4 px a homography explained 93 % of the Middlebury motorcycle pair's (a deep scene,
refined to 0.06 deg), 74 % at 2 px and 47 % at 1 px. Not 1 px: on the wide-baseline scene (seed 5, frame 5
25 deg off and wrongly corrected to 9.3 deg) frame 6, 4.7 deg off and hanging on one wall, is planar at 2
px and was called confirmed at 1.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
import pycolmap

PLANAR_RANSAC_PX = 2.0  # the homography's and the essential matrix's RANSAC threshold (see above)


@dataclass(frozen=True)
class PairSupport:
    """A refined frame placed by one pair: its main partner and how planar their shared points are."""

    name: str
    partner: str
    num_observations: int  # the frame's observations in the model
    num_elsewhere: int  # of them, in tracks that reach a frame other than the partner
    planar_ratio: float  # homography inliers / essential-matrix inliers of the pair's observations

    def describe(self) -> str:
        return (
            f"refined on {self.num_observations} observations, all but {self.num_elsewhere} shared with "
            f"{self.partner} alone, whose matches a homography explains ({self.planar_ratio:.0%} of the "
            "essential matrix's inliers): one pair on one plane leaves its pose ambiguous"
        )


def _reaches_two_others(rec: pycolmap.Reconstruction, image: pycolmap.Image, count: int) -> bool:
    """Whether at least ``count`` of the image's tracks reach two other frames or more (then, whichever its
    partner, that many reach a frame besides it). Stops at the ``count``-th: on a dense video the tracks
    grow with the frame count, and reading every one of every frame grew as frames^2 (21 s at 500 frames)."""
    found = 0
    for point2D in image.points2D:
        if point2D.has_point3D():
            track = rec.points3D[point2D.point3D_id].track
            found += len({e.image_id for e in track.elements} - {image.image_id}) >= 2
            if found >= count:
                return True
    return False


def single_pair(rec: pycolmap.Reconstruction, image_id: int, min_elsewhere: int) -> PairSupport | None:
    """The frame's support when one pair holds it, planar or not (fewer than ``min_elsewhere`` observations
    in tracks reaching any frame but its main partner), with the pair's planarity measured; None otherwise."""
    image = rec.images[image_id]
    if _reaches_two_others(rec, image, min_elsewhere):
        return None
    tracks = [rec.points3D[p.point3D_id].track for p in image.points2D if p.has_point3D()]
    others = [{e.image_id for e in t.elements} - {image_id} for t in tracks]
    counts = Counter(i for o in others for i in o)
    if not counts:
        return None
    partner = counts.most_common(1)[0][0]
    elsewhere = sum(bool(o - {partner}) for o in others)
    if elsewhere >= min_elsewhere:
        return None
    ratio = _planar_ratio(rec, image_id, partner)
    return PairSupport(image.name, rec.images[partner].name, len(tracks), elsewhere, ratio)


def is_planar(support: PairSupport) -> bool:
    """COLMAP's planarity rule on the pair's shared observations (nan, too few to tell: not planar)."""
    return bool(support.planar_ratio > pycolmap.TwoViewGeometryOptions().max_H_inlier_ratio)


def planar_single_pair(rec: pycolmap.Reconstruction, image_id: int, min_elsewhere: int) -> PairSupport | None:
    """The frame's support when it hangs on one planar pair (:func:`single_pair`, and COLMAP's planarity test
    passes on the pair's shared observations); None otherwise."""
    support = single_pair(rec, image_id, min_elsewhere)
    return support if support is not None and is_planar(support) else None


def _planar_ratio(rec: pycolmap.Reconstruction, image_id: int, partner: int) -> float:
    """Homography inliers over essential-matrix inliers of the two frames' shared observations (nan: too few)."""
    mine, theirs = [], []
    for p in rec.images[image_id].points2D:
        if not p.has_point3D():
            continue
        for e in rec.points3D[p.point3D_id].track.elements:
            if e.image_id == partner:
                mine.append(p.xy)
                theirs.append(rec.images[partner].points2D[e.point2D_idx].xy)
    if len(mine) < 8:
        return float("nan")
    mine, theirs = np.asarray(mine, np.float64), np.asarray(theirs, np.float64)
    ransac = pycolmap.TwoViewGeometryOptions().ransac
    ransac.max_error = PLANAR_RANSAC_PX
    ransac.random_seed = 0
    cams = rec.cameras[rec.images[image_id].camera_id], rec.cameras[rec.images[partner].camera_id]
    essential = pycolmap.estimate_essential_matrix(mine, theirs, cams[0], cams[1], ransac)
    homography = pycolmap.estimate_homography_matrix(mine, theirs, ransac)
    if essential is None or essential["num_inliers"] == 0:
        return float("nan")
    return (0 if homography is None else homography["num_inliers"]) / essential["num_inliers"]
