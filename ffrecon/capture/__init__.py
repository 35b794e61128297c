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

from ffrecon.capture.images import (
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    Photo,
    broken_links,
    frame_size_problem,
    list_images,
    load_photo,
)
from ffrecon.capture.lens import undistort_lens
from ffrecon.capture.masks import write_masks
from ffrecon.capture.names import check_names
from ffrecon.capture.quality import CaptureQuality, FrameMeasures, QualityOptions, assess_capture, measure_frame
from ffrecon.capture.video import extract_video_frames
from ffrecon.checks import check_number
from ffrecon.concurrency import available_cores, map_in_order
from ffrecon.errors import InputError, ResourceError
from ffrecon.formats.intrinsics import KnownIntrinsics, read_intrinsics
from ffrecon.formats.poses import read_poses
from ffrecon.types import Frame, PinholeCamera, capped_size

log = logging.getLogger("ffrecon.capture")


MIN_IMAGE_SIZE = 64  # the smallest cap: below it SIFT and the models find next to nothing


@dataclass(frozen=True, kw_only=True)
class CaptureOptions:
    """How photos or a video become frames. Checked where made (``__post_init__``): the CLI and the
    Python API refuse the same values with the same message.

    ``max_image_size``: the long side, in pixels, of the frames every later stage works on; larger
    photos and video frames are area-averaged to it at capture and written so into ``images/``
    (COLMAP, the model, the splat and transforms.json all see the same frames; the report records each
    frame's original size and scale). None or 0 keeps full size. 1600 is the 3DGS reference's choice
    (its convert and train scripts scale wider images to 1600 px) and nerfstudio's downscale factors
    serve the same end: the model works at about 518 px and COLMAP's SIFT at most 3200 px anyway, while
    the splat holds every training image in float32 and renders at full size, so its memory and time
    grow with the pixels. Measured (docs/benchmarks.md, "Very large photos"): one 12000x9000 photo
    among five 1024x768 ones was killed at 23 GB at full size and runs in a few GB capped.
    """

    video_frames: int = 48  # frames kept from a video (at least 2)
    skip_bad_images: bool = (
        False  # leave out unreadable, truncated and corrupt files and non-images instead of stopping
    )
    max_images: int | None = None  # keep at most this many (evenly spaced), None for all
    max_image_size: int | None = 1600  # long side of the frames, px; larger ones are downscaled; None or 0: full size
    quality: QualityOptions = field(default_factory=QualityOptions)
    # Known intrinsics (--intrinsics, COLMAP's cameras.txt form: ffrecon.formats.intrinsics), scaled to each
    # frame. Fixed by default: the model's own estimate is replaced (and reported beside them), the cross-check
    # starts from them as focal priors and the bundle adjustment keeps them; with ``intrinsics_prior`` the
    # bundle adjustment refines them.
    intrinsics: Path | None = None
    intrinsics_prior: bool = False
    # A folder of masks (--masks; nerfstudio's and COLMAP's convention: a PNG per photo named after it,
    # <stem>.png or <name>.png, 0 where the photo is to be ignored: moving objects, people, the photographer).
    # Applied to SIFT extraction, the model's depth (no fused points, no dense evidence there) and the splat's
    # loss and scores; written as OUT/masks/<name>.png and named in transforms.json.
    masks: Path | None = None
    # Known poses (--poses: a COLMAP model or a transforms.json, ffrecon.formats.poses), by photo name, three or
    # more: they replace the model's poses (moved into its frame by a Sim(3) on the camera centres; the model's
    # own are kept and compared with them); the bundle adjustment holds them fixed (with ``poses_prior``: keeps
    # the camera centres near them).
    poses: Path | None = None
    poses_prior: bool = False  # the given poses are priors (centres held near them), not fixed

    def __post_init__(self) -> None:
        check_number("capture video_frames", self.video_frames, low=2, integer=True, flag="--video-frames")
        check_number("capture max_images", self.max_images, low=1, integer=True, allow_none=True)
        try:
            check_number(
                "capture max_image_size",
                self.max_image_size or None,
                low=MIN_IMAGE_SIZE,
                integer=True,
                allow_none=True,
                flag="--max-image-size",
            )
        except InputError as err:
            raise InputError(err.problem, f"{err.fix}, or 0 for full size") from None
        # Whole numbers as int, 0 as None: equal options give equal stage keys (ffrecon.resume).
        object.__setattr__(self, "video_frames", int(self.video_frames))
        object.__setattr__(self, "max_images", None if self.max_images is None else int(self.max_images))
        object.__setattr__(self, "max_image_size", int(self.max_image_size) if self.max_image_size else None)


