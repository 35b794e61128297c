"""Capture checks that run before any expensive work: blur, exposure drift, overlap.

They flag; they do not stop the run (the gates after COLMAP do that). Each flag says why.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

_WORK_SIDE = 640  # checks run on images downscaled to this long side


def _gray_small(image: np.ndarray, bgr: bool = False) -> np.ndarray:
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if bgr else cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    scale = _WORK_SIDE / max(gray.shape)
    if scale < 1:
        gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return gray


def sharpness(image: np.ndarray, bgr: bool = True) -> float:
    """Variance of the Laplacian of the downscaled grey image (higher is sharper)."""
    return float(cv2.Laplacian(_gray_small(image, bgr), cv2.CV_32F).var())


@dataclass(frozen=True, kw_only=True)
class QualityOptions:
    blur_ratio: float = 0.35  # flag frames sharper than this fraction of the median sharpness...
    blur_absolute: float = 15.0  # ...or under this absolute Laplacian variance
    exposure_stops: float = 0.8  # flag mean brightness this many stops from the median
    min_overlap_matches: int = 40  # flag a frame whose best neighbour shares fewer ORB inliers
    overlap_neighbours: int = 2


@dataclass(frozen=True)
class FrameFlag:
    name: str
    kind: str  # "blur", "exposure" or "overlap"
    value: float
    message: str


@dataclass(frozen=True)
class CaptureQuality:
    sharpness: tuple[float, ...]
    brightness_stops: tuple[float, ...]  # log2(mean / median mean)
    best_neighbour_matches: tuple[int, ...]  # ORB inliers with the best nearby frame (-1: single frame)
    flags: tuple[FrameFlag, ...] = field(default=())

    def flagged(self, kind: str) -> list[str]:
        return [f.name for f in self.flags if f.kind == kind]

    def to_report(self) -> dict:
        return {
            "sharpness": list(self.sharpness),
            "brightness_stops": list(self.brightness_stops),
            "best_neighbour_matches": list(self.best_neighbour_matches),
            "flags": [{"name": f.name, "kind": f.kind, "value": f.value, "message": f.message} for f in self.flags],
        }


def _orb_inliers(a: tuple, b: tuple, matcher: cv2.BFMatcher) -> int:
    (kp_a, des_a), (kp_b, des_b) = a, b
    if des_a is None or des_b is None or len(kp_a) < 8 or len(kp_b) < 8:
        return 0
    pairs = matcher.knnMatch(des_a, des_b, k=2)
    good = [m for m, *rest in pairs if rest and m.distance < 0.8 * rest[0].distance]
    if len(good) < 8:
        return len(good)
    pa = np.float32([kp_a[m.queryIdx].pt for m in good])
    pb = np.float32([kp_b[m.trainIdx].pt for m in good])
    _, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 2.0, 0.999)
    return int(mask.sum()) if mask is not None else 0


def assess_capture(
    names: Sequence[str], images: Sequence[np.ndarray], options: QualityOptions = QualityOptions()
) -> CaptureQuality:
    """Score every frame; flag blur, exposure drift and frames with too little overlap.

    Overlap is checked against the ``overlap_neighbours`` frames before and after in input order
    (capture order for videos and most photo sets) with ORB + fundamental-matrix RANSAC.
    """
    grays = [_gray_small(img) for img in images]
    sharp = np.array([float(cv2.Laplacian(g, cv2.CV_32F).var()) for g in grays])
    bright = np.array([max(float(g.mean()), 1.0) for g in grays])
    stops = np.log2(bright / np.median(bright))
    orb = cv2.ORB_create(nfeatures=1500)
    feats = [orb.detectAndCompute(g, None) for g in grays]
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    n = len(images)
    best = [-1] * n
    for i in range(n):
        for j in range(max(0, i - options.overlap_neighbours), min(n, i + options.overlap_neighbours + 1)):
            if j != i:
                best[i] = max(best[i], _orb_inliers(feats[i], feats[j], matcher))
    flags = []
    med = float(np.median(sharp))
    for k, name in enumerate(names):
        if n > 1 and sharp[k] < options.blur_ratio * med or sharp[k] < options.blur_absolute:
            flags.append(
                FrameFlag(
                    name,
                    "blur",
                    float(sharp[k]),
                    f"{name} looks blurred (sharpness {sharp[k]:.1f}, median {med:.1f}): retake it or drop it",
                )
            )
        if abs(stops[k]) > options.exposure_stops:
            flags.append(
                FrameFlag(
                    name,
                    "exposure",
                    float(stops[k]),
                    f"{name} is {stops[k]:+.1f} stops from the median exposure: lock exposure while capturing",
                )
            )
        if n > 1 and best[k] < options.min_overlap_matches:
            flags.append(
                FrameFlag(
                    name,
                    "overlap",
                    float(best[k]),
                    f"{name} shares only {best[k]} feature matches with its neighbours: capture more views between it and the others",
                )
            )
    return CaptureQuality(tuple(sharp.tolist()), tuple(stops.tolist()), tuple(best), tuple(flags))
