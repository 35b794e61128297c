"""Frames from a video: a target number of frames, the sharpest of each window."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from ffrecon.capture.quality import edge_sharpness
from ffrecon.errors import InputError

log = logging.getLogger("ffrecon.capture")


def _open(path: Path) -> tuple[cv2.VideoCapture, int]:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(
            f"cannot open video {path.name}",
            "check the file plays; re-encode it with `ffmpeg -i IN -c:v libx264 OUT.mp4` "
            "if OpenCV cannot read its codec",
        )
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or 0
    if total <= 0:
        cap.release()
        raise InputError(
            f"video {path.name} reports no frames",
            "re-encode the video (ffmpeg) or extract frames to a folder yourself",
        )
    return cap, total


def extract_video_frames(path: Path, num_frames: int) -> Iterator[tuple[str, np.ndarray]]:
    """Split the video into ``num_frames`` equal windows and yield the sharpest frame of each.

    Yields ``(name, rgb [H, W, 3] uint8)`` with names ``<stem>_<frame index:06d>.png`` (white space in the
    stem made ``_``: COLMAP's pair lists split names on it, see :mod:`.names`), each as soon
    as its window has been read, so only one kept frame is held at a time. Sharpness is
    :func:`ffrecon.capture.quality.edge_sharpness` (every frame is decoded anyway, so scoring all of
    them costs little beside decoding). Fewer frames than asked come with a warning saying why (a
    shorter video, or decoding that stopped before the frame count the container reports).
    """
    cap, total = _open(path)
    stem = "_".join(path.stem.split()) or "frame"
    num = min(num_frames, total)
    if num < num_frames:
        log.warning("%s has only %d frames: keeping all of them, not %d (--video-frames)", path.name, total, num_frames)
    edges = np.linspace(0, total, num + 1).round().astype(int)
    best: tuple[float, int, np.ndarray | None] = (-1.0, -1, None)
    window = kept = decoded = 0
    try:
        for index in tqdm(range(total), desc="video frames", unit="frame", disable=None):
            ok, bgr = cap.read()
            if not ok:
                break
            decoded += 1
            if window < num - 1 and index >= edges[window + 1]:
                if best[2] is not None:
                    kept += 1
                    yield f"{stem}_{best[1]:06d}.png", cv2.cvtColor(best[2], cv2.COLOR_BGR2RGB)
                best = (-1.0, -1, None)
                while window < num - 1 and index >= edges[window + 1]:
                    window += 1
            score = edge_sharpness(bgr, bgr=True)
            if score > best[0]:
                best = (score, index, bgr)
    finally:
        cap.release()
    if best[2] is not None:
        kept += 1
        yield f"{stem}_{best[1]:06d}.png", cv2.cvtColor(best[2], cv2.COLOR_BGR2RGB)
    if not kept:
        raise InputError(
            f"no frame of {path.name} could be decoded",
            "re-encode the video (ffmpeg) or extract frames to a folder yourself",
        )
    if kept < num:  # windows past the last decodable frame stayed empty
        log.warning(
            "%s: decoding stopped after %d of the %d frames its container reports, so %d of the %d windows "
            "had a frame to keep; re-encode it (`ffmpeg -i IN -c:v libx264 OUT.mp4`) to keep them all",
            path.name,
            decoded,
            total,
            kept,
            num,
        )
    log.info("kept %d of %d video frames (sharpest of each window)", kept, decoded)
