"""Capture: load photos or video frames and check them before any expensive work."""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2
from tqdm.auto import tqdm

from ffrecon.capture.images import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, list_images, load_image
from ffrecon.capture.quality import CaptureQuality, QualityOptions, assess_capture
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
    frames: tuple[Frame, ...]
    image_dir: Path  # OUT/images: every frame under its name; COLMAP and transforms.json read these
    source: Path
    is_video: bool
    skipped: tuple[tuple[str, str], ...]  # (file name, reason)
    quality: CaptureQuality

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.frames)

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


def _load_folder(folder: Path, options: CaptureOptions, image_dir: Path) -> tuple[list[Frame], list[tuple[str, str]]]:
    paths, others = list_images(folder)
    skipped: list[tuple[str, str]] = []
    if others:
        listed = ", ".join(p.name for p in others[:5]) + (" ..." if len(others) > 5 else "")
        if not options.skip_bad_images:
            raise InputError(
                f"{folder} holds {len(others)} file(s) that are not images ({listed}); supported: {', '.join(IMAGE_EXTENSIONS)}",
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
    frames = []
    for path in tqdm(paths, desc="loading images", unit="img", disable=None):
        try:
            rgb, focal, converted = load_image(path)
        except InputError as err:
            if not options.skip_bad_images:
                raise
            skipped.append((path.name, err.problem))
            log.warning("skipping %s: %s", path.name, err.problem)
            continue
        target = image_dir / path.name
        if converted:  # upright 8-bit RGB copy for tools that read files directly (COLMAP, nerfstudio)
            cv2.imwrite(str(target), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        elif not target.exists() or target.stat().st_size != path.stat().st_size:
            shutil.copyfile(path, target)
        frames.append(Frame(path.name, rgb, focal, target))
    return frames, skipped


def run_capture(source: Path, options: CaptureOptions, out_dir: Path) -> Capture:
    """Load ``source`` (a folder of images or a video) into frames under ``out_dir/images``.

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
        frames = []
        for name, rgb in extract_video_frames(source, options.video_frames):
            target = image_dir / name
            cv2.imwrite(str(target), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            frames.append(Frame(name, rgb, None, target))
    else:
        frames, skipped = _load_folder(source, options, image_dir)
    if not frames:
        raise InputError(f"no readable images in {source}", "check the files open in an image viewer")
    names = [f.name for f in frames]
    if len(set(names)) != len(names):
        raise FFReconError("two input files share a name", "rename them so every image name is unique")
    quality = assess_capture(names, [f.image for f in frames], options.quality)
    for flag in quality.flags:
        log.warning(flag.message)
    return Capture(tuple(frames), image_dir, source, source.is_file(), tuple(skipped), quality)
