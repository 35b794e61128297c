"""A photometric check of the frames no image match could check: do the other frames, seen from its camera,
look like its photo?

For frame k, each pixel of a small copy of its photo is lifted with the model's depth of k and its final
camera, and looked up in a neighbour's photo through the neighbour's final camera (a backward warp). Where the
camera is right the warped neighbour looks like the photo; a camera turned 25 deg shows the neighbour's
pixels of another part of the scene. The photos are compared small (``side_px``) and blurred, so the few
degrees a model is off (2.5 deg: about 2 px at 64 px) keep a high correlation while tens of degrees do not,
and so fine repeated patterns average out and the scene's layout decides.

The frame does not judge itself: neither its depth (the model's, independent of its pose) nor its photo
shapes the neighbours it is compared with, which are frames the evidence confirmed. A frame's score is its
best normalised cross-correlation over those neighbours that cover enough of it; it is judged against the
confirmed frames' own scores (each against the other confirmed frames), not against a fixed number, since
texture and blur change what a good score is.

Written with OpenCV's resize and remap rather than a renderer: a backward warp through one depth map is a
few lines, needs no splat, and so also runs with ``--no-splat``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ffrecon.checks import check_number
from ffrecon.geometry.projection import pixel_centers
from ffrecon.types import Prediction


@dataclass(frozen=True, kw_only=True)
class PhotometricOptions:
    enabled: bool = True
    side_px: int = 64  # photos compared at this long side
    blur_px: float = 1.0  # Gaussian blur (sigma, pixels at side_px) before comparing
    min_overlap: float = 0.25  # share of the frame's pixels a neighbour must show to count
    min_depth_conf: float = 1.0
    # Contradicted: the frame's best score is below ratio x the confirmed frames' median score. Tuned on seeds
    # 101-106 of tools/sweep_families.py (see docs/pipeline.md), checked on 201-203.
    ratio: float = 0.6
    min_reference: int = 2  # confirmed frames needed to judge anything

    def __post_init__(self) -> None:
        check_number("PhotometricOptions.side_px", self.side_px, low=16, integer=True)
        check_number("PhotometricOptions.blur_px", self.blur_px, low=0)
        check_number("PhotometricOptions.min_overlap", self.min_overlap, low=0, low_open=True, high=1)
        check_number("PhotometricOptions.min_depth_conf", self.min_depth_conf, low=0)
        check_number("PhotometricOptions.ratio", self.ratio, low=0, low_open=True, high=1)
        check_number("PhotometricOptions.min_reference", self.min_reference, low=1, integer=True)


@dataclass(frozen=True)
class PhotometricScore:
    """One frame's best correlation with a confirmed neighbour seen from its camera (nan: none covers it)."""

    score: float
    neighbour: str | None
    overlap: float


@dataclass(frozen=True)
class PhotometricCheck:
    reference: float  # the confirmed frames' median score
    scores: dict[str, PhotometricScore]  # the frames checked
    threshold: float  # below: contradicted

    def contradicts(self, name: str) -> bool:
        s = self.scores.get(name)
        return s is not None and np.isfinite(s.score) and s.score < self.threshold

    def describe(self, name: str) -> str:
        s = self.scores[name]
        return (
            f"its photo matches the confirmed frames seen from its camera at {s.score:.2f} (best, {s.neighbour}, "
            f"{s.overlap:.0%} of it covered) against {self.reference:.2f} for the confirmed frames (< "
            f"{self.threshold:.2f}): its camera is wrong"
        )


