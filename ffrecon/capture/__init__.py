"""Capture: load photos or video frames and check them before any expensive work."""

from __future__ import annotations

import logging
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from ffrecon.capture.images import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, list_images, load_image
from ffrecon.capture.quality import CaptureQuality, FrameMeasures, QualityOptions, assess_capture, measure_frame
from ffrecon.capture.video import extract_video_frames
from ffrecon.errors import FFReconError, InputError
from ffrecon.types import Frame

log = logging.getLogger("ffrecon.capture")


@dataclass(frozen=True, kw_only=True)
class CaptureOptions:
    video_frames: int = 48  # frames kept from a video
    skip_bad_images: bool = False  # leave out unreadable files and non-images instead of stopping
    max_images: int | None = None  # keep at most this many (evenly spaced), None for all
    quality: QualityOptions = field(default_factory=QualityOptions)


@dataclass(frozen=True)
class Capture:
    """The loaded frames (paths and sizes, no pixels: see :meth:`read_images`) and their quality checks."""

    frames: tuple[Frame, ...]
    image_dir: Path  # OUT/images: every frame under its name; COLMAP and transforms.json read these
    source: Path
    is_video: bool
    skipped: tuple[tuple[str, str], ...]  # (file name, reason)
    quality: CaptureQuality

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.frames)

    def read_images(self, indices: Sequence[int] | None = None) -> list[np.ndarray]:
        """``[H_i, W_i, 3]`` uint8 RGB upright images of the frames at ``indices`` (all by default), read from disk."""
        chosen = range(len(self.frames)) if indices is None else indices
        return [self.frames[i].read_rgb() for i in chosen]

    def to_report(self) -> dict:
        return {
            "source": str(self.source),
            "kind": "video" if self.is_video else "images",
            "num_frames": len(self.frames),
            "names": list(self.names),
            "sizes_wh": [list(f.size_wh) for f in self.frames],
            "focal_prior_px": [f.focal_prior_px for f in self.frames],
            "skipped": [{"name": n, "reason": r} for n, r in self.skipped],
            "quality": self.quality.to_report(),
        }


DATASET_DOCUMENTS = frozenset({"license", "licence", "readme", "copying", "credits", "attribution", "authors"})


def _list_inputs(folder: Path, options: CaptureOptions) -> tuple[list[Path], list[tuple[str, str]]]:
    """The image files to load (at most ``max_images``, evenly spaced) and the files left out, with why."""
    paths, others = list_images(folder)
    # A dataset's license and readme files travel with its photos: leave them out, and say so.
    docs = [p for p in others if p.stem.lower() in DATASET_DOCUMENTS]
    others = [p for p in others if p not in docs]
    skipped: list[tuple[str, str]] = [(p.name, "a dataset's documentation, not an image") for p in docs]
    for p in docs:
        log.info("leaving out %s (a dataset's documentation, not an image)", p.name)
    if others:
        listed = ", ".join(p.name for p in others[:5]) + (" ..." if len(others) > 5 else "")
        if not options.skip_bad_images:
            raise InputError(
                f"{folder} holds {len(others)} file(s) that are not images ({listed}); "
                f"supported: {', '.join(IMAGE_EXTENSIONS)}",
                "move them out of the folder, or pass --skip-bad-images to leave them out",
            )
        skipped += [(p.name, "not an image") for p in others]
    if not paths:
        raise InputError(
            f"no images found in {folder}",
            f"put photos ({', '.join(IMAGE_EXTENSIONS)}) in the folder, or pass a video file",
        )
    if options.max_images and len(paths) > options.max_images:
        step = len(paths) / options.max_images
        paths = [paths[int(k * step)] for k in range(options.max_images)]
    return paths, skipped


def _store_frame(
    rgb: np.ndarray, target: Path, focal: float | None, original: Path | None
) -> tuple[Frame, FrameMeasures]:
    """Measure one loaded frame (``[H, W, 3]`` uint8 RGB, upright) and put its file at ``target``.

    ``original`` is the source file when its bytes already hold these pixels (it is copied as is);
    None writes the pixels with OpenCV (converted photos, video frames): an upright 8-bit RGB file
    for tools that read files directly (COLMAP, nerfstudio). The caller then drops the pixels.
    """
    if original is None:
        if not cv2.imwrite(str(target), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise FFReconError(f"cannot write {target}", "check that the output folder is writable and has space")
    elif not target.exists() or target.stat().st_size != original.stat().st_size:
        shutil.copyfile(original, target)
    frame = Frame(name=target.name, path=target, size_wh=(int(rgb.shape[1]), int(rgb.shape[0])), focal_prior_px=focal)
    return frame, measure_frame(rgb)


def _load_folder(
    folder: Path, options: CaptureOptions, image_dir: Path
) -> tuple[list[Frame], list[FrameMeasures], list[tuple[str, str]]]:
    paths, skipped = _list_inputs(folder, options)
    frames, measures = [], []
    for path in tqdm(paths, desc="loading images", unit="img", disable=None):
        try:
            rgb, focal, converted = load_image(path)
        except InputError as err:
            if not options.skip_bad_images:
                raise
            skipped.append((path.name, err.problem))
            log.warning("skipping %s: %s", path.name, err.problem)
            continue
        frame, measured = _store_frame(rgb, image_dir / path.name, focal, None if converted else path)
        frames.append(frame)
        measures.append(measured)
    return frames, measures, skipped


def _load_video(source: Path, options: CaptureOptions, image_dir: Path) -> tuple[list[Frame], list[FrameMeasures]]:
    frames, measures = [], []
    for name, rgb in extract_video_frames(source, options.video_frames):
        frame, measured = _store_frame(rgb, image_dir / name, None, None)
        frames.append(frame)
        measures.append(measured)
    return frames, measures


def run_capture(source: Path, options: CaptureOptions, out_dir: Path) -> Capture:
    """Load ``source`` (a folder of images or a video) into frames under ``out_dir/images``.

    Each image is decoded once: measured for the capture checks, written (or copied) upright and
    8-bit to ``out_dir/images``, and dropped; :meth:`Frame.read_rgb` reads it back when needed.
    Raises :class:`InputError` with the problem and the fix for unusable input.
    """
    source = Path(source)
    if not source.exists():
        raise InputError(f"input not found: {source}", "pass an existing folder of images or a video file")
    image_dir = Path(out_dir) / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    skipped: list[tuple[str, str]] = []
    if source.is_file():
        if source.suffix.lower() not in VIDEO_EXTENSIONS:
            raise InputError(
                f"{source.name} is neither a folder nor a video ({', '.join(VIDEO_EXTENSIONS)})",
                "pass a folder of images or a video file",
            )
        frames, measures = _load_video(source, options, image_dir)
    else:
        frames, measures, skipped = _load_folder(source, options, image_dir)
    if not frames:
        raise InputError(f"no readable images in {source}", "check the files open in an image viewer")
    names = [f.name for f in frames]
    if len(set(names)) != len(names):
        raise FFReconError("two input files share a name", "rename them so every image name is unique")
    quality = assess_capture(names, measures, options.quality)
    for flag in quality.flags:
        log.warning(flag.message)
    return Capture(tuple(frames), image_dir, source, source.is_file(), tuple(skipped), quality)
