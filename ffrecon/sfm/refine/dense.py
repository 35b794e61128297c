"""Dense evidence guided by the model: correspondences where SIFT finds too few (issue 21).

On wide baselines and low texture SIFT shares a handful of matches between views that overlap well:
descriptors change with the viewpoint and the ratio test drops the rest. The model already says
where each pixel of frame i lands in frame j (its depth of i, its cameras of i and j). That
prediction is wrong by the model's pose and depth errors, a few degrees, so it is refined on the
images themselves:

1. frame j is warped into frame i's view through the predicted map (``cv2.remap``), which undoes
   the perspective change between the views; what is left is a small, smooth misalignment;
2. DIS optical flow (OpenCV, medium preset) measures the misalignment left between frame i and the
   warped image, in both directions; at frame i's Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) a
   correspondence is kept when following the flow there and back returns to within
   ``max_fb_error_px`` of its start (the forward-backward check), it moved at most ``max_shift`` of
   the image diagonal and its windows correlate (normalised cross-correlation, ``min_ncc``);
   where the model's cameras are a few degrees off, the map is first moved by the offset in frame j
   that the photos agree on (``sfm/refine/prealign.py``) and the pass that keeps more corners is used;
3. the kept positions are mapped back through the predicted map into frame j's pixels, and COLMAP
   verifies each pair's correspondences as it verifies SIFT matches (an essential matrix by RANSAC
   with the database cameras): only its inliers are written.

DIS was chosen over pyramidal Lucas-Kanade by measurement against the synthetic truth (frames 3 -> 4
of the wide-baseline scene, ``tests/sfm/test_sparse_views.py``): both kept correspondences within
0.2-0.3 px, LK half as many (153 against 287 of 613 corners). A flow measured at every pixel is
only read at the corners, where it means something; the walls' flat pixels are never used.

The correspondences enter COLMAP's database as extra keypoints (after SIFT's) and inlier matches of
the pair, so that the refinement's triangulation and bundle adjustment use them beside SIFT, track
merging included. Where a family has descriptors (MASt3R) they are not matched here yet.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ffrecon.checks import check_number
from ffrecon.geometry.projection import pixel_centers
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.sfm.refine.dense_db import Keypoints, add_matches
from ffrecon.sfm.refine.prealign import offset_in_other_frame, shifted_map
from ffrecon.types import Prediction

logger = logging.getLogger("ffrecon.sfm")


@dataclass(frozen=True, kw_only=True)
class DenseOptions:
    enabled: bool = True
    # Where it runs: frames whose verified SIFT matches (summed over their pairs) are below this
    # get dense evidence on each of their overlapping pairs; SIFT-friendly captures pay nothing.
    min_sift_matches: int = 300
    min_pair_overlap: float = 0.1  # predicted overlap (smaller of both directions) of a pair worth tracking
    max_pairs_per_image: int = 4  # the most overlapping ones
    max_corners: int = 1500  # corners of each frame tracked into its neighbours
    corner_quality: float = 0.005  # goodFeaturesToTrack's qualityLevel (relative to the strongest corner)
    corner_spacing_px: int = 5  # goodFeaturesToTrack's minDistance
    window_px: int = 11  # side of the window whose correlation is checked
    max_fb_error_px: float = 1.0  # forward-backward: distance from the start after following the flow there and back
    max_shift: float = 0.15  # largest refinement of a prediction, fraction of the image diagonal
    min_ncc: float = 0.8  # normalised cross-correlation of the window at the start and at the end
    min_depth_conf: float = 1.0
    ransac_px: float = 2.0  # COLMAP's verification of the correspondences (its max_error)
    min_inliers: int = 15  # fewer verified correspondences: the pair gets none
    # The prediction's offset in the other frame, by consensus of patch searches (sfm/refine/prealign.py),
    # tried before the flow where the model's cameras are a few degrees off; the pass tracking more is kept.
    prealign: bool = True
    prealign_samples: int = 96  # corners searched for the consensus
    prealign_window_px: int = 15  # side of the searched patch
    prealign_min_votes: int = 4  # agreeing offsets that make a consensus
    prealign_tolerance: float = 0.0075  # offsets within this fraction of the image diagonal (at least 2 px) agree
    # A pair whose verified rotation lies further than this (deg) from the model's is not written; None: every
    # verified pair is. Set on look-alike surfaces (sfm/refine/matching.py, _on_lookalikes) to the guided pairs'
    # GuidanceOptions.max_pair_gap_deg: tracks that started from the model's prediction lock on a period of the
    # pattern where it is more than half a period off, and verify as well as the truth (held-out room 351,
    # repeated tile: 108 tracks between frames 0 and 1, all 11 px off the true epipolar lines, a rotation 26 deg
    # from the model's that left out a frame the model had within 2.7 deg).
    max_model_gap_deg: float | None = None

    def __post_init__(self) -> None:
        integers = ("min_sift_matches", "max_pairs_per_image", "max_corners", "corner_spacing_px", "min_inliers")
        for name in integers + ("prealign_samples", "prealign_min_votes"):
            check_number(f"DenseOptions.{name}", getattr(self, name), low=0, integer=True)
        check_number("DenseOptions.window_px", self.window_px, low=3, integer=True)
        check_number("DenseOptions.prealign_window_px", self.prealign_window_px, low=3, integer=True)
        for name in ("min_pair_overlap", "min_ncc", "corner_quality"):
            check_number(f"DenseOptions.{name}", getattr(self, name), low=0, high=1)
        for name in ("max_fb_error_px", "max_shift", "ransac_px", "prealign_tolerance"):
            check_number(f"DenseOptions.{name}", getattr(self, name), low=0, low_open=True)
        check_number("DenseOptions.min_depth_conf", self.min_depth_conf, low=0)
        check_number("DenseOptions.max_model_gap_deg", self.max_model_gap_deg, low=0, high=180, allow_none=True)


@dataclass(frozen=True)
class DenseStats:
    """What dense evidence added: the frames it ran for, the pairs tracked and the correspondences kept."""

    frames: tuple[str, ...]  # frames SIFT left short
    num_pairs: int  # pairs tracked
    num_tracked: int  # correspondences that passed the forward-backward and correlation checks
    num_verified: int  # ... and COLMAP's verification: written to the database
    per_frame: dict[str, int]  # verified correspondences per frame
    seconds: float
    # Per pair tracked: (frame, frame, corners predicted inside the other frame in both directions, verified).
    pairs: tuple[tuple[str, str, int, int], ...] = ()
    # Pairs whose tracks verified turned beyond DenseOptions.max_model_gap_deg from the model: not written.
    turned: tuple[tuple[str, str], ...] = ()

    @property
    def per_frame_predicted(self) -> dict[str, int]:
        """Per frame SIFT left short: the corners the model's cameras and depth put inside the other frame of the
        pairs it was tracked in (both directions): what the tracking tried."""
        out = dict.fromkeys(self.frames, 0)
        for a, b, predicted, _ in self.pairs:
            for name in {a, b} & out.keys():
                out[name] += predicted
        return out

    def merged(self, other: DenseStats) -> DenseStats:
        """Two passes as one (the second for frames the first bundle adjustment still left out)."""
        per_frame = dict(self.per_frame)
        for name, count in other.per_frame.items():
            per_frame[name] = per_frame.get(name, 0) + count
        frames = self.frames + tuple(f for f in other.frames if f not in self.frames)
        return DenseStats(
            frames,
            self.num_pairs + other.num_pairs,
            self.num_tracked + other.num_tracked,
            self.num_verified + other.num_verified,
            per_frame,
            self.seconds + other.seconds,
            self.pairs + other.pairs,
            self.turned + other.turned,
        )

    def to_report(self) -> dict:
        return {
            "frames": list(self.frames),
            "num_pairs": self.num_pairs,
            "num_tracked": self.num_tracked,
            "num_verified": self.num_verified,
            "per_frame": dict(self.per_frame),
            "per_frame_predicted": dict(self.per_frame_predicted),
            "pairs": [list(p) for p in self.pairs],
            "turned_pairs": [list(p) for p in self.turned],
            "seconds": round(self.seconds, 3),
        }


def short_frames(names: Sequence[str], sift_matches: np.ndarray, options: DenseOptions) -> list[int]:
    """Indices of the frames whose verified SIFT matches (``[N]``, summed over pairs) are below the bar.

    >>> short_frames(["a", "b", "c"], np.array([1200, 40, 0]), DenseOptions())
    [1, 2]
    """
    return [k for k in range(len(names)) if sift_matches[k] < options.min_sift_matches]


def dense_pairs(score: np.ndarray, frames: Sequence[int], options: DenseOptions) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, ``i < j``, to track: each short frame's best overlapping neighbours.

    ``score``: ``[N, N]`` symmetric predicted overlap (:meth:`OverlapGraph.score`).

    >>> s = np.array([[0, 0.5, 0.05], [0.5, 0, 0.3], [0.05, 0.3, 0]])
    >>> dense_pairs(s, [2], DenseOptions())
    [(1, 2)]
    """
    out = set()
    for i in frames:
        order = [j for j in np.argsort(-score[i], kind="stable") if j != i and score[i, j] >= options.min_pair_overlap]
        out.update((min(i, int(j)), max(i, int(j))) for j in order[: options.max_pairs_per_image])
    return sorted(out)