class _Small:
    """The frames' photos (grey, small, blurred) and cameras at that size, read once each when needed."""

    def __init__(self, read: Callable[[int], np.ndarray], prediction: Prediction, options: PhotometricOptions):
        self.read, self.prediction, self.options = read, prediction, options
        self.grey: dict[int, np.ndarray] = {}

    def photo(self, k: int) -> np.ndarray:
        if k not in self.grey:
            rgb = self.read(k)
            h, w = rgb.shape[:2]
            s = self.options.side_px / max(h, w)
            size = (max(int(round(w * s)), 8), max(int(round(h * s)), 8))
            grey = cv2.cvtColor(cv2.resize(rgb, size, interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2GRAY)
            blur = self.options.blur_px
            self.grey[k] = (cv2.GaussianBlur(grey, (0, 0), blur) if blur > 0 else grey).astype(np.float32)
        return self.grey[k]

    def camera(self, k: int):
        h, w = self.photo(k).shape
        cam = self.prediction.cameras[k]
        return cam.scaled(w / cam.width, h / cam.height)


def _warp_score(small: _Small, poses: np.ndarray, k: int, j: int) -> tuple[float, float]:
    """``(ncc, overlap)`` of frame k's photo and frame j's photo warped into k's camera."""
    grey_k, cam_k, cam_j = small.photo(k), small.camera(k), small.camera(j)
    h, w = grey_k.shape
    depth = cv2.resize(small.prediction.depth[k], (w, h), interpolation=cv2.INTER_NEAREST).astype(np.float64)
    conf = cv2.resize(small.prediction.depth_conf[k], (w, h), interpolation=cv2.INTER_NEAREST)
    uv = pixel_centers(h, w)
    rays = np.stack([(uv[..., 0] - cam_k.cx) / cam_k.fx, (uv[..., 1] - cam_k.cy) / cam_k.fy, np.ones((h, w))], -1)
    world = (rays * depth[..., None] - poses[k][:, 3]) @ poses[k][:, :3]
    pc = world @ poses[j][:, :3].T + poses[j][:, 3]
    z = pc[..., 2]
    ok = (depth > 0) & (conf >= small.options.min_depth_conf) & (z > 1e-9)
    safe = np.where(ok, z, 1.0)
    x = cam_j.fx * pc[..., 0] / safe + cam_j.cx - 0.5  # COLMAP's pixel rule -> OpenCV indices
    y = cam_j.fy * pc[..., 1] / safe + cam_j.cy - 0.5
    hj, wj = small.photo(j).shape
    ok &= (x >= 0) & (x <= wj - 1) & (y >= 0) & (y <= hj - 1)
    overlap = float(ok.mean())
    if ok.sum() < 16:
        return float("nan"), overlap
    warped = cv2.remap(small.photo(j), x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR)
    a, b = grey_k[ok] - grey_k[ok].mean(), warped[ok] - warped[ok].mean()
    den = float(np.sqrt((a @ a) * (b @ b)))
    return (float(a @ b) / den if den > 1e-9 else float("nan")), overlap


def _best(small: _Small, poses: np.ndarray, k: int, others: Sequence[int]) -> PhotometricScore:
    names = small.prediction.names
    best = PhotometricScore(float("nan"), None, 0.0)
    for j in others:
        if j == k:
            continue
        score, overlap = _warp_score(small, poses, k, j)
        if overlap >= small.options.min_overlap and np.isfinite(score) and not best.score >= score:
            best = PhotometricScore(score, names[j], overlap)
    return best


def photometric_check(
    read: Callable[[int], np.ndarray],
    prediction: Prediction,
    cam_from_world: np.ndarray,
    confirmed: Sequence[int],
    checked: Sequence[int],
    options: PhotometricOptions = PhotometricOptions(),
) -> PhotometricCheck | None:
    """Score the frames ``checked`` against the ``confirmed`` ones (see the module docstring).

    Args:
        read: frame index -> ``[H, W, 3]`` uint8 RGB photo.
        prediction: the model's depth and intrinsics (its poses are not used).
        cam_from_world: ``[N, 3, 4]`` the final cameras, in the prediction's world (depth's scale).
    Returns:
        None when it cannot judge (disabled, no depth, too few confirmed frames scoring).
    """
    if not options.enabled or not checked or len(confirmed) < options.min_reference or prediction.depth is None:
        return None
    small = _Small(read, prediction, options)
    reference = [_best(small, cam_from_world, c, confirmed).score for c in confirmed]
    reference = [r for r in reference if np.isfinite(r)]
    if len(reference) < options.min_reference:
        return None
    median = float(np.median(reference))
    scores = {prediction.names[k]: _best(small, cam_from_world, k, confirmed) for k in checked}
    return PhotometricCheck(median, scores, options.ratio * median)
