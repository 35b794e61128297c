"""The model's prediction of one frame in another, shifted by the photos before the dense tracking.

The dense tracking (:mod:`ffrecon.sfm.refine.dense`) warps frame j into frame i's view through the
model's predicted map and measures what misalignment is left with optical flow. Where the model's
cameras are a few degrees off and the frames' texture is a strip along an image border (a room's
plain walls over a textured floor), that misalignment is 15-30 px and the flow does not find it: on
room seed 323 (fov 85 deg) a frame 1 deg from the truth kept 0 of 101 corners, and the verdicts then
called its camera contradicted. With the truth's map the same corners track (71 of 101).

A camera's rotation error moves every pixel it predicts in frame j by nearly the same amount
(there: a standard deviation of 1-3 px around an offset of 17-30 px), so one offset in frame j's
pixels is estimated by consensus: for a sample of frame i's corners, the patch around the corner is
searched for in the warped image within the tracking's largest shift (normalised cross-correlation,
``cv2.matchTemplate``); each peak above the correlation bar gives, through the map, the offset in
frame j that would have put the corner there; the offset most of them agree on (within a tolerance)
is the consensus. A peak that another place in the window matches nearly as well does not vote: on a
repeated pattern every period fits, and the corners would agree on a period off (held-out street seed
327, repeated tiles: the second adjustment, on such tracks, kept no frame).

This is written here rather than taken from a library because it is a vote over template matches on
the warped image (OpenCV does each search); OpenCV's ``phaseCorrelate`` was not used because it
would measure the shift in frame i's pixels, where the map's foreshortening makes it vary, and the
black borders of the warped image dominate its spectrum.
"""

from __future__ import annotations

import cv2
import numpy as np

# A patch's peak must beat the best correlation elsewhere in its window (beyond a patch's width from it) by this
# much: on a repeated pattern (tiles, windows of a facade) every period fits about as well, and a consensus of such
# peaks can be a period off. Small: on a smooth texture the correlation falls slowly around the peak (room seed 323,
# a floor strip: 0.1 left the frame without a consensus)
_UNIQUE_MARGIN = 0.02


def offset_in_other_frame(
    gray_i: np.ndarray,
    warped: np.ndarray,
    xy_map: np.ndarray,
    corners: np.ndarray,
    *,
    window_px: int,
    radius_px: int,
    min_ncc: float,
    samples: int,
    tolerance_px: float,
    min_votes: int,
) -> np.ndarray | None:
    """The consensus offset ``[2]`` (frame j's pixels) to add to ``xy_map``, or None without a consensus.

    Args:
        gray_i: ``[H, W]`` frame i; warped: frame j warped into frame i's view through ``xy_map``.
        xy_map: ``[H, W, 2]`` where frame i's pixels land in frame j (``-1`` where unknown).
        corners: ``[M, 2]`` frame i's corners inside the map, OpenCV pixel indices.
        window_px: side of the searched patch; radius_px: the farthest a peak may lie from its corner.
        min_ncc: the correlation a peak needs; samples: at most this many corners searched (spread
            over the list); tolerance_px: how close two offsets must be to agree; min_votes: the
            fewest agreeing offsets that make a consensus.
    """
    if not len(corners) or not samples:
        return None
    h, w = gray_i.shape
    half = window_px // 2
    pick = np.unique(np.linspace(0, len(corners) - 1, min(samples, len(corners))).astype(int))
    offsets = []
    for x, y in np.rint(corners[pick]).astype(int):
        if not (half <= x < w - half and half <= y < h - half) or xy_map[y, x, 0] < 0:
            continue
        x0, y0 = max(0, x - radius_px - half), max(0, y - radius_px - half)
        region = warped[y0 : min(h, y + radius_px + half + 1), x0 : min(w, x + radius_px + half + 1)]
        patch = gray_i[y - half : y + half + 1, x - half : x + half + 1]
        if region.shape[0] < window_px or region.shape[1] < window_px or float(patch.std()) < 1.0:
            continue
        score = cv2.matchTemplate(region, patch, cv2.TM_CCOEFF_NORMED)
        _, peak, _, (px, py) = cv2.minMaxLoc(score)
        if peak < min_ncc or _second_peak(score, (px, py), window_px) >= peak - _UNIQUE_MARGIN:
            continue  # too weak, or a look-alike elsewhere in the window fits nearly as well (a repeated pattern)
        px, py = x0 + px + half, y0 + py + half
        if xy_map[py, px, 0] < 0:
            continue
        offsets.append(xy_map[py, px].astype(np.float64) - xy_map[y, x])
    if len(offsets) < max(1, min_votes):
        return None
    offsets = np.asarray(offsets)
    agree = np.linalg.norm(offsets[:, None] - offsets[None], axis=2) <= tolerance_px
    best = int(agree.sum(1).argmax())
    if agree[best].sum() < min_votes:
        return None
    return offsets[agree[best]].mean(0)


def _second_peak(score: np.ndarray, at: tuple[int, int], radius: int) -> float:
    """The best correlation of ``score`` outside ``radius`` of the peak ``at`` (x, y): -1 when nothing is left."""
    rest = score.copy()
    x, y = at
    rest[max(0, y - radius) : y + radius + 1, max(0, x - radius) : x + radius + 1] = -1.0
    return float(rest.max())


def shifted_map(xy_map: np.ndarray, offset: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """``xy_map`` moved by ``offset`` in frame j (``size_wh``: frame j's size); what leaves frame j is ``-1``.

    >>> m = np.array([[[1.0, 1.0], [-1.0, -1.0], [9.5, 2.0]]], np.float32)
    >>> shifted_map(m, np.array([1.0, 0.5]), (10, 5)).tolist()
    [[[2.0, 1.5], [-1.0, -1.0], [-1.0, -1.0]]]
    """
    valid = xy_map[..., 0] >= 0
    out = np.where(valid[..., None], xy_map + offset.astype(np.float32), np.float32(-1)).astype(np.float32)
    w, h = size_wh
    outside = (out[..., 0] < 0) | (out[..., 0] > w) | (out[..., 1] < 0) | (out[..., 1] > h)
    out[outside] = -1.0
    return out
