"""Which image pairs overlap, according to the feed-forward geometry.

Confident depth points of frame i are projected into frame j with the predicted cameras; the share
that lands inside j, in front of it and agrees with j's own predicted depth (so occluded points do
not count) is the overlap of i in j. Only overlapping pairs are matched, which is what makes the
refinement cheaper than exhaustive matching.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ffrecon.checks import check_number
from ffrecon.geometry.projection import flat_pixel_centers, project_points
from ffrecon.types import Prediction

logger = logging.getLogger("ffrecon.geometry")


@dataclass(frozen=True, kw_only=True)
class OverlapOptions:
    min_overlap: float = 0.25  # pairs whose overlap (the smaller of both directions) reaches this are matched
    max_pairs_per_image: int = 12  # ... but at most this many per image, the most overlapping first
    min_pairs_per_image: int = 4  # the best pairs of each image are matched whatever their overlap ...
    min_any_overlap: float = 0.02  # ... if they overlap at all
    fallback_neighbours: int = 2  # a frame with no pair reaching min_overlap also gets this many neighbours by index
    # Loop candidates: each frame also keeps its best pairs reaching min_overlap with frames at least
    # ``loop_min_gap`` apart in capture order (a revisit), however many nearer neighbours overlap more.
    loop_pairs_per_image: int = 2
    loop_min_gap: int = 30
    min_depth_conf: float = 1.0  # depth pixels below this confidence are not used
    max_depth_ratio: float = 0.15  # |z_projected / z_j - 1| above this: occluded in j
    samples_per_image: int = 1500
    # Long captures: from this many frames, pairs are first estimated on a tenth of the samples and measured
    # on all of them only where the estimate reaches coarse_min_overlap either way (see overlap_matrix).
    coarse_from_frames: int = 300
    coarse_min_overlap: float = 0.05
    # ... and only for each frame's best coarse_margin x (max_pairs_per_image + min_pairs_per_image) partners by
    # the estimate and its best coarse_margin x loop_pairs_per_image revisits: those that can be chosen, with room
    # for the estimate's error. On an orbit of a room every frame overlaps nearly every other (500 frames: 210
    # partners a frame at 0.25 or more), and measuring them all took 29 s.
    coarse_margin: int = 3
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("min_overlap", "min_any_overlap"):
            check_number(f"OverlapOptions.{name}", getattr(self, name), low=0, high=1)
        names = ("max_pairs_per_image", "min_pairs_per_image", "fallback_neighbours", "loop_pairs_per_image")
        check_number("OverlapOptions.loop_min_gap", self.loop_min_gap, low=1, integer=True)
        for name in names:
            check_number(f"OverlapOptions.{name}", getattr(self, name), low=0, integer=True)
        check_number("OverlapOptions.samples_per_image", self.samples_per_image, low=1, integer=True)
        check_number("OverlapOptions.coarse_from_frames", self.coarse_from_frames, low=0, integer=True)
        check_number("OverlapOptions.coarse_min_overlap", self.coarse_min_overlap, low=0, high=1)
        check_number("OverlapOptions.coarse_margin", self.coarse_margin, low=1, integer=True)
        check_number("OverlapOptions.min_depth_conf", self.min_depth_conf, low=0)
        check_number("OverlapOptions.max_depth_ratio", self.max_depth_ratio, low=0, low_open=True)


@dataclass(frozen=True)
class OverlapGraph:
    """Overlap fractions and the pairs chosen for matching."""

    overlap: np.ndarray  # [N, N] float, overlap[i, j]: share of i's confident points seen by j
    pairs: np.ndarray  # [P, 2] int, i < j
    options: OverlapOptions = OverlapOptions()  # what made it (a later user may reuse it under the same options)

    def score(self) -> np.ndarray:
        """``[N, N]`` symmetric score: the smaller overlap of the two directions."""
        return np.minimum(self.overlap, self.overlap.T)

    def reach(self) -> np.ndarray:
        """``[N, N]`` symmetric: the larger overlap of the two directions. On a forward walk the later
        frame sees a small share of the earlier one's points (it has passed them) but the earlier frame
        sees most of the later one's: lund every 4th photo scores 0.06 one way and 0.24 the other."""
        return np.maximum(self.overlap, self.overlap.T)


