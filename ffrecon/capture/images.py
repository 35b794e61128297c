"""Loading photos strictly: formats, bit depths, alpha, EXIF orientation and focal length, the size cap.

Pixels are decoded by OpenCV (it reads 16-bit and float TIFF/PNG that Pillow cannot); EXIF is read by
Pillow. OpenCV's ``IMREAD_UNCHANGED`` ignores the EXIF orientation, so it is applied here, once.

Strict decoding, chosen by measurement (OpenCV 5.0, Pillow 13, one 1024x768 photo cut or damaged):
OpenCV refuses a PNG cut short, without IEND or with a bad chunk CRC, a truncated TIFF, WebP or BMP
(``imread`` returns None), but decodes a JPEG cut anywhere, even in half, filling the rest grey with
only a warning on stderr. So JPEGs are also decoded by Pillow at 1/8 scale (``draft``: the whole
entropy-coded stream is read, the inverse DCT is cheap), which raises "image file is truncated" for
any cut; this costs 2 ms for 1 MP and 0.13 s for 108 MP (OpenCV's full decode: 0.48 s). Data appended
after the image (motion photos) is accepted, as by both decoders; damage inside the stream that still
decodes (zeroed bytes) is not detected by either.

Frames larger than the cap are area-averaged (``cv2.INTER_AREA``) to it right after decoding, before
any colour conversion, so the full-size array is the only large one and is freed at once.
OpenCV's ``IMREAD_REDUCED_*`` flags (JPEG decoded at 1/2, 1/4, 1/8 by the DCT) would avoid the full
decode, but they are not an area average: on a 4096x3072 mosaic of real photos reduced to 1600 px,
the 1/2 decode followed by INTER_AREA differs from the full decode followed by INTER_AREA by 1.4 grey
levels on average and up to 46, so they are not used.
"""

from __future__ import annotations

import contextlib
import logging
import math
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageFile, UnidentifiedImageError

from ffrecon.errors import InputError, ResourceError
from ffrecon.types import capped_size

log = logging.getLogger("ffrecon.capture")

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp", ".bmp")
VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")
OPENCV_MAX_PIXELS = 1 << 30  # OpenCV refuses to decode larger images (its CV_IO_MAX_IMAGE_PIXELS default)
_EXIF_IFD = 0x8769
_TAG_ORIENTATION = 0x0112
_TAG_FOCAL_35MM = 0xA405
_TAG_FOCAL_MM = 0x920A
_TAG_FPLANE_XRES = 0xA20E
_TAG_FPLANE_UNIT = 0xA210
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # EXIF resolution units in mm
_JPEG_FORMATS = ("JPEG", "MPO")  # MPO: a multi-picture JPEG (some cameras); both decoders read its first image

# The smallest frames every stage accepts, measured (OpenCV 5.0): dense evidence's DIS optical flow (medium
# preset) raises below 8 px on a side, raises or crashes the process (segmentation fault) for short sides of
# 8 to 15 px once the long side is 48 px or more, and runs on every size with a short side of 16 px (up to
# 20000 px long). SIFT (pycolmap) and the models' preprocessing take any such size; the models' resizing
# needs the short side at least one patch once the long side is scaled to the network's: DUSt3R's (512 px,
# 16-px patches) refuses photos more than 32 times as long as wide, VGGT's (518 px, rounded to 14) more
# than 74. Frames are checked at the size they are captured at (after --max-image-size).
MIN_FRAME_SIDE = 16  # px, the short side of a frame
MAX_FRAME_ASPECT = 32  # long side over short side
# EXIF focal lengths outside this range, in multiples of the photo's diagonal, are ignored (as if absent):
# real lenses span about 0.18x (an 8 mm-equivalent fisheye) to 67x (a 3000 mm-equivalent superzoom, the
# longest made); corrupt EXIF gives values far outside (1.2e6 px and 1.7e14 px seen on 640-px photos).
PLAUSIBLE_FOCAL_DIAGONALS = (0.1, 100.0)


def list_images(folder: Path) -> tuple[list[Path], list[Path]]:
    """Image files in ``folder`` (sorted by name) and other visible files found there."""
    if not folder.is_dir():
        raise InputError(f"not a folder: {folder}", "pass a folder of images or a video file")
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    images = [p for p in files if p.suffix.lower() in IMAGE_EXTENSIONS]
    others = [p for p in files if p.suffix.lower() not in IMAGE_EXTENSIONS]
    return images, others


