"""Masks the user gives (``--masks FOLDER``): which pixels of each photo to ignore.

nerfstudio's and COLMAP's convention: one PNG per photo, named ``<stem>.png`` (nerfstudio) or
``<photo name>.png`` (COLMAP), 0 where the photo is to be ignored (moving objects, people, the
photographer), anything else where it is used; at the photo's size (upright). A photo without a mask is
used whole. The capture writes every frame's mask at the frame's size as ``OUT/masks/<name>.png`` (255 use,
0 ignore): COLMAP's naming, which transforms.json's ``mask_path`` also names.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ffrecon.checks import MB, check_option_folder, read_option_bytes
from ffrecon.errors import InputError
from ffrecon.types import Frame

log = logging.getLogger("ffrecon.capture")
LIMIT_BYTES = 64 * MB  # one mask PNG (a binary mask of a 100 MP photo compresses to a few MB)
FIX = "give one PNG per photo named <photo stem>.png or <photo name>.png, 0 where the photo is to be ignored"


def _mask_file(folder: Path, name: str) -> Path | None:
    for candidate in (folder / f"{name}.png", folder / f"{Path(name).stem}.png"):
        if os.path.lexists(candidate):  # a FIFO or a device too: refused when read, not taken for "no mask"
            return candidate
    return None


def _read_mask(path: Path, original_wh: tuple[int, int], size_wh: tuple[int, int]) -> np.ndarray:
    """``[H, W]`` uint8 (255 use, 0 ignore) at the frame's size; an :class:`InputError` for a bad file."""
    data = np.frombuffer(read_option_bytes("--masks", path, limit_bytes=LIMIT_BYTES, fix=FIX), np.uint8)
    mask = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if mask is None or mask.ndim not in (2, 3):
        raise InputError(f"--masks: {path} cannot be read as an image", FIX)
    if mask.ndim == 3:  # a colour or RGBA PNG: ignored where every channel is 0
        mask = mask.max(axis=2)
    h, w = mask.shape
    if (w, h) not in (tuple(original_wh), tuple(size_wh)):
        raise InputError(
            f"--masks: {path.name} is {w}x{h}, its photo {original_wh[0]}x{original_wh[1]}",
            "make each mask the size of its photo (upright, after EXIF orientation)",
        )
    keep = np.where(mask > 0, 255, 0).astype(np.uint8)
    if (w, h) != tuple(size_wh):  # the photo was downscaled at capture: so is its mask (nearest, stays binary)
        keep = cv2.resize(keep, tuple(size_wh), interpolation=cv2.INTER_NEAREST)
    return keep


def write_masks(folder: Path, frames: Sequence[Frame], originals_wh: Sequence[tuple[int, int]], out_dir: Path) -> Path:
    """Every frame's mask, as ``out_dir/<name>.png`` at the frame's size (all 255 where none was given)."""
    check_option_folder("--masks", folder, fix=FIX)
    out_dir.mkdir(parents=True, exist_ok=True)
    found = 0
    for frame, original in zip(frames, originals_wh):
        path = _mask_file(folder, frame.name)
        w, h = frame.size_wh
        keep = np.full((h, w), 255, np.uint8) if path is None else _read_mask(path, tuple(original), (w, h))
        found += path is not None
        if not cv2.imwrite(str(out_dir / f"{frame.name}.png"), keep):
            raise InputError(f"cannot write {out_dir / frame.name}.png", "check the output folder is writable")
    if found == 0:
        raise InputError(f"--masks {folder} holds no mask of these photos", FIX)
    log.info("masks: %d of %d frames have one (%s)", found, len(frames), folder)
    return out_dir
