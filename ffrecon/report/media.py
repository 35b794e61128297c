"""Moving pictures for the report: a video file turned into an animated WebP that an <img> tag plays.

The report embeds an animated image rather than ``flythrough.mp4`` itself because OpenCV's pip wheels
write MPEG-4 Part 2 (``mp4v``), which browsers do not decode; an animated WebP plays in every current
browser, inline and offline, at a tenth of the size of a GIF.
"""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

MAX_FRAMES = 48  # every k-th frame of a longer video, so the report stays small
MAX_SIDE = 360  # pixels, long side


def video_frames(path: Path, max_frames: int = MAX_FRAMES, max_side: int = MAX_SIDE) -> tuple[list[np.ndarray], float]:
    """``(frames [H, W, 3] uint8 RGB, frames per second)`` read from ``path``, evenly thinned to at most
    ``max_frames`` and shrunk to ``max_side``; ``([], 0.0)`` when OpenCV cannot read it.

    The frame count is bounded even when the container's is wrong: reading stops after
    ``max_frames * 64`` frames.
    """
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        return [], 0.0
    fps = capture.get(cv2.CAP_PROP_FPS) or 24.0
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or max_frames
    step = max(1, int(np.ceil(total / max_frames)))
    frames = []
    for index in range(max_frames * 64):
        ok, bgr = capture.read()
        if not ok or len(frames) >= max_frames:
            break
        if index % step:
            continue
        scale = min(1.0, max_side / max(bgr.shape[:2]))
        if scale < 1.0:
            bgr = cv2.resize(bgr, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        frames.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    capture.release()
    return frames, fps / step


def animated_webp(frames: list[np.ndarray], fps: float, quality: int = 70) -> bytes:
    """An endlessly looping animated WebP of ``frames`` (``[H, W, 3]`` uint8 RGB) at ``fps``.

    >>> data = animated_webp([np.zeros((8, 8, 3), np.uint8), np.full((8, 8, 3), 255, np.uint8)], 2.0)
    >>> data[:4], data[8:12]
    (b'RIFF', b'WEBP')
    """
    images = [Image.fromarray(f) for f in frames]
    buf = io.BytesIO()
    duration = int(round(1000.0 / max(fps, 1e-3)))
    first, rest = images[0], images[1:]
    first.save(buf, format="WEBP", save_all=True, append_images=rest, duration=duration, loop=0, quality=quality)
    return buf.getvalue()
