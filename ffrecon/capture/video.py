"""Frames from a video: a target number of frames, the sharpest of each window."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from ffrecon.capture.quality import sharpness
from ffrecon.errors import InputError

log = logging.getLogger("ffrecon.capture")


def extract_video_frames(path: Path, num_frames: int) -> list[tuple[str, np.ndarray]]:
    """Split the video into ``num_frames`` equal windows and keep the sharpest frame of each.

    Returns ``[(name, rgb [H, W, 3] uint8)]`` with names ``<stem>_<frame index:06d>.png``.
    Sharpness is the variance of the Laplacian on a downscaled grey frame (every frame is decoded
    anyway, so scoring all of them costs little beside decoding).
    """
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(
            f"cannot open video {path.name}",
            "check the file plays; re-encode it with `ffmpeg -i IN -c:v libx264 OUT.mp4` if OpenCV cannot read its codec",
        )
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or 0
    if total <= 0:
        cap.release()
        raise InputError(
            f"video {path.name} reports no frames",
            "re-encode the video (ffmpeg) or extract frames to a folder yourself",
        )
    num = min(num_frames, total)
    edges = np.linspace(0, total, num + 1).round().astype(int)
    best: list[tuple[float, int, np.ndarray | None]] = [(-1.0, -1, None)] * num
    window = 0
    for index in tqdm(range(total), desc="video frames", unit="frame", disable=None):
        ok, bgr = cap.read()
        if not ok:
            break
        while window < num - 1 and index >= edges[window + 1]:
            window += 1
        score = sharpness(bgr)
        if score > best[window][0]:
            best[window] = (score, index, bgr)
    cap.release()
    frames = [
        (f"{path.stem}_{idx:06d}.png", cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)) for _, idx, bgr in best if bgr is not None
    ]
    if not frames:
        raise InputError(
            f"no frame of {path.name} could be decoded",
            "re-encode the video (ffmpeg) or extract frames to a folder yourself",
        )
    log.info("kept %d of %d video frames (sharpest of each window)", len(frames), total)
    return frames
