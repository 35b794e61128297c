"""Relocalisation of a frame the model placed far off: its neighbours, rendered where the model says
it is, matched to its own photo (issue 21).

Dense evidence (``sfm/refine/dense.py``) warps a neighbour into a frame's view through the model's
prediction and measures what is left: a few degrees. A frame the model got grossly wrong (tens of
degrees) is predicted a hundred pixels or more from where it is, beyond any flow's reach, and SIFT
across the wide baseline finds too little, so the frame would end with no evidence either way.

This is a second chance for such frames, run only for the frames the first adjustment left out:

1. each well-placed neighbour j is rendered into frame i's predicted view (forward warping of j's
   pixels with j's depth and camera, a z-buffer keeping the nearest; ``cv2`` has no forward warp);
   the perspective change of the wide baseline is undone, what is left between the rendering and
   frame i's photo is the error of frame i's pose: mostly a rotation, which SIFT is invariant to.
   Where that places nothing, the first rendering is onto a canvas wider than the photo (same focal
   length and centre): a view 25 deg off looks partly past the edge of the predicted one, and what
   it sees there is the content that places it;
2. SIFT (OpenCV) matches the rendering to frame i's photo (Lowe's ratio test); a match carries the
   3D point (neighbour's depth, in the model's world) rendered at its pixel;
3. pycolmap's absolute pose (LO-RANSAC and refinement, frame i's intrinsics held) places frame i
   on those 2D-3D matches.

The pose found is not evidence by itself: it only seeds dense evidence for the frame again (whose
forward-backward, correlation and essential-matrix checks decide), and bundle adjustment.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ffrecon.checks import check_number
from ffrecon.geometry.overlap import OverlapOptions, overlap_matrix
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.sfm.refine.dense import world_at_size
from ffrecon.types import PinholeCamera, Prediction

logger = logging.getLogger("ffrecon.sfm")


@dataclass(frozen=True, kw_only=True)
class RelocalizeOptions:
    enabled: bool = True
    # The placed frames nearest to the frame's predicted centre are rendered into its view. Not the ones
    # the predicted overlap ranks first: that comes from the frame's pose, the thing in doubt (25 deg off,
    # its true neighbours are predicted to share 4 % of its view).
    max_neighbours: int = 4
    fill_px: int = 7  # holes of the rendering narrower than this are filled (inpainting) before SIFT
    working_side_px: int = 640  # images rendered and matched at most this long side
    ratio: float = 0.8  # Lowe's ratio test of the SIFT matches
    ransac_fraction: float = 0.01  # absolute-pose RANSAC threshold, fraction of the image diagonal
    # Fewer 2D-3D inliers: no pose. The pose only seeds dense evidence and the adjustment, which decide (a
    # pose they do not keep leaves the frame contradicted). Measured on the wide scene, 24 seeds, each
    # frame 25 deg off in turn (tools/sweep_bad_frames.py): at 20, seeds 10 and 15 frame 7 (19 and 14
    # inliers on the photo's canvas, 9 and 7 deg from the truth) stayed unchecked at 25 deg; at 12 their
    # next round finds 28 and 60 and both end corrected (2.0 and 0.1 deg); no bad frame confirmed either way.
    min_inliers: int = 12
    # Frames rendered from: registered by the adjustment within this of their model rotation
    max_source_change_deg: float = 5.0
    rounds: int = 2  # renderings from the pose found, matched again
    # Where the photo's own canvas places nothing, the first rendering is onto this much larger a canvas
    # per side (same focal length; 1: never): 2 reaches half a field of view past each edge. Measured on
    # the wide scene, seed 5, frame 6 (25 deg off): 12 inliers on the photo's canvas (no pose), 24 at 2x
    # and 23 at 3x, then 37 from the pose found (2.1 deg). Not first: on seed 1 it placed a good frame
    # 11.5 deg off that the photo's canvas placed within 1.5 deg.
    first_canvas: float = 2.0
    min_depth_conf: float = 1.0

    def __post_init__(self) -> None:
        for name in ("max_neighbours", "working_side_px", "min_inliers", "rounds"):
            check_number(f"RelocalizeOptions.{name}", getattr(self, name), low=1, integer=True)
        check_number("RelocalizeOptions.fill_px", self.fill_px, low=1, integer=True)
        for name in ("ratio", "ransac_fraction"):
            check_number(f"RelocalizeOptions.{name}", getattr(self, name), low=0, high=1, low_open=True)
        check_number("RelocalizeOptions.min_depth_conf", self.min_depth_conf, low=0)
        check_number("RelocalizeOptions.first_canvas", self.first_canvas, low=1, high=4)
        check_number("RelocalizeOptions.max_source_change_deg", self.max_source_change_deg, low=0, low_open=True)


@dataclass(frozen=True)
class Relocalized:
    """One frame placed again: its pose in the model's world and the matches that placed it."""

    index: int
    cam_from_world: np.ndarray  # [3, 4] float64
    num_matches: int  # SIFT matches between the renderings and the photo
    num_inliers: int  # ... consistent with the pose
    change_deg: float  # rotation from the model's pose
    reach: dict[int, float]  # predicted overlap (larger direction) with each rendered neighbour, from the new pose

    def to_report(self, names: Sequence[str]) -> dict:
        return {
            "name": names[self.index],
            "num_matches": self.num_matches,
            "num_inliers": self.num_inliers,
            "change_deg": round(self.change_deg, 3),
        }


