"""Global alignment, step 1 (see :mod:`ffrecon.models.global_alignment`): the pairs as a graph over the views,
and a first pose, focal and depth map per view from a walk of its maximum spanning tree.

The pair graph's edges are weighted by the mean confidences of their best pair; from view 0, every new view's
points are brought into the world with a confidence-weighted Umeyama fit on the view already placed. Poses come
from fitting each view's own-frame points to its world points, focals from pixel rays vs points. A view that is
never first in a pair is placed by PnP. Plain arrays, no ONNX, deterministic.
"""

from __future__ import annotations

import enum
import logging
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ffrecon.checks import check_number
from ffrecon.errors import FFReconError, ModelError
from ffrecon.geometry.alignment import Sim3, umeyama
from ffrecon.geometry.projection import pixel_centers

log = logging.getLogger("ffrecon.models.global_alignment")

MAX_FIT_POINTS = 20000  # points per Umeyama / focal fit (evenly strided), plenty for 7 unknowns
FOCAL_RANGE = (0.1, 20.0)  # plausible focal lengths, in units of the long image side (157 to 3 degrees)


@dataclass(frozen=True)
class PairPrediction:
    """A pairwise model's output for one ordered pair, in network pixels (``H x W``).

    ``pts_i_in_i``: ``[H, W, 3]`` float32, view i's points in view i's camera frame (pair scale);
    ``conf_i``: ``[H, W]`` float32 >= 1; ``pts_j_in_i``: ``[H, W, 3]`` float32, view j's points,
    also in view i's camera frame; ``conf_j``: ``[H, W]`` float32 >= 1.
    """

    i: int
    j: int
    pts_i_in_i: np.ndarray
    conf_i: np.ndarray
    pts_j_in_i: np.ndarray
    conf_j: np.ndarray

    def points_of(self, view: int) -> tuple[np.ndarray, np.ndarray]:
        """``(points [H, W, 3] in view i's frame, conf [H, W])`` of ``view`` (i or j)."""
        return (self.pts_i_in_i, self.conf_i) if view == self.i else (self.pts_j_in_i, self.conf_j)


class ConfidenceWeight(enum.Enum):
    LOG = "log"  # w = log(conf): DUSt3R's default; pixels with conf 1 carry (almost) no weight
    LINEAR = "linear"  # w = conf


@dataclass(frozen=True, kw_only=True)
class AlignmentOptions:
    iterations: int = 300  # Adam steps (0: initialisation only)
    lr: float = 0.01  # Adam learning rate; lengths are normalised so the median depth is 1
    lr_min: float = 1e-5  # end of the cosine schedule
    confidence_weight: ConfidenceWeight = ConfidenceWeight.LOG
    depth_downsample: int = 1  # depth unknowns on a grid this many times coarser (bilinear up)
    optimize_focal: bool = True
    keep_best: bool = True  # return the lowest-loss iterate (False: the last one)

    def __post_init__(self) -> None:
        check_number("AlignmentOptions.iterations", self.iterations, low=0, integer=True)
        check_number("AlignmentOptions.lr", self.lr, low=0, low_open=True)
        check_number("AlignmentOptions.lr_min", self.lr_min, low=0)
        check_number("AlignmentOptions.depth_downsample", self.depth_downsample, low=1, integer=True)


