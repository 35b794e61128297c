"""Capture checks that run before any expensive work: blur, texture, exposure drift, overlap.

Each frame is measured once, when it is loaded (:func:`measure_frame`); :func:`assess_capture` then
compares the frames and flags the odd ones. The checks flag; they do not stop the run (the gates
after COLMAP do that, naming blur or texture from these flags). Each flag says why.

Blur is measured as **edge sharpness**: mean |Laplacian| / mean |Sobel gradient| of the grey image.
For an edge blurred to a Gaussian profile of width ``s`` pixels it is about ``0.1 / s`` (Sobel's
3x3 kernel is 8 times a unit derivative), whatever the edge's contrast, so it separates blur from
faint texture and from exposure. Texture is the mean Sobel gradient itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from tqdm.auto import tqdm

WORK_SIDE = 640  # frames are measured downscaled (INTER_AREA) to this long side
# Light smoothing before the derivatives: without it, 8-bit rounding and sensor noise dominate the
# Laplacian of faint or blurred images and make them read as sharp (a Gaussian-blurred test pattern
# measured 0.11 against 0.09 for the sharp original).
_SMOOTH_SIGMA_PX = 1.0
_ORB_FEATURES = 1500


def working_grey(image: np.ndarray, *, bgr: bool = False) -> np.ndarray:
    """``[h, w]`` uint8 grey of an ``[H, W, 3]`` uint8 RGB (or BGR) image, long side at most 640.

    >>> working_grey(np.zeros((960, 1280, 3), np.uint8)).shape
    (480, 640)
    """
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if bgr else cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    scale = WORK_SIDE / max(grey.shape)
    if scale < 1:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return grey


def edge_measures(grey: np.ndarray) -> tuple[float, float]:
    """``(edge_sharpness, mean_gradient)`` of a ``[h, w]`` uint8 grey image at working size.

    ``mean_gradient`` is the mean Sobel gradient magnitude of the grey image scaled to [0, 1] (after
    a 1 px Gaussian); ``edge_sharpness`` is the mean |Laplacian| divided by it (low: blurred).

    >>> rng = np.random.default_rng(0)
    >>> sharp = cv2.resize(rng.integers(0, 255, (30, 40), dtype=np.uint8), (160, 120), interpolation=cv2.INTER_CUBIC)
    >>> blurred = cv2.GaussianBlur(sharp, (0, 0), 6)
    >>> [round(edge_measures(g)[0], 3) for g in (sharp, blurred, sharp // 16)]  # faint but sharp stays sharp
    [0.08, 0.027, 0.081]
    """
    g = cv2.GaussianBlur(grey.astype(np.float32) / 255.0, (0, 0), _SMOOTH_SIGMA_PX)
    gradient = float(np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)).mean())
    laplacian = float(np.abs(cv2.Laplacian(g, cv2.CV_32F)).mean())
    return laplacian / max(gradient, 1e-6), gradient


def edge_sharpness(image: np.ndarray, *, bgr: bool = False) -> float:
    """Edge sharpness (see :func:`edge_measures`) of an ``[H, W, 3]`` uint8 RGB or BGR image."""
    return edge_measures(working_grey(image, bgr=bgr))[0]


@dataclass(frozen=True)
class FrameMeasures:
    """What the capture checks need from one frame, measured once at load time at working size."""

    edge_sharpness: float  # mean |Laplacian| / mean |Sobel gradient|; ~0.1 / edge width in px; low = blurred
    mean_gradient: float  # mean Sobel gradient magnitude of grey in [0, 1]; low = textureless
    brightness: float  # mean grey level, 0..255
    keypoints_xy: np.ndarray = field(repr=False)  # [K, 2] float32 ORB keypoints, working-size pixels
    descriptors: np.ndarray = field(repr=False)  # [K, 32] uint8 ORB descriptors


def measure_frame(rgb: np.ndarray) -> FrameMeasures:
    """Blur, texture, brightness and ORB features of one ``[H, W, 3]`` uint8 RGB frame."""
    grey = working_grey(rgb)
    sharpness, gradient = edge_measures(grey)
    keypoints, descriptors = cv2.ORB_create(nfeatures=_ORB_FEATURES).detectAndCompute(grey, None)
    xy = np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2)
    descriptors = np.zeros((0, 32), np.uint8) if descriptors is None else descriptors
    return FrameMeasures(sharpness, gradient, float(grey.mean()), xy, descriptors)


@dataclass(frozen=True, kw_only=True)
class QualityOptions:
    min_edge_sharpness: float = 0.05  # flag "blur" below this (edges wider than ~2 px at working size)...
    blur_relative: float = 0.6  # ...or below this fraction of the capture's median edge sharpness
    min_gradient: float = 0.05  # flag "texture" below this mean gradient (unless already flagged "blur")
    exposure_stops: float = 0.8  # flag mean brightness this many stops from the median
    min_overlap_matches: int = 40  # flag a frame whose best neighbour shares fewer ORB inliers
    overlap_neighbours: int = 2


@dataclass(frozen=True)
class FrameFlag:
    name: str
    kind: str  # "blur", "texture", "exposure" or "overlap"
    value: float
    message: str


@dataclass(frozen=True)
class CaptureQuality:
    """Per-frame measures (in capture order) and the flags raised on them."""

    names: tuple[str, ...]
    edge_sharpness: tuple[float, ...]  # see FrameMeasures
    mean_gradient: tuple[float, ...]  # see FrameMeasures
    brightness_stops: tuple[float, ...]  # log2(mean / median mean)
    # ORB inliers with the best nearby frame matched (-1: single frame); at least min_overlap_matches where it is
    # reached (farther neighbours are then not matched: _best_neighbour_matches)
    best_neighbour_matches: tuple[int, ...]
    flags: tuple[FrameFlag, ...] = field(default=())

    def flagged(self, kind: str) -> list[str]:
        return [f.name for f in self.flags if f.kind == kind]

    def to_report(self) -> dict:
        return {
            "edge_sharpness": list(self.edge_sharpness),
            "mean_gradient": list(self.mean_gradient),
            "brightness_stops": list(self.brightness_stops),
            "best_neighbour_matches": list(self.best_neighbour_matches),
            "flags": [{"name": f.name, "kind": f.kind, "value": f.value, "message": f.message} for f in self.flags],
        }


def _orb_inliers(a: FrameMeasures, b: FrameMeasures, matcher: cv2.BFMatcher) -> int:
    if len(a.descriptors) < 8 or len(b.descriptors) < 8:
        return 0
    pairs = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    good = [m for m, *rest in pairs if rest and m.distance < 0.8 * rest[0].distance]
    if len(good) < 8:
        return len(good)
    pa = a.keypoints_xy[[m.queryIdx for m in good]]
    pb = b.keypoints_xy[[m.trainIdx for m in good]]
    _, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 2.0, 0.999)
    return int(mask.sum()) if mask is not None else 0


def _best_neighbour_matches(measures: Sequence[FrameMeasures], neighbours: int, enough: int | None = None) -> list[int]:
    """ORB + fundamental-matrix RANSAC inliers of each frame with its best of ``neighbours`` each side.

    Each pair is matched once, its inliers counting for both frames: matching both ways doubled the work (96
    frames of 640x480 on the 2-core machine: 4.3-4.4 CPU s both ways, 2.2 once). OpenCV's matcher already uses
    the cores: running the pairs in threads as well measured no faster (3.2-3.4 s wall either way, load 5).
    Nearest pairs first; with ``enough``, a pair whose two frames already share that many inliers with a nearer
    neighbour is not matched (the check only asks whether a frame reaches the bar): a frame's count is then the
    best of the pairs matched, at least ``enough``. On ordered captures that halves the work."""
    n = len(measures)
    pairs = [(i, i + gap) for gap in range(1, neighbours + 1) for i in range(n - gap)]
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    best = [-1] * n
    for i, j in tqdm(pairs, desc="capture overlap check", unit="pair", disable=None if pairs else True):
        if enough is not None and min(best[i], best[j]) >= enough:
            continue
        count = _orb_inliers(measures[i], measures[j], matcher)
        best[i], best[j] = max(best[i], count), max(best[j], count)
    return best


def _blur_or_texture_flag(name: str, m: FrameMeasures, median_sharpness: float, options: QualityOptions):
    """A "blur" flag, else a "texture" flag, else None (blur also lowers the gradient, so it comes first)."""
    limit = max(options.min_edge_sharpness, options.blur_relative * median_sharpness)
    if m.edge_sharpness < limit:
        return FrameFlag(
            name,
            "blur",
            m.edge_sharpness,
            f"{name} looks blurred (edge sharpness {m.edge_sharpness:.3f}, median {median_sharpness:.3f}, "
            f"flagged below {limit:.3f}): retake it or drop it",
        )
    if m.mean_gradient < options.min_gradient:
        return FrameFlag(
            name,
            "texture",
            m.mean_gradient,
            f"{name} shows little texture (mean gradient {m.mean_gradient:.3f} < {options.min_gradient:g}): "
            "feature matching may fail on it; include textured surfaces in the view or light the scene evenly",
        )
    return None


def assess_capture(
    names: Sequence[str], measures: Sequence[FrameMeasures], options: QualityOptions = QualityOptions()
) -> CaptureQuality:
    """Compare the frames' measures; flag blur, lack of texture, exposure drift and too little overlap.

    A frame is blurred when its edge sharpness is under ``min_edge_sharpness`` or, with more than one
    frame, under ``blur_relative`` times the median. Overlap is checked against the
    ``overlap_neighbours`` frames before and after in input order (capture order for videos and most
    photo sets) with ORB + fundamental-matrix RANSAC.
    """
    if len(names) != len(measures):
        raise ValueError(f"{len(names)} names but {len(measures)} measured frames")
    n = len(measures)
    sharp = np.array([m.edge_sharpness for m in measures])
    bright = np.array([max(m.brightness, 1.0) for m in measures])
    stops = np.log2(bright / np.median(bright))
    best = _best_neighbour_matches(measures, options.overlap_neighbours, options.min_overlap_matches)
    median_sharpness = float(np.median(sharp)) if n > 1 else 0.0
    flags = []
    for k, name in enumerate(names):
        flag = _blur_or_texture_flag(name, measures[k], median_sharpness, options)
        flags += [flag] if flag is not None else []
        if abs(stops[k]) > options.exposure_stops:
            message = f"{name} is {stops[k]:+.1f} stops from the median exposure: lock exposure while capturing"
            flags.append(FrameFlag(name, "exposure", float(stops[k]), message))
        if n > 1 and best[k] < options.min_overlap_matches:
            message = (
                f"{name} shares only {best[k]} feature matches with its neighbours: "
                "capture more views between it and the others"
            )
            flags.append(FrameFlag(name, "overlap", float(best[k]), message))
    return CaptureQuality(
        tuple(names),
        tuple(sharp.tolist()),
        tuple(m.mean_gradient for m in measures),
        tuple(stops.tolist()),
        tuple(best),
        tuple(flags),
    )
