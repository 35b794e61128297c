"""Loading photos: formats, bit depths, alpha, EXIF orientation and EXIF focal length.

Pixels are decoded by OpenCV (it reads 16-bit and float TIFF/PNG that PIL cannot); EXIF is read by
Pillow. OpenCV's ``IMREAD_UNCHANGED`` ignores the EXIF orientation, so it is applied here, once.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from ffrecon.errors import InputError

log = logging.getLogger("ffrecon.capture")

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp", ".bmp")
VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")
_EXIF_IFD = 0x8769
_TAG_ORIENTATION = 0x0112
_TAG_FOCAL_35MM = 0xA405
_TAG_FOCAL_MM = 0x920A
_TAG_FPLANE_XRES = 0xA20E
_TAG_FPLANE_UNIT = 0xA210
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # EXIF resolution units in mm


def list_images(folder: Path) -> tuple[list[Path], list[Path]]:
    """Image files in ``folder`` (sorted by name) and other visible files found there."""
    if not folder.is_dir():
        raise InputError(f"not a folder: {folder}", "pass a folder of images or a video file")
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    images = [p for p in files if p.suffix.lower() in IMAGE_EXTENSIONS]
    others = [p for p in files if p.suffix.lower() not in IMAGE_EXTENSIONS]
    return images, others


def _to_rgb8(pixels: np.ndarray) -> np.ndarray:
    """Any OpenCV-decoded array (gray, BGR, BGRA; 8/16-bit or float) to ``[H, W, 3]`` uint8 RGB."""
    arr = pixels
    if arr.dtype == np.uint16:
        arr = (arr.astype(np.float32) / 257.0).round().astype(np.uint8)
    elif arr.dtype.kind == "f":
        arr = (np.clip(np.nan_to_num(arr), 0.0, 1.0) * 255.0).round().astype(np.uint8)
    elif arr.dtype != np.uint8:
        arr = np.clip(arr, 0, 255).astype(np.uint8)
    if arr.ndim == 2:
        return cv2.cvtColor(arr, cv2.COLOR_GRAY2RGB)
    if arr.shape[2] == 4:  # composite on white, as the VGGT reference does for RGBA
        alpha = arr[..., 3:4].astype(np.float32) / 255.0
        rgb = arr[..., :3].astype(np.float32) * alpha + 255.0 * (1.0 - alpha)
        return cv2.cvtColor(rgb.round().astype(np.uint8), cv2.COLOR_BGR2RGB)
    if arr.shape[2] == 1:
        return cv2.cvtColor(arr[..., 0], cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(arr[..., :3], cv2.COLOR_BGR2RGB)


def _apply_orientation(rgb: np.ndarray, orientation: int) -> np.ndarray:
    """EXIF orientation 1..8 to upright pixels (the same result as PIL's ``exif_transpose``)."""
    ops = {
        2: lambda a: a[:, ::-1],
        3: lambda a: a[::-1, ::-1],
        4: lambda a: a[::-1],
        5: lambda a: np.swapaxes(a, 0, 1),
        6: lambda a: np.rot90(a, k=-1),
        7: lambda a: np.swapaxes(a, 0, 1)[::-1, ::-1],
        8: lambda a: np.rot90(a, k=1),
    }
    op = ops.get(orientation)
    return np.ascontiguousarray(op(rgb)) if op else rgb


def read_exif(path: Path) -> tuple[int, float | None, float | None]:
    """``(orientation, focal_35mm_equivalent_mm, focal_mm_per_pixel_based)`` from EXIF.

    The third value is the focal length in *pixels* computed from FocalLength and the focal-plane
    resolution when both exist (independent of the 35 mm table), else None.
    """
    try:
        with Image.open(path) as img:
            exif = img.getexif()
            sub = exif.get_ifd(_EXIF_IFD)
            orientation = int(exif.get(_TAG_ORIENTATION, 1) or 1)
            f35 = sub.get(_TAG_FOCAL_35MM)
            f_mm, xres, unit = sub.get(_TAG_FOCAL_MM), sub.get(_TAG_FPLANE_XRES), sub.get(_TAG_FPLANE_UNIT, 2)
    except (UnidentifiedImageError, OSError, ValueError):
        return 1, None, None
    f_px = None
    if f_mm and xres and unit in _UNIT_MM and float(xres) > 0:
        f_px = float(f_mm) * float(xres) / _UNIT_MM[unit]
    return orientation, (float(f35) if f35 else None), f_px


def focal_prior_px(width: int, height: int, focal_35mm: float | None, focal_px_exif: float | None) -> float | None:
    """Focal length in pixels of an upright image from EXIF, or None.

    A 35 mm-equivalent focal length refers to a 36 mm wide frame, matched to the long image side.

    >>> round(focal_prior_px(4000, 3000, 26.0, None), 3)
    2888.889
    """
    if focal_px_exif:
        return focal_px_exif
    if focal_35mm:
        return focal_35mm / 36.0 * max(width, height)
    return None


def load_image(path: Path) -> tuple[np.ndarray, float | None, bool]:
    """Read one photo: ``(rgb [H, W, 3] uint8 upright, focal prior in px or None, converted)``.

    ``converted`` is True when the pixels differ from the file's own (orientation, bit depth,
    alpha, gray), so the caller must write a normalised copy for tools that read files directly.
    """
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    if raw is None or raw.size == 0:
        raise InputError(
            f"cannot decode image {path.name} (corrupt, truncated or not really a {path.suffix} file)",
            f"remove or replace {path}, or pass --skip-bad-images to leave it out",
        )
    rgb = _to_rgb8(raw)
    orientation, f35, f_px = read_exif(path)
    upright = _apply_orientation(rgb, orientation)
    converted = orientation != 1 or raw.dtype != np.uint8 or raw.ndim == 2 or raw.shape[2] != 3
    focal = focal_prior_px(upright.shape[1], upright.shape[0], f35, f_px)
    return upright, focal, converted