TILES = 4  # each frame's sampled points are grouped by a TILES x TILES grid of its image for the frustum test


def _sample_points(
    prediction: Prediction, i: int, options: OverlapOptions, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``([M, 3] world points, [M] image tile)`` from confident depth of frame i (random subset of the valid
    pixels), ordered by tile (row-major over a ``TILES`` x ``TILES`` grid of the image)."""
    valid = np.flatnonzero(prediction.valid_mask(i, options.min_depth_conf).ravel())
    if len(valid) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    pick = (
        valid
        if len(valid) <= options.samples_per_image
        else rng.choice(valid, options.samples_per_image, replace=False)
    )
    h, w = prediction.depth[i].shape
    tile = (pick // w) * TILES // h * TILES + (pick % w) * TILES // w
    pick = pick[np.argsort(tile, kind="stable")]
    cam = prediction.depth_camera(i)
    depth = prediction.depth[i].ravel()[pick].astype(np.float64)
    uv = flat_pixel_centers(pick, w)
    rays = np.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy, np.ones(len(pick))], axis=1)
    pose = prediction.cam_from_world[i]
    return (rays * depth[:, None] - pose[:, 3]) @ pose[:, :3], np.sort(tile)


@dataclass(frozen=True)
class _Groups:
    """The sampled points of every frame, grouped by frame and image tile: group g holds the points
    ``start[g] : start[g] + count[g]`` of ``points``, of frame ``frame[g]``, inside the ball (centre, radius)."""

    points: np.ndarray  # [M, 3]
    frame: np.ndarray  # [G]
    start: np.ndarray  # [G]
    count: np.ndarray  # [G]
    centre: np.ndarray  # [G, 3]
    radius: np.ndarray  # [G]

    @classmethod
    def of(cls, samples: list[tuple[np.ndarray, np.ndarray]]) -> _Groups:
        points = np.concatenate([p for p, _ in samples]) if samples else np.zeros((0, 3))
        key = np.concatenate([i * TILES * TILES + t for i, (_, t) in enumerate(samples)]) if samples else []
        key = np.asarray(key, np.int64)
        first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if len(key) else np.zeros(0, np.int64)
        count = np.diff(np.r_[first, len(key)])
        owner = np.repeat(np.arange(len(first)), count)
        centre = np.add.reduceat(points, first, axis=0) / count[:, None] if len(first) else np.zeros((0, 3))
        distance = np.linalg.norm(points - centre[owner], axis=1)
        radius = np.maximum.reduceat(distance, first) if len(first) else np.zeros(0)
        return cls(points, key[first] // (TILES * TILES), first, count, centre, radius)

    def rows(self, groups: np.ndarray) -> np.ndarray:
        """The indices into ``points`` of ``groups``, in order."""
        count = self.count[groups]
        offset = np.repeat(self.start[groups] - np.r_[0, np.cumsum(count)[:-1]], count)
        return offset + np.arange(count.sum())


def _in_view(groups: _Groups, prediction: Prediction, j: int) -> np.ndarray:
    """``[G]`` bool: the group's points may land in frame j's image.

    A group's points lie in its ball; a ball wholly behind one of frame j's four image-border planes has no
    point in the image (a point with ``0 <= u < w``, ``0 <= v < h`` at positive depth is on the inner side of
    all four). The test never drops a group that could be seen, so the overlap is unchanged; it only saves
    projections. (A few lines of numpy: open3d's frustum tests work on meshes and boxes, not on balls.)
    """
    cam = prediction.depth_camera(j)
    h, w = prediction.depth[j].shape
    pose = prediction.cam_from_world[j]
    centre = groups.centre @ pose[:, :3].T + pose[:, 3]
    normals = np.array([[cam.fx, 0, cam.cx], [-cam.fx, 0, w - cam.cx], [0, cam.fy, cam.cy], [0, -cam.fy, h - cam.cy]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)  # inner normals of the planes u = 0, w; v = 0, h
    margin = groups.radius * (1 + 1e-9) + 1e-9 * (1 + np.abs(centre).max(1, initial=0.0))
    return ((centre @ normals.T) >= -margin[:, None]).all(1)


def overlap_matrix(prediction: Prediction, options: OverlapOptions = OverlapOptions()) -> np.ndarray:
    """``[N, N]`` overlap[i, j] in [0, 1]: share of frame i's confident depth points visible in frame j.

    The diagonal is 1 (0 for a frame with no confident depth). Into each frame j go the sampled points
    that may be in its view (:func:`_in_view`, per frame and image tile). From ``coarse_from_frames``
    frames, every pair is first estimated on a tenth of the samples, and only the pairs that reach
    ``coarse_min_overlap`` either way and that :func:`select_pairs` could choose (:func:`_worth_measuring`)
    are measured on all of them (the others keep the estimate): on an orbit every frame is in every other's
    view, and projecting every frame's points into every frame grew as frames^2 (16 s at 400 frames, 27 s
    at 500).
    """
    n = len(prediction)
    rng = np.random.default_rng(options.seed)
    samples = [_sample_points(prediction, i, options, rng) for i in range(n)]
    if n < options.coarse_from_frames:
        return _overlaps(_Groups.of(samples), prediction, options)
    coarse = _overlaps(_Groups.of([(p[::10], t[::10]) for p, t in samples]), prediction, options)
    candidates = (np.maximum(coarse, coarse.T) >= options.coarse_min_overlap) & _worth_measuring(coarse, options)
    fine = _overlaps(_Groups.of(samples), prediction, options, candidates)
    return np.where(candidates, fine, coarse)


def _worth_measuring(coarse: np.ndarray, options: OverlapOptions) -> np.ndarray:
    """``[N, N]`` symmetric bool: each frame's best ``coarse_margin`` times as many partners as
    :func:`select_pairs` may choose by the estimated score, and as many times its best revisits."""
    n = len(coarse)
    score = np.minimum(coarse, coarse.T)
    np.fill_diagonal(score, -1.0)
    near = min(n - 1, options.coarse_margin * (options.max_pairs_per_image + options.min_pairs_per_image))
    far = options.coarse_margin * options.loop_pairs_per_image
    rows = np.arange(n)[:, None]
    keep = np.zeros((n, n), bool)
    keep[rows, np.argsort(-score, axis=1, kind="stable")[:, :near]] = True
    revisit = np.where(np.abs(rows - np.arange(n)[None, :]) >= options.loop_min_gap, score, -1.0)
    keep[rows, np.argsort(-revisit, axis=1, kind="stable")[:, : min(far, n)]] = True
    np.fill_diagonal(keep, False)  # a short row's revisit ranking may reach the frame itself
    return keep | keep.T


def _overlaps(
    groups: _Groups, prediction: Prediction, options: OverlapOptions, candidates: np.ndarray | None = None
) -> np.ndarray:
    """The overlap matrix on ``groups``' points; with ``candidates`` ``[N, N]`` only its pairs (others 0)."""
    n = len(prediction)
    counts = np.bincount(groups.frame, weights=groups.count, minlength=n).astype(np.int64)
    out = np.zeros((n, n))
    for j in range(n):
        near = _in_view(groups, prediction, j)
        if candidates is not None:
            near &= candidates[groups.frame, j]
        near = np.flatnonzero(near)
        owner = np.repeat(groups.frame[near], groups.count[near])
        cam = prediction.depth_camera(j)
        h, w = prediction.depth[j].shape
        uv, z = project_points(groups.points[groups.rows(near)], cam.K, prediction.cam_from_world[j])
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        col = np.clip(uv[inside, 0].astype(int), 0, w - 1)
        row = np.clip(uv[inside, 1].astype(int), 0, h - 1)
        z_j = prediction.depth[j][row, col].astype(np.float64)
        seen = np.where(z_j > 0, np.abs(z[inside] / np.maximum(z_j, 1e-12) - 1.0) <= options.max_depth_ratio, True)
        out[:, j] = np.bincount(owner[inside][seen], minlength=n) / np.maximum(counts, 1)
    out[np.arange(n), np.arange(n)] = (counts > 0).astype(float)
    return out


def select_pairs(overlap: np.ndarray, options: OverlapOptions = OverlapOptions()) -> np.ndarray:
    """``[P, 2]`` pairs i < j to match, from an overlap matrix (see :class:`OverlapOptions`).

    >>> ov = np.array([[1.0, 0.6, 0.0], [0.5, 1.0, 0.3], [0.0, 0.4, 1.0]])
    >>> select_pairs(ov, OverlapOptions(min_pairs_per_image=1)).tolist()
    [[0, 1], [1, 2]]
    """
    n = len(overlap)
    score = np.minimum(overlap, overlap.T)
    np.fill_diagonal(score, -1.0)
    chosen = np.zeros((n, n), bool)
    for i in range(n):
        order = np.argsort(-score[i], kind="stable")
        good = [j for j in order if score[i, j] >= options.min_overlap][: options.max_pairs_per_image]
        best = [j for j in order[: options.min_pairs_per_image] if score[i, j] >= options.min_any_overlap]
        loops = [j for j in order if abs(i - j) >= options.loop_min_gap and score[i, j] >= options.min_overlap]
        chosen[i, good + best + loops[: options.loop_pairs_per_image]] = True
    chosen |= chosen.T
    # A frame the prediction places apart from the others (no pair reaches min_overlap: maybe a badly
    # predicted pose) also gets its neighbours in input order, the likeliest overlaps of ordered captures.
    for i in np.flatnonzero(score.max(1) < options.min_overlap):
        for j in range(i - options.fallback_neighbours, i + options.fallback_neighbours + 1):
            if 0 <= j < n and j != i:
                chosen[i, j] = chosen[j, i] = True
    i, j = np.nonzero(np.triu(chosen, k=1))
    return np.stack([i, j], axis=1)


def overlap_graph(prediction: Prediction, options: OverlapOptions = OverlapOptions()) -> OverlapGraph:
    """Overlap matrix and chosen pairs; logs how many pairs exhaustive matching would have needed."""
    overlap = overlap_matrix(prediction, options)
    pairs = select_pairs(overlap, options)
    n = len(prediction)
    logger.info("feed-forward overlap: %d of %d image pairs to match", len(pairs), n * (n - 1) // 2)
    return OverlapGraph(overlap, pairs, options)


def view_agreement(
    prediction: Prediction, frames: Sequence[int], options: OverlapOptions = OverlapOptions(), partners: int = 32
) -> np.ndarray:
    """``[len(frames), 2]``: for each frame i of ``frames``, summed over the ``partners`` other frames whose model
    centres are nearest its own (a bound on the cost of long captures), the share of i's
    confident depth points that land inside j's image in front of it, and the share that also agree with j's own
    depth (within ``options.max_depth_ratio``: the overlap of i in j). How well the model's depth of a frame,
    placed with its camera, agrees with the other frames' depth where they look at the same space: a camera
    turned far from the truth puts its points where the other frames see something else."""
    rng = np.random.default_rng(options.seed)
    out = np.zeros((len(frames), 2))
    pose = prediction.cam_from_world
    centres = np.einsum("nij,ni->nj", pose[:, :, :3], -pose[:, :, 3])
    for row, i in enumerate(frames):
        points, _ = _sample_points(prediction, i, options, rng)
        if len(points) == 0:
            continue
        order = np.argsort(np.linalg.norm(centres - centres[i], axis=1), kind="stable")
        for j in [int(j) for j in order if j != i][:partners]:
            cam = prediction.depth_camera(j)
            h, w = prediction.depth[j].shape
            uv, z = project_points(points, cam.K, prediction.cam_from_world[j])
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            col = np.clip(uv[inside, 0].astype(int), 0, w - 1)
            line = np.clip(uv[inside, 1].astype(int), 0, h - 1)
            z_j = prediction.depth[j][line, col].astype(np.float64)
            agree = (z_j > 0) & (np.abs(z[inside] / np.maximum(z_j, 1e-12) - 1.0) <= options.max_depth_ratio)
            out[row] += (inside.sum() / len(points), agree.sum() / len(points))
    return out
