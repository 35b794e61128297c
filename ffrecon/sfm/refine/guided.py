"""SIFT matching checked, or guided, by the feed-forward geometry.

A keypoint of image i, lifted with i's predicted depth and moved into image j with the predicted
cameras, lands near its true match. Feed-forward pose errors shift and slightly warp those
predictions for the whole pair, so a 2D map from predicted to matched positions (a homography when
filtering, an affine map when guiding) is fitted robustly per pair, and a match must lie within a
few pixels of its mapped prediction.

Two uses: FILTER drops COLMAP's verified matches that disagree; GUIDED searches each keypoint's match
only near its prediction, with the ratio test among those candidates, and leaves verification to
COLMAP afterwards. On repeated textures, look-alikes make the global ratio test discard most true
matches and let wrong ones through epipolar verification; guided search keeps the true ones.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ffrecon.checks import check_number
from ffrecon.types import Prediction
from ffrecon.validate import validate_prediction

logger = logging.getLogger("ffrecon.sfm")


class MatchGuidance(enum.Enum):
    AUTO = "auto"  # FILTER, switching to GUIDED when the filter rejects most matches (look-alike surfaces)
    NONE = "none"  # COLMAP's matching and verification, as in the cross-check
    FILTER = "filter"  # COLMAP's matches, minus those that disagree with the feed-forward geometry
    GUIDED = "guided"  # each match searched near its feed-forward prediction (best on repeated textures)


@dataclass(frozen=True, kw_only=True)
class GuidanceOptions:
    mode: MatchGuidance = MatchGuidance.AUTO
    auto_max_rejected: float = 0.25  # AUTO: above this share of rejected matches, redo the matching guided
    window_deg: float = 10.0  # first cut: predicted and matched positions within focal * tan(this)
    tolerance: float = 0.02  # guided: search radius around the corrected prediction, fraction of the image diagonal
    filter_tolerance: float = 0.03  # filter: RANSAC threshold of the predicted-to-matched homography, same unit
    max_ratio: float = 0.8  # guided: ratio test among the candidates inside the window
    max_distance: float = 0.5  # guided: largest L2 distance of unit descriptors (stricter than COLMAP's 0.7)
    min_depth_conf: float = 1.0
    min_fit_matches: int = 8  # fewer candidates than this: keep those inside the first cut only
    seed: int = 0  # RANSAC of the filter
    fit_keypoints: int = 500  # guided: keypoints used in the wide search that measures the pair's error
    # Guided: a verified pair whose own relative rotation is further than this from the model's is dropped
    # (:func:`ffrecon.sfm.refine.screen.drop_contradicting_pairs`): on look-alike surfaces such pairs are one period of
    # the pattern off. Feed-forward errors are a few degrees (2.5 per frame: pairs within ~3.5, ~7 at worst).
    max_pair_gap_deg: float = 8.0
    # Guided: the adjustment triangulates two-view tracks too, with a robust fine pass (sfm/refine/run.py,
    # _on_lookalikes); False: COLMAP's default, tracks over three frames or more only.
    two_view_tracks: bool = True

    def __post_init__(self) -> None:
        check_number("GuidanceOptions.auto_max_rejected", self.auto_max_rejected, low=0, high=1)
        check_number("GuidanceOptions.max_ratio", self.max_ratio, low=0, low_open=True, high=1)
        # the first cut is focal * tan(window_deg): unbounded at 90 degrees
        check_number("GuidanceOptions.window_deg", self.window_deg, low=0, low_open=True, high=89)
        for name in ("tolerance", "filter_tolerance", "max_distance"):
            check_number(f"GuidanceOptions.{name}", getattr(self, name), low=0, low_open=True)
        check_number("GuidanceOptions.min_depth_conf", self.min_depth_conf, low=0)
        check_number("GuidanceOptions.min_fit_matches", self.min_fit_matches, low=0, integer=True)
        check_number("GuidanceOptions.fit_keypoints", self.fit_keypoints, low=1, integer=True)
        check_number("GuidanceOptions.max_pair_gap_deg", self.max_pair_gap_deg, low=0, low_open=True, high=180)


@dataclass(frozen=True)
class GuidanceStats:
    mode: MatchGuidance
    num_pairs: int
    matches_before: int  # FILTER: COLMAP's verified matches; GUIDED: matches of the wide first search
    matches_after: int  # matches handed to geometric verification
    num_unchecked: int  # FILTER: matches with no confident depth at either end, kept
    median_residual_px: float = float("nan")  # FILTER: kept matches' distance to their mapped predictions
    dropped_pairs: int = 0  # GUIDED: verified pairs dropped as far from the model (look-alike periods)

    @property
    def lookalike(self) -> bool:
        """Whether the matching was guided by the model: what the refinement does on look-alike surfaces."""
        return self.mode is MatchGuidance.GUIDED

    @property
    def rejected_share(self) -> float:
        return 1.0 - self.matches_after / self.matches_before if self.matches_before else 0.0

    def to_report(self) -> dict:
        return {
            "mode": self.mode.value,
            "num_pairs": self.num_pairs,
            "matches_before": self.matches_before,
            "matches_after": self.matches_after,
            "num_unchecked": self.num_unchecked,
            "median_residual_px": self.median_residual_px if np.isfinite(self.median_residual_px) else None,
            "dropped_pairs": self.dropped_pairs,
        }


def predict_positions(
    prediction: Prediction, i: int, j: int, xy_i: np.ndarray, min_conf: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where ``[M, 2]`` pixels of image i should appear in image j (COLMAP pixel convention).

    Returns ``(xy_j [M, 2], valid [M] bool)``; invalid where i has no confident depth or the point
    falls behind camera j.
    """
    cam_i, cam_j = prediction.cameras[i], prediction.cameras[j]
    depth, conf = prediction.depth[i], prediction.depth_conf[i]
    h, w = depth.shape
    col = np.clip((xy_i[:, 0] * w / cam_i.width).astype(int), 0, w - 1)
    row = np.clip((xy_i[:, 1] * h / cam_i.height).astype(int), 0, h - 1)
    z = depth[row, col].astype(np.float64)
    ok = (z > 0) & (conf[row, col] >= min_conf)
    rays = np.stack(
        [(xy_i[:, 0] - cam_i.cx) / cam_i.fx, (xy_i[:, 1] - cam_i.cy) / cam_i.fy, np.ones(len(xy_i))], axis=1
    )
    pose_i, pose_j = prediction.cam_from_world[i], prediction.cam_from_world[j]
    world = (rays * z[:, None] - pose_i[:, 3]) @ pose_i[:, :3]
    pc = world @ pose_j[:, :3].T + pose_j[:, 3]
    ok &= pc[:, 2] > 1e-9
    safe_z = np.where(ok, pc[:, 2], 1.0)
    xy_j = np.stack([cam_j.fx * pc[:, 0] / safe_z + cam_j.cx, cam_j.fy * pc[:, 1] / safe_z + cam_j.cy], axis=1)
    return xy_j, ok