class FramesOnDemand(Sequence):
    """``[H, W, 3]`` uint8 RGB upright images of frames, each read from disk when indexed. With ``keep_bytes``, the
    first frames read are kept while they take at most that much, and served again from memory (a stage that goes
    through its frames twice, as the feed-forward stage does for the network and then the fusion, reads those
    once); without it nothing is kept."""

    def __init__(self, frames: tuple[Frame, ...], keep_bytes: int = 0) -> None:
        self._frames = frames
        self._kept: dict[int, np.ndarray] = {}
        self._room = keep_bytes

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, index):  # an int gives an image, a slice a list of them
        if isinstance(index, slice):
            return [self[k] for k in range(*index.indices(len(self)))]
        k = range(len(self))[index]
        if k in self._kept:
            return self._kept[k]
        image = self._frames[k].read_rgb()
        if image.nbytes <= self._room:
            image.flags.writeable = False  # shared by every reader: none may change it
            self._kept[k] = image
            self._room -= image.nbytes
        return image


@dataclass(frozen=True)
class Capture:
    """The loaded frames (paths and sizes, no pixels: see :meth:`read_images`) and their quality checks."""

    frames: tuple[Frame, ...]
    image_dir: Path  # OUT/images: every frame under its name; COLMAP and transforms.json read these
    source: Path
    is_video: bool
    skipped: tuple[tuple[str, str], ...]  # (file name, reason)
    quality: CaptureQuality
    original_sizes_wh: tuple[tuple[int, int], ...] = ()  # per frame, upright size in the input (empty: = size_wh)
    max_image_size: int | None = None  # the cap the frames were made with (CaptureOptions.max_image_size)
    known_cameras: tuple[PinholeCamera, ...] = ()  # per frame, the given intrinsics at its size (empty: none given)
    intrinsics_fixed: bool = True  # the known cameras are fixed (else starting values the adjustment refines)
    known_file: Path | None = None  # the file they came from (--intrinsics)
    mask_dir: Path | None = None  # OUT/masks: a mask per frame, <name>.png at its size, 255 keep / 0 ignore
    known_poses: tuple[np.ndarray | None, ...] = ()  # per frame the given cam_from_world [3, 4] (None: not given)
    poses_file: Path | None = None  # the file or folder they came from (--poses)
    poses_fixed: bool = True  # the given poses stay as given (else priors the adjustment moves a little)

    def read_masks(self, indices: Sequence[int] | None = None) -> list[np.ndarray] | None:
        """``[H_i, W_i]`` bool masks (True: use the pixel) of the frames at ``indices``; None without masks."""
        if self.mask_dir is None:
            return None
        chosen = range(len(self.frames)) if indices is None else indices
        return [
            cv2.imread(str(self.mask_dir / f"{self.frames[i].name}.png"), cv2.IMREAD_GRAYSCALE) > 127 for i in chosen
        ]

    @property
    def focal_priors_px(self) -> list[float | None]:
        """Per frame, the focal length COLMAP starts from: the given intrinsics', else EXIF's, else None."""
        if self.known_cameras:
            return [float(np.sqrt(c.fx * c.fy)) for c in self.known_cameras]
        return [f.focal_prior_px for f in self.frames]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.frames)

    @property
    def scales(self) -> tuple[float, ...]:
        """Per frame, its long side over the input's (1.0: full size; below 1: downscaled at capture)."""
        originals = self.original_sizes_wh or tuple(f.size_wh for f in self.frames)
        return tuple(max(f.size_wh) / max(o) for f, o in zip(self.frames, originals))

    def frames_on_demand(self, indices: Sequence[int] | None = None, keep_bytes: int = 0) -> FramesOnDemand:
        """The frames at ``indices`` (all by default) as a sequence read from disk one at a time, when asked
        for: a stage that goes through them in order holds one, not all (1,000 frames of 640x480 are 0.9 GB;
        of 1600x1200, 5.8 GB), or those that fit in ``keep_bytes`` (:class:`FramesOnDemand`)."""
        chosen = range(len(self.frames)) if indices is None else indices
        return FramesOnDemand(tuple(self.frames[i] for i in chosen), keep_bytes)

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
            "max_image_size": self.max_image_size,
            "original_sizes_wh": [list(o) for o in (self.original_sizes_wh or [f.size_wh for f in self.frames])],
            "scales": [round(s, 6) for s in self.scales],
            "focal_prior_px": [f.focal_prior_px for f in self.frames],
            "skipped": [{"name": n, "reason": r} for n, r in self.skipped],
            "quality": self.quality.to_report(),
            "given": {  # what the user gave besides the photos (--intrinsics, --poses, --masks)
                "intrinsics": None if self.known_file is None else str(self.known_file),
                "intrinsics_fixed": self.intrinsics_fixed if self.known_cameras else None,
                "poses": None if self.poses_file is None else str(self.poses_file),
                "num_poses": sum(p is not None for p in self.known_poses),
                "masks": self.mask_dir is not None,
            },
        }