def with_poses(prediction: Prediction, found: Sequence[Relocalized]) -> Prediction:
    """The prediction with the relocalised frames' poses replaced."""
    cam_from_world = prediction.cam_from_world.copy()
    for r in found:
        cam_from_world[r.index] = r.cam_from_world
    return dataclasses.replace(prediction, cam_from_world=cam_from_world)


def reach_matrix(n: int, found: Sequence[Relocalized]) -> np.ndarray:
    """``[N, N]`` symmetric overlap of the relocalised frames with their neighbours (0 elsewhere), to
    choose the pairs of their dense evidence."""
    out = np.zeros((n, n))
    for r in found:
        for j, value in r.reach.items():
            out[r.index, j] = out[j, r.index] = value
    return out


def render_into(
    gray_j: np.ndarray,
    prediction: Prediction,
    j: int,
    cam_from_world_i: np.ndarray,
    camera_i: PinholeCamera,
    min_conf: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Frame j seen from frame i's pose: ``(image [H, W] uint8, world [H, W, 3] float64)`` at ``camera_i``'s
    size, 0 and NaN where nothing of j lands.

    Each pixel of j (its depth resized to ``gray_j``) is splatted onto the 2 x 2 pixels around where it
    lands (fewer holes where i is closer), the nearest surface winning.
    """
    world, known = world_at_size(prediction, j, (gray_j.shape[1], gray_j.shape[0]), min_conf)
    world = world.reshape(-1, 3)
    pc = world @ cam_from_world_i[:, :3].T + cam_from_world_i[:, 3]
    ok = known.ravel() & (pc[:, 2] > 1e-9) & np.isfinite(pc).all(axis=1)
    source, world, pc = np.flatnonzero(ok), world[ok], pc[ok]
    x = camera_i.fx * pc[:, 0] / pc[:, 2] + camera_i.cx - 0.5  # COLMAP's rule -> OpenCV's pixel indices
    y = camera_i.fy * pc[:, 1] / pc[:, 2] + camera_i.cy - 0.5
    hi, wi = camera_i.height, camera_i.width
    target, order = [], []
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        col, row = np.floor(x).astype(np.int64) + dx, np.floor(y).astype(np.int64) + dy
        inside = (col >= 0) & (col < wi) & (row >= 0) & (row < hi)
        target.append(np.where(inside, row * wi + col, -1))
        order.append(np.arange(len(x)))
    target, index = np.concatenate(target), np.concatenate(order)
    keep = target >= 0
    target, index = target[keep], index[keep]
    first = np.lexsort((pc[index, 2], target))  # by pixel, nearest first
    target, index = target[first], index[first]
    winner = np.ones(len(target), bool)
    winner[1:] = target[1:] != target[:-1]
    image = np.zeros(hi * wi, np.uint8)
    points = np.full((hi * wi, 3), np.nan)
    image[target[winner]] = gray_j.ravel()[source[index[winner]]]
    points[target[winner]] = world[index[winner]]
    return image.reshape(hi, wi), points.reshape(hi, wi, 3)


def fill_holes(image: np.ndarray, side: int) -> np.ndarray:
    """``image`` with the holes of a rendering (0) filled where a ``side`` x ``side`` closing of what was
    rendered covers them (the stripes a forward warp leaves where it magnifies); the rest stays 0."""
    rendered = (image > 0).astype(np.uint8)
    closed = cv2.morphologyEx(rendered, cv2.MORPH_CLOSE, np.ones((side, side), np.uint8))
    holes = (closed > 0) & (rendered == 0)
    return cv2.inpaint(image, holes.astype(np.uint8), 3, cv2.INPAINT_TELEA) if holes.any() else image


def _point_near(world: np.ndarray, xy: tuple[float, float], radius: int) -> np.ndarray | None:
    """The rendered world point at OpenCV pixel ``xy``, or the nearest one within ``radius`` pixels."""
    col, row = int(round(xy[0])), int(round(xy[1]))
    h, w = world.shape[:2]
    for dr, dc in _OFFSETS[radius]:
        r, c = row + dr, col + dc
        if 0 <= r < h and 0 <= c < w and np.isfinite(world[r, c, 0]):
            return world[r, c]
    return None


_OFFSETS = {
    r: sorted(((dr, dc) for dr in range(-r, r + 1) for dc in range(-r, r + 1)), key=lambda o: o[0] ** 2 + o[1] ** 2)
    for r in range(0, 8)
}


def relocalize(
    image_dir: Path,
    prediction: Prediction,
    frames: Sequence[int],
    placed: Sequence[int],
    options: RelocalizeOptions = RelocalizeOptions(),
) -> list[Relocalized]:
    """Place ``frames`` again from their ``placed`` neighbours (frames whose model pose the evidence kept).

    Args:
        image_dir: the photos; prediction: the model's cameras and depth (original-photo pixels).
        frames: indices of the frames to place; placed: indices of frames to render from.
    Returns:
        the frames placed, with at least ``options.min_inliers`` inliers.
    """
    if not options.enabled or not frames or not placed:
        return []
    sift = cv2.SIFT_create(nfeatures=4000)
    gray: dict[int, np.ndarray] = {}
    out: list[Relocalized] = []
    # On the photo's own canvas first, then, for the frames still not placed, on the wider one (which
    # also offers more false matches). Two sweeps each: a frame placed in the first renders for its
    # neighbours in the second (the end of a path whose next frame was left out too).
    canvases = (1.0, options.first_canvas) if options.first_canvas > 1 else (1.0,)
    for canvas in canvases:
        for _ in range(2):
            new = _sweep(image_dir, prediction, frames, placed, out, canvas, gray, sift, options)
            out += new
            if not new or len(out) == len(frames):
                break
        if len(out) == len(frames):
            break
    logger.info(
        "relocalised %d of %d frames left out (their neighbours rendered in their view, matched to their photos)",
        len(out),
        len(frames),
    )
    return out


def _sweep(image_dir, prediction, frames, placed, out, canvas: float, gray, sift, options) -> list[Relocalized]:
    """One pass over the ``frames`` not yet in ``out``, rendering from ``placed`` and ``out``: those it places."""
    current = with_poses(prediction, out)
    centers = camera_centers(current.cam_from_world)
    done = {r.index for r in out}
    sources = np.array(sorted(set(placed) | done), int)
    new: list[Relocalized] = []
    for i in [k for k in frames if k not in done]:
        distance = np.linalg.norm(centers[sources] - centers[i], axis=1)
        neighbours = [int(j) for j in sources[np.argsort(distance, kind="stable")] if j != i]
        neighbours = neighbours[: options.max_neighbours]
        for k in [i, *neighbours]:
            if k not in gray:
                gray[k] = _read_working(image_dir / prediction.names[k], options.working_side_px)
        found = _place(gray, current, i, neighbours, sift, canvas, options)
        if found is not None:
            new.append(dataclasses.replace(found, change_deg=_change_deg(found.cam_from_world, prediction, i)))
    return new


def _change_deg(cam_from_world: np.ndarray, prediction: Prediction, i: int) -> float:
    """Rotation (degrees) between a pose and the model's pose of frame i."""
    return float(rotation_angle_deg(cam_from_world[:, :3] @ prediction.cam_from_world[i][:, :3].T))


def _read_working(path: Path, side: int) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise FileNotFoundError(f"cannot read {path}")
    scale = min(1.0, side / max(image.shape))
    if scale < 1.0:
        size = (round(image.shape[1] * scale), round(image.shape[0] * scale))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return image


def _place(gray: dict, prediction: Prediction, i: int, neighbours: list[int], sift, canvas: float, options):
    """Frame i's pose from its neighbours' renderings (None when too few matches agree on one).

    The first round renders from the model's pose onto a canvas ``canvas`` times the photo's per side;
    later rounds render from the pose found, onto the photo's canvas, closer to the photo: more matches,
    and the pose from them (bounded: ``options.rounds``).
    """
    photo = gray[i]
    full = prediction.cameras[i]
    sx, sy = photo.shape[1] / full.width, photo.shape[0] / full.height
    scaled = full.scaled(sx, sy)
    camera = PinholeCamera(photo.shape[1], photo.shape[0], scaled.fx, scaled.fy, scaled.cx, scaled.cy)
    kp_i, desc_i = sift.detectAndCompute(photo, None)
    if desc_i is None or len(kp_i) < options.min_inliers:
        return None
    photo_features = (np.array([k.pt for k in kp_i], np.float64), desc_i)

    def pose_from(pose: np.ndarray, canvas: PinholeCamera) -> tuple[np.ndarray, int, int] | None:
        xy, xyz = _matches(gray, prediction, pose, canvas, neighbours, photo_features, sift, options)
        placed = _absolute_pose((xy + 0.5) / np.array([sx, sy]), xyz, full, options)  # full-resolution pixels
        return None if placed is None else (*placed, len(xy))

    placed = pose_from(prediction.cam_from_world[i], _widened(camera, canvas))
    found = None
    for round_ in range(options.rounds):
        if placed is None:
            break
        pose, inliers, matches = placed
        found = Relocalized(i, pose, matches, inliers, _change_deg(pose, prediction, i), {})
        placed = pose_from(pose, camera) if round_ + 1 < options.rounds else None
    if found is None:
        return None
    subset = with_poses(prediction, [found]).subset([i, *neighbours])
    overlap = overlap_matrix(subset, OverlapOptions(min_depth_conf=options.min_depth_conf))
    reach = np.maximum(overlap[0, 1:], overlap[1:, 0])
    return dataclasses.replace(found, reach={j: float(v) for j, v in zip(neighbours, reach)})


def _widened(camera: PinholeCamera, factor: float) -> PinholeCamera:
    """``camera``'s image grown ``factor`` times per side, equally on every edge, at the same focal length:
    the photo's view plus what lies past its edges."""
    width, height = round(camera.width * factor), round(camera.height * factor)
    pad_x, pad_y = (width - camera.width) / 2, (height - camera.height) / 2
    return PinholeCamera(width, height, camera.fx, camera.fy, camera.cx + pad_x, camera.cy + pad_y)


def _matches(gray, prediction, pose_i, canvas, neighbours, photo_features, sift, options):
    """SIFT matches of the photo with each neighbour rendered from ``pose_i`` onto ``canvas``:
    ``(xy [M, 2], world [M, 3])``, the photo's OpenCV pixel indices and the rendered world points."""
    xy_i, desc_i = photo_features
    points2d, points3d = [], []
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    for j in neighbours:
        image, world = render_into(gray[j], prediction, j, pose_i, canvas, options.min_depth_conf)
        image = fill_holes(image, options.fill_px)
        mask = cv2.erode((image > 0).astype(np.uint8) * 255, np.ones((7, 7), np.uint8))
        kp_r, desc_r = sift.detectAndCompute(image, mask)
        if desc_r is None or len(kp_r) < 2:
            continue
        for pair in matcher.knnMatch(desc_i, desc_r, k=2):
            if len(pair) < 2 or pair[0].distance >= options.ratio * pair[1].distance:
                continue
            point = _point_near(world, kp_r[pair[0].trainIdx].pt, options.fill_px // 2)
            if point is not None:
                points2d.append(xy_i[pair[0].queryIdx])
                points3d.append(point)
    return np.array(points2d).reshape(-1, 2), np.array(points3d).reshape(-1, 3)


def _absolute_pose(xy: np.ndarray, xyz: np.ndarray, camera: PinholeCamera, options: RelocalizeOptions):
    """pycolmap's LO-RANSAC absolute pose with the intrinsics held: ``(cam_from_world [3, 4], inliers)`` or None."""
    if len(xy) < options.min_inliers:
        return None
    colmap_camera = pycolmap.Camera(
        model="PINHOLE", width=camera.width, height=camera.height, params=[camera.fx, camera.fy, camera.cx, camera.cy]
    )
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = options.ransac_fraction * float(np.hypot(camera.width, camera.height))
    estimation.ransac.random_seed = 0
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.refine_focal_length = False
    refinement.refine_extra_params = False
    result = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, colmap_camera, estimation, refinement)
    if result is None or int(result["num_inliers"]) < options.min_inliers:
        return None
    return np.asarray(result["cam_from_world"].matrix(), np.float64), int(result["num_inliers"])