def world_at_size(
    prediction: Prediction, i: int, size_wh: tuple[int, int], min_conf: float
) -> tuple[np.ndarray, np.ndarray]:
    """Frame i's depth (resized to ``size_wh``) as world points: ``(world [H, W, 3] float64, ok [H, W] bool)``,
    ``ok`` where the depth is known with confidence >= ``min_conf``."""
    w, h = size_wh
    depth = cv2.resize(prediction.depth[i], (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float64)
    conf = cv2.resize(prediction.depth_conf[i], (w, h), interpolation=cv2.INTER_NEAREST)
    full = prediction.cameras[i]
    cam = full.scaled(w / full.width, h / full.height)
    uv = pixel_centers(h, w)
    rays = np.stack([(uv[..., 0] - cam.cx) / cam.fx, (uv[..., 1] - cam.cy) / cam.fy, np.ones((h, w))], -1)
    pose = prediction.cam_from_world[i]
    return (rays * depth[..., None] - pose[:, 3]) @ pose[:, :3], (depth > 0) & (conf >= min_conf)


def predicted_map(prediction: Prediction, i: int, j: int, size_wh: tuple[int, int], min_conf: float) -> np.ndarray:
    """``[H, W, 2]`` float32: where each pixel of frame i (``size_wh``) lands in frame j, COLMAP's pixel rule.

    Frame i's depth is resized to the image; pixels without confident depth, behind camera j or
    outside it are ``-1``.
    """
    world, ok = world_at_size(prediction, i, size_wh, min_conf)
    cam_j, pose_j = prediction.cameras[j], prediction.cam_from_world[j]
    pc = world @ pose_j[:, :3].T + pose_j[:, 3]
    z = pc[..., 2]
    ok &= z > 1e-9
    safe = np.where(ok, z, 1.0)
    xy = np.stack([cam_j.fx * pc[..., 0] / safe + cam_j.cx, cam_j.fy * pc[..., 1] / safe + cam_j.cy], -1)
    ok &= (xy[..., 0] >= 0) & (xy[..., 0] <= cam_j.width) & (xy[..., 1] >= 0) & (xy[..., 1] <= cam_j.height)
    xy[~ok] = -1.0
    return xy.astype(np.float32)


def _ncc(a: np.ndarray, b: np.ndarray, pa: np.ndarray, pb: np.ndarray, side: int) -> np.ndarray:
    """Normalised cross-correlation of ``side`` x ``side`` windows of ``a`` at ``pa`` and ``b`` at ``pb``
    (``[M, 2]``, OpenCV pixel indices, sub-pixel); -1 for a flat window."""
    out = np.full(len(pa), -1.0)
    for k, (p, q) in enumerate(zip(pa, pb)):
        wa = cv2.getRectSubPix(a, (side, side), (float(p[0]), float(p[1]))).astype(np.float64).ravel()
        wb = cv2.getRectSubPix(b, (side, side), (float(q[0]), float(q[1]))).astype(np.float64).ravel()
        wa, wb = wa - wa.mean(), wb - wb.mean()
        den = np.sqrt((wa @ wa) * (wb @ wb))
        out[k] = wa @ wb / den if den > 1e-9 else -1.0
    return out


def _sample(field: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples ``[M, C]`` of ``field`` ``[H, W, C]`` float32 at ``xy`` ``[M, 2]`` (OpenCV pixel indices)."""
    if len(xy) == 0:
        return np.zeros((0, field.shape[2] if field.ndim == 3 else 1))
    xy = np.ascontiguousarray(xy, np.float32).reshape(-1, 1, 2)
    out = cv2.remap(field, xy[..., 0], xy[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(len(xy), -1).astype(np.float64)


def track_pair(
    gray_i: np.ndarray, gray_j: np.ndarray, corners_i: np.ndarray, xy_map: np.ndarray, options: DenseOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Frame i's corners found in frame j, refined on the images.

    Args:
        gray_i, gray_j: ``[H, W]`` uint8 images of frames i and j.
        corners_i: ``[M, 2]`` float32 corners of i, OpenCV pixel indices (top-left pixel's centre at 0, 0).
        xy_map: :func:`predicted_map` of i in j (COLMAP's rule).
    Returns:
        ``(corner [K] int, xy_j [K, 2] float64)``: the corners that pass every check (indices into
        ``corners_i``) and their positions in frame j, COLMAP's pixel rule.

    With ``options.prealign`` a second pass tracks on the map moved by the offset the photos agree on
    (:mod:`ffrecon.sfm.refine.prealign`; searched within ``max_shift``), and the pass keeping more
    corners is returned.
    """
    index, xy_j, warped = _track(gray_i, gray_j, corners_i, xy_map, options)
    if not options.prealign or warped is None:
        return index, xy_j
    h, w = gray_i.shape
    diagonal = float(np.hypot(w, h))
    pixel = np.rint(corners_i).astype(int)
    inside = corners_i[xy_map[pixel[:, 1].clip(0, h - 1), pixel[:, 0].clip(0, w - 1), 0] >= 0]
    offset = offset_in_other_frame(
        gray_i, warped, xy_map, inside,
        window_px=options.prealign_window_px, radius_px=int(options.max_shift * diagonal), min_ncc=options.min_ncc,
        samples=options.prealign_samples, tolerance_px=max(2.0, options.prealign_tolerance * diagonal),
        min_votes=options.prealign_min_votes,
    )  # fmt: skip
    if offset is None or float(np.linalg.norm(offset)) <= 1.0:
        return index, xy_j
    moved = _track(gray_i, gray_j, corners_i, shifted_map(xy_map, offset, gray_j.shape[::-1]), options)
    return (moved[0], moved[1]) if len(moved[0]) > len(index) else (index, xy_j)


def _track(gray_i, gray_j, corners_i, xy_map, options: DenseOptions):
    """One pass of :func:`track_pair` on a given map; also returns the warped image (None when nothing to track)."""
    h, w = gray_i.shape
    valid = xy_map[..., 0] >= 0
    if len(corners_i) == 0 or valid.sum() < 16:
        return np.zeros(0, int), np.zeros((0, 2)), None
    map_x, map_y = xy_map[..., 0] - 0.5, xy_map[..., 1] - 0.5  # COLMAP's rule -> OpenCV's indices (boundary)
    warped = cv2.remap(gray_j, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    warped[~valid] = 0
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    ahead, back = flow.calc(gray_i, warped, None), flow.calc(warped, gray_i, None)
    rows, cols = corners_i[:, 1].round().astype(int).clip(0, h - 1), corners_i[:, 0].round().astype(int).clip(0, w - 1)
    index = np.flatnonzero(valid[rows, cols])
    start = corners_i[index].astype(np.float64)
    end = start + _sample(ahead, start)
    returned = end + _sample(back, end)
    fb = np.linalg.norm(returned - start, axis=1)
    shift = np.linalg.norm(end - start, axis=1)
    keep = (fb <= options.max_fb_error_px) & (shift <= options.max_shift * float(np.hypot(w, h)))
    keep &= (end[:, 0] >= 0) & (end[:, 0] <= w - 1) & (end[:, 1] >= 0) & (end[:, 1] <= h - 1)
    index, start, end = index[keep], start[keep], end[keep]
    # Where the track ends in the warped image, frame j's pixel is the predicted map there (bilinear;
    # every map pixel of the 2x2 neighbourhood must be valid, else it straddles a hole or an edge).
    r0, c0 = np.floor(end[:, 1]).astype(int), np.floor(end[:, 0]).astype(int)
    r1, c1 = np.minimum(r0 + 1, h - 1), np.minimum(c0 + 1, w - 1)
    inside = valid[r0, c0] & valid[r0, c1] & valid[r1, c0] & valid[r1, c1]
    keep = inside & (_ncc(gray_i, warped, start, end, options.window_px) >= options.min_ncc)
    return index[keep], _sample(xy_map, end[keep]), warped


def frame_corners(gray: np.ndarray, options: DenseOptions) -> np.ndarray:
    """``[M, 2]`` float32 Shi-Tomasi corners of a frame, OpenCV pixel indices (none on a flat image)."""
    corners = cv2.goodFeaturesToTrack(
        gray, options.max_corners, options.corner_quality, options.corner_spacing_px, blockSize=5
    )
    return np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2).astype(np.float32)


def _read_gray(image_dir: Path, name: str) -> np.ndarray:
    gray = cv2.imread(str(Path(image_dir) / name), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise FileNotFoundError(f"cannot read {Path(image_dir) / name}")
    return gray


def add_dense_evidence(
    db_path: Path,
    image_dir: Path,
    prediction: Prediction,
    frames: Sequence[int],
    score: np.ndarray,
    options: DenseOptions = DenseOptions(),
) -> DenseStats:
    """Track, verify and write model-guided correspondences for the short ``frames`` (database updated).

    Args:
        db_path: the refinement's COLMAP database (SIFT keypoints and verified matches in it).
        image_dir: the photos; prediction: the model's cameras and depth (original-photo pixels).
        frames: indices of the frames SIFT left short (:func:`short_frames`).
        score: ``[N, N]`` predicted overlap of each pair.
    """
    start_s = time.perf_counter()
    names = list(prediction.names)
    pairs = dense_pairs(score, frames, options)
    views = _Views(Path(image_dir), names, options)
    counts = []  # per pair: (predicted, tracked, verified)
    db = pycolmap.Database.open(str(db_path))
    try:
        images = {im.name: im for im in db.read_all_images()}
        cameras = {name: db.read_camera(im.camera_id) for name, im in images.items()}
        keypoints = Keypoints(db, views, {images[n].image_id: k for k, n in enumerate(names)})
        for i, j in pairs:
            ids = (images[names[i]].image_id, images[names[j]].image_id)
            found = [_found(a, b, views, prediction, options) for a, b in ((i, j), (j, i))]
            cams = (cameras[names[i]], cameras[names[j]])
            counts.append(
                _write_pair(db, keypoints, ids, (i, j), found, views, cams, _implied(prediction, i, j), options)
            )
        keypoints.write()
    finally:
        db.close()
    seconds = time.perf_counter() - start_s
    per_frame = dict.fromkeys((names[k] for k in frames), 0)
    for (i, j), (_, _, kept, _) in zip(pairs, counts):
        for name in {names[i], names[j]} & per_frame.keys():
            per_frame[name] += kept
    tracked, verified = sum(c[1] for c in counts), sum(c[2] for c in counts)
    pair_counts = tuple((names[i], names[j], c[0], c[2]) for (i, j), c in zip(pairs, counts))
    turned = tuple((names[i], names[j]) for (i, j), c in zip(pairs, counts) if c[3])
    stats = DenseStats(
        tuple(names[k] for k in frames), len(pairs), tracked, verified, per_frame, seconds, pair_counts, turned
    )
    logger.info(
        "dense evidence for %d frames SIFT left short: %d pairs tracked, %d of %d correspondences verified (%.1f s)",
        len(frames),
        len(pairs),
        verified,
        tracked,
        seconds,
    )
    return stats


def _implied(prediction: Prediction, i: int, j: int) -> np.ndarray:
    """``[3, 3]`` the model's relative rotation ``cam_j_from_cam_i``."""
    rotations = prediction.cam_from_world[:, :, :3]
    return rotations[j] @ rotations[i].T


def _write_pair(
    db, keypoints, ids, pair, found, views, cameras, implied, options: DenseOptions
) -> tuple[int, int, int, bool]:
    """Verify one pair's tracked correspondences (``found``: :func:`_found` both ways) and write the inliers;
    returns (corners predicted inside the other frame, correspondences tracked, verified, turned). ``implied``: the
    model's ``cam_j_from_cam_i`` rotation, which the verified one must lie near (``options.max_model_gap_deg``);
    a pair turned further is not written and counts no predicted corner either: its tracks held, a period of
    the pattern off or the model's camera as far off, which the photos tell apart (``turned``:
    :func:`ffrecon.sfm.verify.unmatched._photometric`)."""
    (i, j), (id_i, id_j) = pair, ids
    predicted = found[0][2] + found[1][2]
    xy_i = np.concatenate([views(i)[1][found[0][0]] + 0.5, found[1][1]])  # OpenCV's indices -> COLMAP's rule
    xy_j = np.concatenate([found[0][1], views(j)[1][found[1][0]] + 0.5])
    inliers = _verify(cameras[0], xy_i, cameras[1], xy_j, implied, options)
    if inliers is None:
        logger.info(
            "dense evidence: pair %s-%s turned from the model's cameras (a pattern's period off?)", *views.of(i, j)
        )
        return 0, len(xy_i), 0, True
    if len(inliers) < options.min_inliers:
        return predicted, len(xy_i), 0, False
    # A corner is one keypoint of its frame in every pair, so that tracks run through it; a
    # position it was found at in another frame is a keypoint of that pair only.
    ahead, back = inliers[inliers < len(found[0][0])], inliers[inliers >= len(found[0][0])] - len(found[0][0])
    kp_i = [keypoints.corners(id_i, found[0][0][ahead]), keypoints.add(id_i, found[1][1][back])]
    kp_j = [keypoints.add(id_j, found[0][1][ahead]), keypoints.corners(id_j, found[1][0][back])]
    add_matches(db, id_i, id_j, np.stack([np.concatenate(kp_i), np.concatenate(kp_j)], axis=1))
    return predicted, len(xy_i), len(inliers), False


class _Views:
    """Grey images and their corners, read once each."""

    def __init__(self, image_dir: Path, names: Sequence[str], options: DenseOptions) -> None:
        self.image_dir, self.names, self.options = image_dir, names, options
        self.gray: dict[int, np.ndarray] = {}
        self.corners: dict[int, np.ndarray] = {}

    def of(self, *frames: int) -> tuple[str, ...]:
        return tuple(self.names[k] for k in frames)

    def __call__(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        if k not in self.gray:
            gray = cv2.imread(str(self.image_dir / self.names[k]), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise FileNotFoundError(f"cannot read {self.image_dir / self.names[k]}")
            self.gray[k], self.corners[k] = gray, frame_corners(gray, self.options)
        return self.gray[k], self.corners[k]


def _found(a: int, b: int, views: _Views, prediction: Prediction, options: DenseOptions):
    """:func:`track_pair` of frame a's corners into frame b, and how many of them the prediction put in b."""
    (gray_a, corners_a), (gray_b, _) = views(a), views(b)
    xy_map = predicted_map(prediction, a, b, (gray_a.shape[1], gray_a.shape[0]), options.min_depth_conf)
    h, w = gray_a.shape
    rows = corners_a[:, 1].round().astype(int).clip(0, h - 1)
    cols = corners_a[:, 0].round().astype(int).clip(0, w - 1)
    return (*track_pair(gray_a, gray_b, corners_a, xy_map, options), int((xy_map[rows, cols, 0] >= 0).sum()))


def _verify(camera_i, xy_i: np.ndarray, camera_j, xy_j: np.ndarray, implied: np.ndarray, options: DenseOptions):
    """Indices of the correspondences COLMAP's essential-matrix RANSAC keeps (none below ``min_inliers``); None
    when the rotation it recovers lies more than ``options.max_model_gap_deg`` from ``implied``."""
    if len(xy_i) < max(options.min_inliers, 5):
        return np.zeros(0, int)
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = options.ransac_px
    ransac.random_seed = 0
    essential = pycolmap.estimate_essential_matrix(xy_i, xy_j, camera_i, camera_j, ransac)
    if essential is None:
        return np.zeros(0, int)
    inliers = np.flatnonzero(np.asarray(essential["inlier_mask"], bool))
    if options.max_model_gap_deg is not None and len(inliers) >= options.min_inliers:
        measured = np.asarray(essential["cam2_from_cam1"].rotation.matrix(), np.float64)
        if rotation_angle_deg(measured @ implied.T) > options.max_model_gap_deg:
            return None
    return inliers