DATASET_DOCUMENTS = frozenset({"license", "licence", "readme", "copying", "credits", "attribution", "authors"})
_LISTED = 8  # bad files named in one error message; the rest are counted
# JPEG frames ffrecon writes: quality 95 without chroma subsampling (OpenCV's default subsamples 4:2:0).
# Re-encoding a 720x477 JPEG photo: mean error 1.7 grey levels and 1.3x the bytes, against 3.0 by default.
_JPEG_PARAMS = [
    cv2.IMWRITE_JPEG_QUALITY,
    95,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
]


@dataclass
class _BadInputs:
    """Input files that cannot be used, collected so that one error (or the skipped list) names them all."""

    folder: Path
    not_images: list[Path] = field(default_factory=list)
    unusable: list[tuple[str, str]] = field(default_factory=list)  # (file name, why, naming the file)

    def __bool__(self) -> bool:
        return bool(self.not_images or self.unusable)

    def skipped(self) -> list[tuple[str, str]]:
        return [(p.name, "not an image") for p in self.not_images] + self.unusable

    def error(self) -> InputError:
        """One error naming every bad file (the first few; the rest counted)."""
        sentences = [why for _, why in self.unusable]
        if self.not_images:
            listed = ", ".join(p.name for p in self.not_images[:_LISTED])
            more = " ..." if len(self.not_images) > _LISTED else ""
            sentences.insert(
                0,
                f"{self.folder} holds {len(self.not_images)} file(s) that are not images ({listed}{more}); "
                f"supported: {', '.join(IMAGE_EXTENSIONS)}",
            )
        count = len(self.not_images) + len(self.unusable)
        text = "; ".join(sentences[:_LISTED]) + (
            f"; and {len(sentences) - _LISTED} more" if len(sentences) > _LISTED else ""
        )
        return InputError(
            text if count == 1 else f"{count} input files cannot be used: {text}",
            "move out or replace the files named, or pass --skip-bad-images to leave them out (the report lists them)",
        )


def _list_inputs(folder: Path, options: CaptureOptions) -> tuple[list[Path], list[tuple[str, str]], _BadInputs]:
    """The image files to load (at most ``max_images``, evenly spaced), the files left out on purpose
    (a dataset's documentation) and the bad ones found so far (non-images, links to missing files)."""
    paths, others = list_images(folder)
    # A dataset's license and readme files travel with its photos: leave them out, and say so.
    docs = [p for p in others if p.stem.lower() in DATASET_DOCUMENTS]
    skipped: list[tuple[str, str]] = [(p.name, "a dataset's documentation, not an image") for p in docs]
    for p in docs:
        log.info("leaving out %s (a dataset's documentation, not an image)", p.name)
    bad = _BadInputs(folder, not_images=[p for p in others if p not in docs])
    for link in broken_links(folder):
        bad.unusable.append((link.name, f"{link.name} is a symbolic link to {link.readlink()}, which does not exist"))
    if options.max_images and len(paths) > options.max_images:
        step = len(paths) / options.max_images
        paths = [paths[int(k * step)] for k in range(options.max_images)]
    check_names([p.name for p in paths], folder)  # before any photo is decoded, with or without --skip-bad-images
    return paths, skipped, bad


def _store_frame(
    rgb: np.ndarray, target: Path, focal: float | None, original: Path | None
) -> tuple[Frame, FrameMeasures]:
    """Measure one loaded frame (``[H, W, 3]`` uint8 RGB, upright) and put its file at ``target``.

    ``original`` is the source file when its bytes already hold these pixels (8-bit RGB, upright, at its
    size: it is copied as is); None writes the pixels with OpenCV (photos that are CMYK, palette, grey, grey
    or RGB with alpha (composited on white), 16-bit or float, EXIF-rotated or downscaled; video frames): a
    3-channel upright 8-bit RGB file for tools that read files directly (COLMAP, nerfstudio, 3DGS), in the
    format its name says (PNG, TIFF, BMP and WebP losslessly). The caller then drops the pixels.
    Raises :class:`ResourceError` when the file cannot be written (disk full, read-only folder).
    """
    try:
        if original is None:
            params = _JPEG_PARAMS if target.suffix.lower() in (".jpg", ".jpeg") else []
            if not cv2.imwrite(str(target), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params):
                raise OSError("OpenCV could not write the file")
        elif not target.exists() or target.stat().st_size != original.stat().st_size:
            shutil.copyfile(original, target)
    except (OSError, cv2.error) as err:
        raise _write_error(target, err) from None
    frame = Frame(name=target.name, path=target, size_wh=(int(rgb.shape[1]), int(rgb.shape[0])), focal_prior_px=focal)
    return frame, measure_frame(rgb)