def _affine_inliers(pred: np.ndarray, obs: np.ndarray, cand: np.ndarray, tol: float, min_fit: int) -> np.ndarray:
    """Matches within ``tol`` px of a robust affine map of ``pred`` onto ``obs`` fitted on ``cand``."""
    if cand.sum() < min_fit:
        return cand
    design = np.concatenate([pred, np.ones((len(pred), 1))], axis=1)
    use = cand.copy()
    for _ in range(3):
        coef, *_ = np.linalg.lstsq(design[use], obs[use], rcond=None)
        resid = np.linalg.norm(design @ coef - obs, axis=1)
        new = cand & (resid <= max(tol, 2.5 * float(np.median(resid[use]))))
        if new.sum() < min_fit or np.array_equal(new, use):
            break
        use = new
    return cand & (resid <= tol)


def _check_pair(
    prediction: Prediction, i: int, j: int, xy_i: np.ndarray, xy_j: np.ndarray, options: GuidanceOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(keep [M] bool, checked [M] bool, residual [M] float)`` for matched keypoints ``xy_i[k] <-> xy_j[k]``.

    In each direction the predicted positions are mapped onto the matched ones by a homography
    (RANSAC, so a badly predicted frame only shifts the map); matches off the map are dropped.
    ``residual`` is the larger distance (pixels) of the two directions between a match and its mapped
    prediction (nan where unchecked): how precisely the model predicts this pair.
    """
    keep = np.ones(len(xy_i), bool)
    checked = np.zeros(len(xy_i), bool)
    residual = np.full(len(xy_i), np.nan)
    for a, b, src, dst in ((i, j, xy_i, xy_j), (j, i, xy_j, xy_i)):
        cam = prediction.cameras[b]
        pred, ok = predict_positions(prediction, a, b, src, options.min_depth_conf)
        tol = options.filter_tolerance * float(np.hypot(cam.width, cam.height))
        inlier = np.zeros(len(src), bool)
        if ok.sum() >= options.min_fit_matches:
            homography, mask = cv2.findHomography(pred[ok], dst[ok], cv2.RANSAC, tol, maxIters=2000, confidence=0.999)
            if homography is not None:
                inlier[np.flatnonzero(ok)] = mask.ravel().astype(bool)
                mapped = cv2.perspectiveTransform(pred[ok].reshape(-1, 1, 2), homography).reshape(-1, 2)
                dist = np.linalg.norm(mapped - dst[ok], axis=1)
                residual[ok] = np.fmax(residual[ok], dist)
        keep &= inlier | ~ok
        checked |= ok
    return keep, checked, residual


def filter_matches(
    db_path: Path,
    prediction: Prediction,
    pairs: Sequence[tuple[str, str]],
    options: GuidanceOptions = GuidanceOptions(),
    *,
    min_inliers: int = 15,
) -> GuidanceStats:
    """Drop verified matches of ``pairs`` that disagree with the feed-forward geometry (database rewritten).

    Works on the inlier matches of COLMAP's two-view geometries; a pair left with fewer than
    ``min_inliers`` loses its geometry (no edge in the correspondence graph).
    """
    validate_prediction(prediction, allow_empty_depth=True)
    index = {name: k for k, name in enumerate(prediction.names)}
    cv2.setRNGSeed(options.seed)
    db = pycolmap.Database.open(str(db_path))
    before = after = unchecked = 0
    kept_residuals: list[np.ndarray] = []
    try:
        ids: Mapping[str, int] = {image.name: image.image_id for image in db.read_all_images()}
        keypoints: dict[int, np.ndarray] = {}

        def xy(image_id: int) -> np.ndarray:
            if image_id not in keypoints:
                keypoints[image_id] = np.asarray(db.read_keypoints(image_id))[:, :2].astype(np.float64)
            return keypoints[image_id]

        for name_a, name_b in pairs:
            id_a, id_b = ids[name_a], ids[name_b]
            if not db.exists_two_view_geometry(id_a, id_b):
                continue
            geometry = db.read_two_view_geometry(id_a, id_b)
            matches = np.asarray(geometry.inlier_matches)
            if len(matches) == 0:
                continue
            keep, checked, residual = _check_pair(
                prediction, index[name_a], index[name_b], xy(id_a)[matches[:, 0]], xy(id_b)[matches[:, 1]], options
            )
            kept = int(keep.sum()) if keep.sum() >= min_inliers else 0
            before += len(matches)
            after += kept
            unchecked += int((~checked).sum())
            kept_residuals.append(residual[keep & checked])
            if kept == 0:
                db.delete_two_view_geometry(id_a, id_b)
            elif kept < len(matches):
                geometry.inlier_matches = np.ascontiguousarray(matches[keep], dtype=np.uint32)
                db.update_two_view_geometry(id_a, id_b, geometry)
    finally:
        db.close()
    kept = np.concatenate(kept_residuals) if kept_residuals else np.zeros(0)
    kept = kept[np.isfinite(kept)]
    median_px = float(np.median(kept)) if len(kept) else float("nan")
    logger.info(
        "feed-forward match filter kept %d of %d matches over %d pairs (kept matches %.1f px from their mapped "
        "predictions, median)",
        after,
        before,
        len(pairs),
        median_px,
    )
    return GuidanceStats(MatchGuidance.FILTER, len(pairs), before, after, unchecked, median_px)


def _unit_descriptors(desc: np.ndarray) -> np.ndarray:
    d = np.asarray(desc, np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-6)


def _window_candidates(
    pred: np.ndarray, rows: np.ndarray, xy_j: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """All ``(i, j)`` with ``|pred[i] - xy_j[j]| <= radius`` for i in ``rows`` (grid hashing, no N x M matrix)."""
    big = np.int64(1 << 24)
    cell_j = np.floor(xy_j / radius).astype(np.int64)
    key_j = cell_j[:, 0] * big + cell_j[:, 1]
    order = np.argsort(key_j, kind="stable")
    sorted_keys = key_j[order]
    cell_i = np.floor(pred[rows] / radius).astype(np.int64)
    ii_parts, jj_parts = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            key = (cell_i[:, 0] + dx) * big + (cell_i[:, 1] + dy)
            lo = np.searchsorted(sorted_keys, key, "left")
            counts = np.searchsorted(sorted_keys, key, "right") - lo
            total = int(counts.sum())
            if total == 0:
                continue
            starts = np.repeat(lo - (np.cumsum(counts) - counts), counts)
            ii_parts.append(np.repeat(rows, counts))
            jj_parts.append(order[starts + np.arange(total)])
    if not ii_parts:
        return np.zeros(0, int), np.zeros(0, int)
    ii, jj = np.concatenate(ii_parts), np.concatenate(jj_parts)
    near = ((pred[ii] - xy_j[jj]) ** 2).sum(1) <= radius**2
    return ii[near], jj[near]


def _first_per_group(group: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices (into the inputs) of the smallest and second-smallest ``value`` per ``group`` (-1: none).

    ``value`` must lie in [0, 4) (descriptor distances do), so one float key sorts by group, then value.
    """
    order = np.argsort(group * 4.0 + value, kind="stable")
    g = group[order]
    first = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    has_second = (first + 1 < len(g)) & (g[np.minimum(first + 1, len(g) - 1)] == g[first])
    second = np.where(has_second, order[np.minimum(first + 1, len(g) - 1)], -1)
    return order[first], second


def _match_in_windows(
    desc_i: np.ndarray,
    desc_j: np.ndarray,
    pred: np.ndarray,
    rows: np.ndarray,
    xy_j: np.ndarray,
    radius: float,
    options: GuidanceOptions,
) -> np.ndarray:
    """``[K, 2]`` mutual best descriptor matches within ``radius`` px of the predictions of ``rows``.

    Ratio test against the second-best candidate inside the same window.
    """
    ii, jj = _window_candidates(pred, rows, xy_j, radius)
    if len(ii) == 0:
        return np.zeros((0, 2), int)
    if len(ii) > 0.1 * len(rows) * len(desc_j):  # dense enough: one matrix product is cheaper
        position = np.zeros(len(desc_i), int)
        position[rows] = np.arange(len(rows))
        dot = (desc_i[rows] @ desc_j.T)[position[ii], jj]
    else:
        dot = np.einsum("kd,kd->k", desc_i[ii], desc_j[jj])
    dist = np.sqrt(np.maximum(2.0 - 2.0 * dot, 0.0))
    best, second = _first_per_group(ii, dist)
    ok = dist[best] <= options.max_distance
    ok &= (second < 0) | (dist[best] <= options.max_ratio * dist[np.maximum(second, 0)])
    col_best, _ = _first_per_group(jj, dist)
    mutual = np.zeros(len(ii), bool)
    mutual[col_best] = True
    chosen = best[ok & mutual[best]]
    return np.stack([ii[chosen], jj[chosen]], axis=1)


def _guided_pair(
    prediction: Prediction,
    i: int,
    j: int,
    xy_i: np.ndarray,
    xy_j: np.ndarray,
    desc_i: np.ndarray,
    desc_j: np.ndarray,
    options: GuidanceOptions,
) -> tuple[np.ndarray, int]:
    """Guided matches ``[K, 2]`` of one pair, and the number found in the wide first search."""
    cam = prediction.cameras[j]
    pred, valid = predict_positions(prediction, i, j, xy_i, options.min_depth_conf)
    rows = np.flatnonzero(valid)
    if len(rows) == 0 or len(xy_j) < 2:
        return np.zeros((0, 2), int), 0
    window = 0.5 * (cam.fx + cam.fy) * np.tan(np.radians(options.window_deg))
    tol = options.tolerance * float(np.hypot(cam.width, cam.height))
    # Wide search on a subset, to measure this pair's feed-forward error as an affine map.
    subset = rows[np.linspace(0, len(rows) - 1, min(len(rows), options.fit_keypoints)).astype(int)]
    first = _match_in_windows(desc_i, desc_j, pred, subset, xy_j, window, options)
    if len(first) < options.min_fit_matches:
        return first, len(first)
    inl = _affine_inliers(pred[first[:, 0]], xy_j[first[:, 1]], np.ones(len(first), bool), tol, options.min_fit_matches)
    if inl.sum() < options.min_fit_matches:
        return first[inl], len(first)
    design = np.concatenate([pred[first[inl, 0]], np.ones((int(inl.sum()), 1))], axis=1)
    coef, *_ = np.linalg.lstsq(design, xy_j[first[inl, 1]], rcond=None)
    corrected = np.concatenate([pred, np.ones((len(pred), 1))], axis=1) @ coef
    # Tight search of every keypoint around its corrected prediction.
    return _match_in_windows(desc_i, desc_j, corrected, rows, xy_j, tol, options), len(first)


def guided_matches(
    db_path: Path,
    prediction: Prediction,
    pairs: Sequence[tuple[str, str]],
    options: GuidanceOptions = GuidanceOptions(),
) -> GuidanceStats:
    """Match ``pairs`` near their feed-forward predictions and write the raw matches to the database.

    Matches are searched from the image of each pair with more confident depth; verification is
    left to COLMAP (:func:`ffrecon.sfm.features.verify_pairs`).
    """
    validate_prediction(
        prediction, allow_empty_depth=True
    )  # an infinite focal would turn every predicted position into NaN
    index = {name: k for k, name in enumerate(prediction.names)}
    db = pycolmap.Database.open(str(db_path))
    first_total = after = 0
    try:
        ids: Mapping[str, int] = {image.name: image.image_id for image in db.read_all_images()}
        cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

        def features(image_id: int) -> tuple[np.ndarray, np.ndarray]:
            if image_id not in cache:
                xy = np.asarray(db.read_keypoints(image_id))[:, :2].astype(np.float64)
                cache[image_id] = (xy, _unit_descriptors(np.asarray(db.read_descriptors(image_id).data)))
            return cache[image_id]

        for name_a, name_b in pairs:
            id_a, id_b = ids[name_a], ids[name_b]
            (xy_a, d_a), (xy_b, d_b) = features(id_a), features(id_b)
            if len(xy_a) == 0 or len(xy_b) == 0:
                continue
            matches, first = _guided_pair(prediction, index[name_a], index[name_b], xy_a, xy_b, d_a, d_b, options)
            first_total += first
            after += len(matches)
            if db.exists_two_view_geometry(id_a, id_b):
                db.delete_two_view_geometry(id_a, id_b)
            if db.exists_matches(id_a, id_b):
                db.delete_matches(id_a, id_b)
            db.write_matches(id_a, id_b, np.ascontiguousarray(matches, dtype=np.uint32))
    finally:
        db.close()
    logger.info("feed-forward guided matching: %d matches over %d pairs", after, len(pairs))
    return GuidanceStats(MatchGuidance.GUIDED, len(pairs), first_total, after, 0)