def estimate_focal(
    points_cam: np.ndarray, weights: np.ndarray, size_hw: tuple[int, int], *, iterations: int = 10
) -> float:
    """Focal length (pixels) that best maps camera-frame points to their pixels.

    Minimises ``sum w * ||(x, y) - f * (X/Z, Y/Z)||`` (robust L1 via Weiszfeld reweighting, starting
    from the weighted least-squares solution), with ``(x, y)`` pixel centres relative to the image centre.

    Args:
        points_cam: ``[H, W, 3]`` points in the camera frame (any scale); weights: ``[H, W]`` >= 0.
    """
    xy = (pixel_centers(*size_hw) - np.array([size_hw[1] / 2, size_hw[0] / 2])).reshape(-1, 2)
    pts = points_cam.reshape(-1, 3).astype(np.float64)
    w = weights.reshape(-1).astype(np.float64)
    z = pts[:, 2]
    valid = (z > 1e-6 * max(np.abs(z).max(), 1e-30)) & (w > 0)
    if valid.sum() < 2:
        raise ModelError(
            "cannot estimate a focal length: no predicted point lies in front of the camera",
            "check the pairwise model's outputs (point maps in the camera frame, z > 0)",
        )
    step = max(1, int(valid.sum()) // MAX_FIT_POINTS)
    xy, ab, w = xy[valid][::step], (pts[valid, :2] / z[valid, None])[::step], w[valid][::step]
    focal = float((w * (xy * ab).sum(1)).sum() / max((w * (ab**2).sum(1)).sum(), 1e-30))
    for _ in range(iterations):
        resid = np.linalg.norm(xy - focal * ab, axis=1)
        wr = w / np.maximum(resid, 1e-8)
        focal = float((wr * (xy * ab).sum(1)).sum() / max((wr * (ab**2).sum(1)).sum(), 1e-30))
    lo, hi = FOCAL_RANGE[0] * max(size_hw), FOCAL_RANGE[1] * max(size_hw)
    if not lo <= focal <= hi:  # points that do not look like a pinhole view (e.g. an untrained model)
        log.warning("focal estimate %.4g px is outside [%.4g, %.4g]: clamped", focal, lo, hi)
        focal = float(np.clip(np.nan_to_num(focal, nan=lo), lo, hi))
    return focal


def _camera_from_foreign_points(points: np.ndarray, weights: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """``[3, 4]`` cam_from_frame for a view known only through points in another view's frame.

    PnP (OpenCV SQPnP) with the focal length that minimises the reprojection error: a coarse
    geometric grid, then a golden-section search around its best value. Used for views that are
    never the first of any pair (non-symmetric pair graphs).
    """
    h, w = size_hw
    uv = pixel_centers(h, w).reshape(-1, 2)
    pts = points.reshape(-1, 3).astype(np.float64)
    keep = np.flatnonzero(weights.reshape(-1) > 0)
    keep = keep[:: max(1, len(keep) // 2000)]
    uv, pts = uv[keep], pts[keep]

    def solve(log_focal: float) -> tuple[float, np.ndarray]:
        focal = math.exp(log_focal)
        K = np.array([[focal, 0, w / 2], [0, focal, h / 2], [0, 0, 1]])
        # uv and K are both in COLMAP pixel coordinates; PnP only needs them to agree.
        ok, rvec, tvec = cv2.solvePnP(pts, uv, K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return math.inf, np.eye(3, 4)
        proj, _ = cv2.projectPoints(pts, rvec, tvec, K, None)
        err = float(np.mean(np.sum((proj[:, 0] - uv) ** 2, axis=1)))
        return err, np.concatenate([cv2.Rodrigues(rvec)[0], tvec], axis=1)

    grid = np.log(np.geomspace(0.2 * max(h, w), 5.0 * max(h, w), 25))
    best = int(np.argmin([solve(g)[0] for g in grid]))
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    ratio = (math.sqrt(5) - 1) / 2
    for _ in range(40):  # golden-section search on log focal
        a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
        if solve(a)[0] < solve(b)[0]:
            hi = b
        else:
            lo = a
    return solve((lo + hi) / 2)[1]


def _fit_sim3(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> Sim3:
    """Weighted Umeyama ``dst_from_src`` on up to MAX_FIT_POINTS evenly strided points."""
    src, dst, weights = src.reshape(-1, 3), dst.reshape(-1, 3), weights.reshape(-1)
    step = max(1, len(src) // MAX_FIT_POINTS)
    return umeyama(
        src[::step].astype(np.float64), dst[::step].astype(np.float64), weights[::step].astype(np.float64) + 1e-12
    )


def _weights(conf: np.ndarray, kind: ConfidenceWeight) -> np.ndarray:
    conf = np.maximum(conf, 1.0)
    w = np.log(conf) if kind is ConfidenceWeight.LOG else conf
    return (w + 1e-6).astype(np.float32)  # the floor keeps all-ones confidence usable (uniform weights)


def maximum_spanning_tree(num_views: int, pairs: Sequence[PairPrediction]) -> list[int]:
    """Indices into ``pairs`` of a maximum spanning tree over the views (Kruskal).

    An edge's weight is ``mean(conf_i) * mean(conf_j)`` of its best pair (both directions compete).
    Raises :class:`FFReconError` if the pairs do not connect all views.
    """
    scores = [float(p.conf_i.mean() * p.conf_j.mean()) for p in pairs]
    parent = list(range(num_views))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    tree = []
    for e in sorted(range(len(pairs)), key=lambda k: -scores[k]):
        ra, rb = root(pairs[e].i), root(pairs[e].j)
        if ra != rb:
            parent[ra] = rb
            tree.append(e)
    if len(tree) != num_views - 1:
        raise FFReconError(
            f"the {len(pairs)} pairs do not connect all {num_views} views",
            "use a connected pair graph (complete, sliding window or one-reference)",
        )
    return tree


@dataclass(frozen=True)
class _Init:
    world_from_cam: np.ndarray  # [N, 3, 4]
    focal: np.ndarray  # [N]
    depth: np.ndarray  # [N, H, W]
    world_from_pair: list[Sim3]  # [E]


def initialise(
    pairs: Sequence[PairPrediction], num_views: int, size_hw: tuple[int, int], kind: ConfidenceWeight
) -> _Init:
    """Spanning-tree initialisation (see the module docstring); world = view 0's camera frame."""
    own, own_w = _own_frame_points(pairs, num_views, size_hw, kind)
    world_pts, world_w, sims = _walk_spanning_tree(pairs, num_views, own, own_w, kind)
    h, w = size_hw
    world_from_cam = np.zeros((num_views, 3, 4))
    depth = np.zeros((num_views, h, w))
    focal = np.zeros(num_views)
    for v in range(num_views):
        sim = Sim3.identity() if v == 0 else _fit_sim3(own[v], world_pts[v], own_w[v])
        world_from_cam[v] = np.concatenate([sim.rotation, sim.translation[:, None]], axis=1)
        depth[v] = sim.scale * own[v][..., 2]
        focal[v] = estimate_focal(own[v], own_w[v], size_hw)
    for e, p in enumerate(pairs):  # pairs off the tree: fit both views at once
        if e not in sims:
            src = np.concatenate([p.pts_i_in_i.reshape(-1, 3), p.pts_j_in_i.reshape(-1, 3)])
            dst = np.concatenate([world_pts[p.i].reshape(-1, 3), world_pts[p.j].reshape(-1, 3)])
            wts = np.concatenate(
                [
                    (_weights(p.conf_i, kind) * world_w[p.i]).reshape(-1),
                    (_weights(p.conf_j, kind) * world_w[p.j]).reshape(-1),
                ]
            )
            sims[e] = _fit_sim3(src, dst, wts)
    return _Init(world_from_cam, focal, depth, [sims[e] for e in range(len(pairs))])


def _own_frame_points(
    pairs: Sequence[PairPrediction], num_views: int, size_hw: tuple[int, int], kind: ConfidenceWeight
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each view's points ``[H, W, 3]`` in its own camera frame, with their weights ``[H, W]``.

    From the view's most confident pair as view i; a view that is never first in a pair is placed
    in its most confident pair's frame by PnP and its points moved into its own camera frame.
    """
    scores = [float(p.conf_i.mean() * p.conf_j.mean()) for p in pairs]
    by_confidence = sorted(range(len(pairs)), key=lambda k: -scores[k])
    own: list[np.ndarray | None] = [None] * num_views
    own_w: list[np.ndarray | None] = [None] * num_views
    for e in by_confidence:
        p = pairs[e]
        if own[p.i] is None:
            own[p.i], own_w[p.i] = p.pts_i_in_i.astype(np.float64), _weights(p.conf_i, kind)
    for e in by_confidence:
        p = pairs[e]
        if own[p.j] is None:  # never first in a pair: place it in the pair frame by PnP
            w = _weights(p.conf_j, kind)
            cam_from_pair = _camera_from_foreign_points(p.pts_j_in_i, w, size_hw)
            own[p.j], own_w[p.j] = p.pts_j_in_i @ cam_from_pair[:, :3].T + cam_from_pair[:, 3], w
            log.debug("view %d is never first in a pair: placed by PnP in pair (%d, %d)", p.j, p.i, p.j)
    return own, own_w


def _walk_spanning_tree(
    pairs: Sequence[PairPrediction],
    num_views: int,
    own: list[np.ndarray],
    own_w: list[np.ndarray],
    kind: ConfidenceWeight,
) -> tuple[list[np.ndarray], list[np.ndarray], dict[int, Sim3]]:
    """Every view's points in the world (view 0's frame), walking the maximum spanning tree from view 0.

    Returns ``(world points [H, W, 3] per view, their weights [H, W], world_from_pair by pair index)``;
    the similarities cover the tree's pairs only.
    """
    tree = maximum_spanning_tree(num_views, pairs)
    neighbours: dict[int, list[int]] = {v: [] for v in range(num_views)}
    for e in tree:
        neighbours[pairs[e].i].append(e)
        neighbours[pairs[e].j].append(e)
    world_pts: list[np.ndarray | None] = [None] * num_views
    world_w: list[np.ndarray | None] = [None] * num_views
    world_pts[0], world_w[0] = own[0], own_w[0]
    sims: dict[int, Sim3] = {}
    queue = deque([0])
    while queue:
        a = queue.popleft()
        for e in neighbours[a]:
            p = pairs[e]
            b = p.j if p.i == a else p.i
            if world_pts[b] is not None:
                continue
            pts_a, conf_a = p.points_of(a)
            sims[e] = _fit_sim3(pts_a, world_pts[a], _weights(conf_a, kind) * world_w[a])
            pts_b, conf_b = p.points_of(b)
            world_pts[b], world_w[b] = sims[e].apply(pts_b.astype(np.float64)), _weights(conf_b, kind)
            queue.append(b)
    return world_pts, world_w, sims