def _write_error(target: Path, err: Exception) -> ResourceError:
    reason = getattr(err, "strerror", None) or str(err).strip().splitlines()[-1]
    try:
        free = f"; {shutil.disk_usage(target.parent).free / 2**20:.0f} MB free there"
    except OSError:
        free = ""
    return ResourceError(
        f"cannot write frame {target.name} into {target.parent} ({reason}{free})",
        "free disk space, or pass an output folder (-o) on a writable disk with room",
    )


@dataclass
class _Loaded:
    """What loading keeps per frame: the frame (a path, no pixels), its measures and its input size."""

    frames: list[Frame] = field(default_factory=list)
    measures: list[FrameMeasures] = field(default_factory=list)
    original_sizes_wh: list[tuple[int, int]] = field(default_factory=list)

    def add(self, frame: Frame, measures: FrameMeasures, original_wh: tuple[int, int]) -> None:
        self.frames.append(frame)
        self.measures.append(measures)
        self.original_sizes_wh.append(original_wh)


def _load_folder(folder: Path, options: CaptureOptions, image_dir: Path) -> tuple[_Loaded, list[tuple[str, str]]]:
    """Every listed image decoded strictly. Without ``skip_bad_images`` the first bad file (or non-image)
    stops the storing, not the checking: the rest are still decoded, so that one error names them all. The frames
    are measured and written on the cores while the next are decoded."""
    paths, skipped, bad = _list_inputs(folder, options)
    if not paths and not bad:
        raise InputError(
            f"no images found in {folder}",
            f"put photos ({', '.join(IMAGE_EXTENSIONS)}) in the folder, or pass a video file",
        )

    def decoded():  # in this thread (Pillow's strict mode is process-wide): each photo, or its problem noted
        for path in tqdm(paths, desc="loading images", unit="img", disable=None):
            try:
                photo = load_photo(path, max_size=options.max_image_size)
            except InputError as err:
                bad.unusable.append((path.name, err.problem))
                continue
            if not bad or options.skip_bad_images:  # else the run stops below: only check the remaining files
                yield path, photo

    def stored(item: tuple[Path, Photo]):  # on the cores: measuring and writing (OpenCV releases the GIL)
        path, photo = item
        original = None if photo.converted else path  # its bytes are copied where they hold the pixels as they are
        frame, measured = _store_frame(photo.rgb, image_dir / path.name, photo.focal_prior_px, original)
        return frame, measured, photo.original_size_wh

    loaded = _Loaded()
    for frame_measured_size in map_in_order(stored, decoded(), available_cores()):
        loaded.add(*frame_measured_size)
    if bad and not options.skip_bad_images:
        raise bad.error()
    for name, why in bad.skipped():
        log.warning("skipping %s: %s", name, why)
    return loaded, skipped + bad.skipped()


def _load_video(source: Path, options: CaptureOptions, image_dir: Path) -> _Loaded:
    loaded = _Loaded()
    for name, rgb in extract_video_frames(source, options.video_frames):
        original_wh = (int(rgb.shape[1]), int(rgb.shape[0]))
        size = capped_size(*original_wh, options.max_image_size)
        problem = frame_size_problem(f"video {source.name}", size, original_wh)
        if problem:
            raise InputError(problem, "use a larger video (or --max-image-size 0 if the cap made them too small)")
        if size != original_wh:
            rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        frame, measured = _store_frame(rgb, image_dir / name, None, None)
        loaded.add(frame, measured, original_wh)
    return loaded


def _log_downscaled(loaded: _Loaded, max_size: int | None) -> None:
    shrunk = [(f, o) for f, o in zip(loaded.frames, loaded.original_sizes_wh) if tuple(f.size_wh) != tuple(o)]
    if shrunk:
        f, o = shrunk[0]
        log.info(
            "%d of %d frames downscaled to %d px on the long side (e.g. %s: %dx%d -> %dx%d); "
            "--max-image-size 0 keeps full size",
            len(shrunk),
            len(loaded.frames),
            max_size,
            f.name,
            *o,
            *f.size_wh,
        )