def broken_links(folder: Path) -> list[Path]:
    """Visible symbolic links in ``folder`` whose target does not exist (sorted by name)."""
    return sorted(p for p in folder.iterdir() if p.is_symlink() and not p.exists() and not p.name.startswith("."))


@dataclass(frozen=True)
class Photo:
    """One decoded photo, upright, at most the cap on its long side."""

    rgb: np.ndarray  # [H, W, 3] uint8 RGB, upright
    focal_prior_px: float | None  # EXIF focal length in pixels of ``rgb`` (scaled with it), or None
    converted: bool  # the pixels differ from the file's own (orientation, bit depth, alpha, gray, size)
    original_size_wh: tuple[int, int]  # upright size of the file's pixels

    @property
    def scale(self) -> float:
        """Long side of ``rgb`` over the file's long side: 1.0 when kept at full size."""
        return max(self.rgb.shape[:2]) / max(self.original_size_wh)


@dataclass(frozen=True)
class _Header:
    """What Pillow reads without decoding the pixels (``size_wh`` None where Pillow cannot read the file,
    e.g. float TIFF, which OpenCV decodes), and the strict check's verdict (``problem``)."""

    size_wh: tuple[int, int] | None  # as stored, before the EXIF orientation
    bands: int
    mode: str | None = None  # Pillow's mode ("RGB", "CMYK", "P", "L", "I;16", ...)
    orientation: int = 1
    focal_35mm: float | None = None
    focal_px: float | None = None
    problem: str | None = None


@contextlib.contextmanager
def _strict_pillow() -> Iterator[None]:
    """Pillow raising on truncated files, quiet (ffrecon reports the problems it finds), and without its
    decompression-bomb limit (it warns above 89 MP and refuses 179 MP; ffrecon bounds the decode itself,
    see :func:`_check_decode_memory`)."""
    truncated, limit = ImageFile.LOAD_TRUNCATED_IMAGES, Image.MAX_IMAGE_PIXELS
    ImageFile.LOAD_TRUNCATED_IMAGES, Image.MAX_IMAGE_PIXELS = False, None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "Corrupt EXIF data", DecompressionBombWarning
            yield
    finally:
        ImageFile.LOAD_TRUNCATED_IMAGES, Image.MAX_IMAGE_PIXELS = truncated, limit


@contextlib.contextmanager
def _quiet_opencv() -> Iterator[None]:
    """OpenCV's own log silenced (a truncated TIFF or BMP logs errors on stderr before imread returns None)."""
    previous = cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(previous)