def run_capture(source: Path, options: CaptureOptions, out_dir: Path) -> Capture:
    """Load ``source`` (a folder of images or a video) into frames under ``out_dir/images``.

    Each image is decoded once, strictly (:func:`ffrecon.capture.images.load_photo`): downscaled to
    ``options.max_image_size``, measured for the capture checks, written (or copied) upright and
    8-bit to ``out_dir/images``, and dropped; :meth:`Frame.read_rgb` reads it back when needed.
    Raises :class:`InputError` with the problem and the fix for unusable input (naming every bad file),
    :class:`ResourceError` when ``out_dir`` cannot take the frames.
    """
    source = Path(source)
    if not source.exists():
        raise InputError(f"input not found: {source}", "pass an existing folder of images or a video file")
    image_dir = Path(out_dir) / "images"
    try:
        image_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise _write_error(image_dir, err) from None
    skipped: list[tuple[str, str]] = []
    if source.is_file():
        if source.suffix.lower() not in VIDEO_EXTENSIONS:
            raise InputError(
                f"{source.name} is neither a folder nor a video ({', '.join(VIDEO_EXTENSIONS)})",
                "pass a folder of images or a video file",
            )
        loaded = _load_video(source, options, image_dir)
    else:
        loaded, skipped = _load_folder(source, options, image_dir)
    if not loaded.frames:
        raise InputError(f"no readable images in {source}", "check the files open in an image viewer")
    names = [f.name for f in loaded.frames]  # unique: photos by check_names, video frames by index
    _log_downscaled(loaded, options.max_image_size)
    quality = assess_capture(names, loaded.measures, options.quality)
    for flag in quality.flags:
        log.warning(flag.message)
    known = ()
    if options.intrinsics is not None:
        intrinsics = read_intrinsics(options.intrinsics)
        originals = loaded.original_sizes_wh or [f.size_wh for f in loaded.frames]
        known = tuple(_known_camera(intrinsics, f, o) for f, o in zip(loaded.frames, originals))
    poses = _known_poses(options.poses, names) if options.poses is not None else ()
    mask_dir = None
    if options.masks is not None:
        originals = loaded.original_sizes_wh or [f.size_wh for f in loaded.frames]
        mask_dir = write_masks(Path(options.masks), loaded.frames, originals, Path(out_dir) / "masks")
    if known:
        _undistort_lenses(intrinsics, loaded.frames, known, image_dir, mask_dir)
    return Capture(
        tuple(loaded.frames),
        image_dir,
        source,
        source.is_file(),
        tuple(skipped),
        quality,
        original_sizes_wh=tuple(loaded.original_sizes_wh),
        max_image_size=options.max_image_size,
        known_cameras=known,
        intrinsics_fixed=not options.intrinsics_prior,
        known_file=options.intrinsics,
        mask_dir=mask_dir,
        known_poses=poses,
        poses_file=options.poses,
        poses_fixed=not options.poses_prior,
    )


def _undistort_lenses(
    intrinsics: KnownIntrinsics,
    frames: Sequence[Frame],
    cameras: tuple[PinholeCamera, ...],
    image_dir: Path,
    mask_dir: Path | None,
) -> None:
    """Frames whose given camera has a lens become pinhole frames of the same K (:mod:`.lens`)."""
    done = []
    for frame, camera in zip(frames, cameras):
        lens = intrinsics.lens_of(frame.name)
        if lens is not None:
            mask = None if mask_dir is None else mask_dir / f"{frame.name}.png"
            undistort_lens(image_dir / frame.name, camera, lens, mask)
            done.append(frame.name)
    if done:
        log.info("%d frames with a given lens undistorted to pinhole frames of the same K", len(done))


def _known_poses(path: Path, names: list[str]) -> tuple[np.ndarray | None, ...]:
    """Per frame the given pose (None where the file has none); an :class:`InputError` below three."""
    known = read_poses(path)
    poses = tuple(known.get(n) for n in names)
    if sum(p is not None for p in poses) < 3:
        raise InputError(
            f"--poses {path} has the poses of {sum(p is not None for p in poses)} of these photos",
            "give the poses of three photos or more, under the photos' file names",
        )
    return poses


def _known_camera(intrinsics: KnownIntrinsics, frame: Frame, original_wh: tuple[int, int]) -> PinholeCamera:
    """The given camera of ``frame`` at its size as captured: given for the photo as it was (upright), then
    scaled as the photo was (downscaled at capture, see ``max_image_size``)."""
    camera = intrinsics.camera(frame.name, tuple(original_wh))
    sx, sy = frame.size_wh[0] / camera.width, frame.size_wh[1] / camera.height
    return camera if (sx, sy) == (1.0, 1.0) else camera.scaled(sx, sy)