def _completeness_problem(path: Path) -> str | None:
    """Why Pillow finds ``path`` cut short or corrupt, or None: a JPEG is decoded at 1/8 scale (the whole
    entropy-coded stream is read), a PNG's chunks are walked to IEND with their CRCs checked (``verify``,
    no decoding; OpenCV would refuse such a PNG too, but libpng prints on stderr first). Other formats:
    None (OpenCV refuses them when broken). Raises Pillow's errors for files it cannot identify."""
    with Image.open(path) as img:
        try:
            if img.format in _JPEG_FORMATS:
                img.draft(None, (max(1, img.width // 8), max(1, img.height // 8)))
                img.load()
            elif img.format == "PNG":
                img.verify()
        except (OSError, ValueError, SyntaxError, EOFError) as err:  # Pillow's "image file is truncated" and kin
            return str(err) or type(err).__name__
    return None


def _read_header(path: Path, *, strict: bool) -> _Header:
    """EXIF and size from Pillow, and with ``strict`` its completeness check (:func:`_completeness_problem`)."""
    try:
        with _strict_pillow():
            problem = _completeness_problem(path) if strict else None
            if problem:
                return _Header(None, 0, problem=problem)
            with Image.open(path) as img:
                exif = Image.Exif() if _png_without_late_exif(img, path) else img.getexif()
                sub = exif.get_ifd(_EXIF_IFD)
                f_mm, xres, unit = sub.get(_TAG_FOCAL_MM), sub.get(_TAG_FPLANE_XRES), sub.get(_TAG_FPLANE_UNIT, 2)
                f35 = sub.get(_TAG_FOCAL_35MM)
                orientation = int(exif.get(_TAG_ORIENTATION, 1) or 1)
                size_wh, bands, mode = img.size, len(img.getbands()), img.mode
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, EOFError):
        return _Header(None, 0)
    f_px = None
    if f_mm and xres and unit in _UNIT_MM and float(xres) > 0:
        f_px = float(f_mm) * float(xres) / _UNIT_MM[unit]
    return _Header(size_wh, bands, mode, orientation, float(f35) if f35 else None, f_px)


def _png_without_late_exif(img: Image.Image, path: Path) -> bool:
    """Whether ``img`` is a PNG with no eXIf chunk at all. Pillow's ``getexif`` decodes a whole PNG to look for one
    after the image data (0.9 s of the capture at 96 frames of 640x480, the photos decoded once more for the
    pixels); the chunks' names and lengths say it without decoding. An eXIf chunk before the image data is in
    ``img.info`` already. Anything unexpected (a short or odd file): False, and Pillow looks as before."""
    if img.format != "PNG" or "exif" in img.info:
        return False
    try:
        with open(path, "rb") as fh:
            if fh.read(8) != b"\x89PNG\r\n\x1a\n":
                return False
            while len(head := fh.read(8)) == 8:
                length, kind = int.from_bytes(head[:4], "big"), head[4:]
                if kind == b"eXIf":
                    return False
                if kind == b"IEND":
                    return True
                fh.seek(length + 4, 1)  # the data and its CRC
    except OSError:
        return False
    return False


def read_exif(path: Path) -> tuple[int, float | None, float | None]:
    """``(orientation, focal_35mm_equivalent_mm, focal_mm_per_pixel_based)`` from EXIF.

    The third value is the focal length in *pixels* computed from FocalLength and the focal-plane
    resolution when both exist (independent of the 35 mm table), else None.
    """
    header = _read_header(path, strict=False)
    return header.orientation, header.focal_35mm, header.focal_px


def focal_prior_px(
    width: int, height: int, focal_35mm: float | None, focal_px_exif: float | None, *, name: str = "a photo"
) -> float | None:
    """Focal length in pixels of an upright image from EXIF, or None.

    A 35 mm-equivalent focal length refers to a 36 mm wide frame, matched to the long image side. The
    focal length from the focal-plane resolution comes first; a value outside
    :data:`PLAUSIBLE_FOCAL_DIAGONALS` is ignored, as if absent, with a warning naming ``name``.

    >>> round(focal_prior_px(4000, 3000, 26.0, None), 3)
    2888.889
    >>> focal_prior_px(640, 480, None, 1.17e6) is None  # 1460 times the diagonal: corrupt EXIF
    True
    """
    candidates = (
        (focal_px_exif, "FocalLength and FocalPlaneXResolution"),
        (focal_35mm and focal_35mm / 36.0 * max(width, height), "FocalLengthIn35mmFilm"),
    )
    low, high = (k * math.hypot(width, height) for k in PLAUSIBLE_FOCAL_DIAGONALS)
    ignored = []
    found = None
    for value, tags in candidates:
        if not value:
            continue
        if low <= value <= high:  # NaN fails too
            found = float(value)
            break
        ignored.append(f"{value:.4g} px (from {tags})")
    if ignored:
        log.warning(
            "%s: EXIF focal length %s outside %.0f-%.0f px (%g-%gx the diagonal): ignored",
            name,
            " and ".join(ignored),
            low,
            high,
            *PLAUSIBLE_FOCAL_DIAGONALS,
        )
    return found


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


def _check_decode_memory(path: Path, header: _Header) -> None:
    """Refuse, before decoding, a photo whose full-size decode cannot fit (OpenCV's limit or free memory).

    Up to 8 bytes a pixel for the decoded array (16-bit RGBA), 40 more while RGBA is composited in float32.
    """
    from ffrecon.machine import available_memory_bytes

    if header.size_wh is None:
        return
    w, h = header.size_wh
    if w * h > OPENCV_MAX_PIXELS:
        raise InputError(
            f"{path.name} is {w}x{h} ({w * h / 1e6:.0f} MP), "
            f"more than OpenCV decodes ({OPENCV_MAX_PIXELS / 1e6:.0f} MP)",
            f"downscale it first (e.g. `convert {path.name} -resize 8000x8000 smaller.jpg`), or leave it out",
        )
    need = w * h * (8 + (40 if header.bands == 4 else 0))
    available = available_memory_bytes()
    if need > available:
        raise ResourceError(
            f"decoding {path.name} ({w}x{h}) needs about {need / 2**30:.1f} GB; {available / 2**30:.1f} GB is free",
            "free memory (close other programs), or downscale the photo first",
        )


def frame_size_problem(name: str, size_wh: tuple[int, int], original_wh: tuple[int, int] | None = None) -> str | None:
    """Why a frame of ``size_wh`` (as captured: after the size cap; ``original_wh`` before it) is too small
    or too elongated for some stage (:data:`MIN_FRAME_SIDE`, :data:`MAX_FRAME_ASPECT`), or None.

    >>> frame_size_problem("a.png", (8, 8))
    'a.png is 8x8 px; every stage needs frames of at least 16 px on the short side'
    """
    w, h = size_wh
    was = "" if original_wh is None or tuple(original_wh) == (w, h) else f" (from {original_wh[0]}x{original_wh[1]})"
    if min(w, h) < MIN_FRAME_SIDE:
        return f"{name} is {w}x{h} px{was}; every stage needs frames of at least {MIN_FRAME_SIDE} px on the short side"
    if max(w, h) > MAX_FRAME_ASPECT * min(w, h):
        return (
            f"{name} is {w}x{h} px{was}, {max(w, h) / min(w, h):.0f} times as long as wide; "
            f"the models take frames at most {MAX_FRAME_ASPECT} times as long as wide"
        )
    return None


def _unreadable(path: Path) -> str | None:
    """Why ``path`` cannot be opened for reading (permissions, I/O error), or None."""
    try:
        with path.open("rb") as f:
            f.read(1)
    except OSError as err:
        return err.strerror or str(err)
    return None


def load_photo(path: Path, *, max_size: int | None = None) -> Photo:
    """Read one photo strictly, upright, its long side capped at ``max_size`` pixels (None or 0: full size).

    Raises :class:`InputError` naming the file for one that cannot be read, is cut short (truncated
    JPEG) or cannot be decoded; :class:`ResourceError` when its decode would not fit in memory.
    """
    path = Path(path)
    fix = f"remove or replace {path}, or pass --skip-bad-images to leave it out"
    reason = _unreadable(path)
    if reason:
        raise InputError(f"cannot read {path.name} ({reason})", fix)
    header = _read_header(path, strict=True)
    if header.problem:
        raise InputError(f"{path.name} is truncated or corrupt: {header.problem}", fix)
    _check_decode_memory(path, header)
    with _quiet_opencv():
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    if raw is None or raw.size == 0:
        raise InputError(
            f"cannot decode image {path.name} (corrupt, truncated or not really a {path.suffix} file)", fix
        )
    stored_wh = (int(raw.shape[1]), int(raw.shape[0]))
    size = capped_size(*stored_wh, max_size)
    problem = frame_size_problem(path.name, size, stored_wh)
    if problem:
        raise InputError(problem, fix)
    kept = size == stored_wh
    # Copied as is only when the file already holds 8-bit RGB (Pillow's "RGB"; OpenCV decodes CMYK JPEGs and
    # palette PNGs to 3 channels too, so its array alone cannot tell), upright and at its size.
    converted = not kept or header.mode != "RGB" or raw.dtype != np.uint8 or raw.ndim == 2 or raw.shape[2] != 3
    if not kept and (raw.ndim == 2 or raw.shape[2] != 4):  # average first: the large array is freed at once
        raw = cv2.resize(raw, size, interpolation=cv2.INTER_AREA)
    rgb = _to_rgb8(raw)
    del raw
    if rgb.shape[1::-1] != size:  # RGBA: composited on white at full size first (averaging is exact after)
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    upright = _apply_orientation(rgb, header.orientation)
    original = stored_wh[::-1] if header.orientation in (5, 6, 7, 8) else stored_wh
    scale = max(size) / max(stored_wh)
    focal = focal_prior_px(
        upright.shape[1],
        upright.shape[0],
        header.focal_35mm,
        header.focal_px and header.focal_px * scale,
        name=path.name,
    )
    return Photo(upright, focal, converted or header.orientation != 1, original)


def load_image(path: Path) -> tuple[np.ndarray, float | None, bool]:
    """Read one photo at full size: ``(rgb [H, W, 3] uint8 upright, focal prior in px or None, converted)``.

    ``converted`` is True when the pixels differ from the file's own (orientation, bit depth,
    alpha, gray), so the caller must write a normalised copy for tools that read files directly.
    See :func:`load_photo` (strict decoding, the size cap).
    """
    photo = load_photo(path)
    return photo.rgb, photo.focal_prior_px, photo.converted
