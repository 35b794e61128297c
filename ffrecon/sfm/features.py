"""SIFT features and matches in a COLMAP database, through pycolmap 4.x (CPU).

Both the COLMAP cross-check and the feed-forward-seeded refinement keep their features and
matches in a COLMAP database, so that COLMAP itself can read them. Keypoints that COLMAP's SIFT
writes already follow COLMAP's pixel-centre rule (top-left pixel centre at (0.5, 0.5)), the rule
ffrecon uses everywhere, so nothing is shifted here.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import threading
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image, UnidentifiedImageError

from ffrecon.checks import check_number
from ffrecon.errors import InputError

logger = logging.getLogger("ffrecon.sfm")


class CameraModel(enum.Enum):
    """COLMAP camera models offered to users (values are COLMAP's names)."""

    SIMPLE_PINHOLE = "SIMPLE_PINHOLE"
    PINHOLE = "PINHOLE"
    SIMPLE_RADIAL = "SIMPLE_RADIAL"
    RADIAL = "RADIAL"
    OPENCV = "OPENCV"


@dataclass(frozen=True, kw_only=True)
class SiftOptions:
    """SIFT extraction and matching settings shared by the cross-check and the refinement."""

    max_num_features: int = 8192
    max_image_size: int = 3200  # longest side SIFT sees, in pixels (COLMAP's default)
    first_octave: int = -1  # -1: SIFT also looks at the image upsampled 2x (COLMAP's default); 0 is ~3x faster
    # With first_octave 0: images whose longest side (as SIFT sees it) is under this still get the 2x
    # upsampled octave. At 320 x 240 the demo scene gives ~410 features per frame without it, ~930 with.
    upsample_below_px: int = 0
    # With first_octave 0 or more: in a capture of at least this many images (0: never), images at or above
    # upsample_below_px start one octave higher (from the half-size image). In a long capture each frame overlaps
    # many others and coarser features hold it; a sparse capture keeps every feature. --quick at 96 frames of 640 x
    # 480: SIFT 13.1 -> 6.2 s beside the network, CPU 36.8 -> 27.6 s, AUC@5 1.000 both, median rotation error 0.03
    # -> 0.08 deg (docs/benchmarks.md, "Quick mode's SIFT").
    coarse_from_images: int = 0
    max_ratio: float = 0.8  # Lowe ratio test
    min_num_inliers: int = 15  # two-view geometry: fewer verified matches = no edge
    num_threads: int = -1  # -1: all cores

    def __post_init__(self) -> None:
        for name in ("max_num_features", "max_image_size"):
            check_number(f"SiftOptions.{name}", getattr(self, name), low=1, integer=True)
        check_number("SiftOptions.first_octave", self.first_octave, low=-1, integer=True)
        check_number("SiftOptions.upsample_below_px", self.upsample_below_px, low=0, integer=True)
        check_number("SiftOptions.coarse_from_images", self.coarse_from_images, low=0, integer=True)
        check_number("SiftOptions.max_ratio", self.max_ratio, low=0, low_open=True, high=1)
        check_number("SiftOptions.min_num_inliers", self.min_num_inliers, low=0, integer=True)


@dataclass(frozen=True)
class FeatureStats:
    """What the database holds per image, in the order of ``names``."""

    names: tuple[str, ...]
    num_keypoints: np.ndarray  # [N] int
    num_verified_pairs: np.ndarray  # [N] int, image pairs with a verified two-view geometry
    num_inlier_matches: np.ndarray  # [N] int, verified matches summed over those pairs
    num_pairs_matched: int  # image pairs that went through matching
    num_pairs_verified: int
    num_loop_candidates: int = 0  # of the matched pairs, those retrieval added (ffrecon.sfm.crosscheck.retrieval)

    def to_report(self) -> dict:
        return {
            "num_pairs_matched": self.num_pairs_matched,
            "num_pairs_verified": self.num_pairs_verified,
            "num_loop_candidates": self.num_loop_candidates,
            "per_image": {
                name: {"keypoints": int(k), "verified_pairs": int(p), "inlier_matches": int(m)}
                for name, k, p, m in zip(
                    self.names, self.num_keypoints, self.num_verified_pairs, self.num_inlier_matches
                )
            },
        }


_LOG_LEVELS: list[int] = []  # glog levels asked for by the blocks open now (threads share COLMAP's one level)
_LOG_LOCK = threading.Lock()
_LOG_BEFORE: list[int] = []  # the level before the first open block


@contextlib.contextmanager
def colmap_log_level(level: int | None = None) -> Iterator[None]:
    """Silence COLMAP's own (glog) messages below ``level`` for the duration of the block.

    By default COLMAP keeps its warnings, and its progress messages too when ffrecon logs at DEBUG.
    Blocks may be open in several threads at once (COLMAP beside the feed-forward stage): the level
    is the most verbose one asked for, and the level from before comes back when the last block ends.
    """
    if level is None:
        level = logging.INFO if logging.getLogger("ffrecon").isEnabledFor(logging.DEBUG) else logging.WARNING
    glog = {logging.DEBUG: 0, logging.INFO: 0, logging.WARNING: 1, logging.ERROR: 2}.get(level, 1)
    with _LOG_LOCK:
        if not _LOG_LEVELS:
            _LOG_BEFORE[:] = [pycolmap.logging.minloglevel]
        _LOG_LEVELS.append(glog)
        pycolmap.logging.minloglevel = min(_LOG_LEVELS)
    try:
        yield
    finally:
        with _LOG_LOCK:
            _LOG_LEVELS.remove(glog)
            pycolmap.logging.minloglevel = min(_LOG_LEVELS) if _LOG_LEVELS else _LOG_BEFORE[0]


def _check_names(names: Sequence[str]) -> None:
    bad = [n for n in names if any(c.isspace() for c in n)]
    if bad:
        raise InputError(
            f"{len(bad)} image names contain white space (e.g. {bad[0]!r}); COLMAP's pair lists cannot hold them",
            "rename the images without spaces",
        )
    if len(set(names)) != len(names):
        raise InputError("image names are not unique", "give every image its own file name")


def create_database(
    db_path: Path,
    image_dir: Path,
    names: Sequence[str],
    *,
    camera_model: CameraModel,
    single_camera: bool,
    focal_prior_px: Sequence[float | None] | None = None,
) -> dict[str, int]:
    """Create ``db_path`` (replacing any old one) holding ``names`` and their cameras.

    Args:
        focal_prior_px: per image, focal length in pixels of that image, or None. Known priors are
            written as COLMAP *prior* focal lengths (so two-view geometry is calibrated); with a
            single camera their median is used.
    Returns:
        image id in the database for each name (COLMAP numbers images in sorted-name order).
    """
    _check_names(names)
    db_path = Path(db_path)
    db_path.parent.mkdir(parents=True, exist_ok=True)
    for suffix in ("", "-shm", "-wal"):
        Path(str(db_path) + suffix).unlink(missing_ok=True)
    pycolmap.Database.open(str(db_path)).close()
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model.value
    with colmap_log_level():
        pycolmap.import_images(str(db_path), str(image_dir), mode, image_names=list(names), options=reader)
    priors = [None] * len(names) if focal_prior_px is None else list(focal_prior_px)
    if len(priors) != len(names):
        raise ValueError(f"focal_prior_px: expected {len(names)} values, got {len(priors)}")
    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        missing = [n for n in names if n not in ids]
        if missing:
            raise InputError(
                f"COLMAP could not read {len(missing)} images, e.g. {missing[0]}", f"check the files in {image_dir}"
            )
        camera_of = {image.name: image.camera_id for image in db.read_all_images()}
        by_camera: dict[int, list[float]] = {}
        for name, prior in zip(names, priors):
            if prior is not None and prior > 0:
                by_camera.setdefault(camera_of[name], []).append(float(prior))
        for camera_id, values in by_camera.items():
            camera = db.read_camera(camera_id)
            params = np.array(camera.params, dtype=np.float64)
            params[list(camera.focal_length_idxs())] = float(np.median(values))
            camera.params = params
            camera.has_prior_focal_length = True
            db.update_camera(camera)
    finally:
        db.close()
    return {name: ids[name] for name in names}


def image_sizes_wh(image_dir: Path, names: Sequence[str]) -> list[tuple[int, int] | None]:
    """``(width, height)`` in pixels of each image file as stored (read from the header only).

    None where the file cannot be read here; COLMAP, which reads the pixels, then decides.
    """
    sizes: list[tuple[int, int] | None] = []
    for name in names:
        try:
            with Image.open(Path(image_dir) / name) as img:
                sizes.append((int(img.width), int(img.height)))
        except (OSError, UnidentifiedImageError, ValueError):
            sizes.append(None)
    return sizes


def focal_prior_flags(db_path: Path, names: Sequence[str]) -> np.ndarray:
    """``[N]`` bool: the database camera of each of ``names`` carries a focal-length prior.

    The prior is ffrecon's (see :func:`create_database`) or one COLMAP read from the file's EXIF.
    """
    db = pycolmap.Database.open(str(db_path))
    try:
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        prior = {image.name: cameras[image.camera_id].has_prior_focal_length for image in db.read_all_images()}
    finally:
        db.close()
    return np.array([bool(prior.get(name, False)) for name in names], dtype=bool)


def set_database_cameras(db_path: Path, cameras: Sequence[pycolmap.Camera]) -> None:
    """Overwrite database cameras (matched by ``camera_id``) with known intrinsics, marked as priors."""
    db = pycolmap.Database.open(str(db_path))
    try:
        for camera in cameras:
            camera.has_prior_focal_length = True
            db.update_camera(camera)
    finally:
        db.close()


def extract_sift(
    db_path: Path,
    image_dir: Path,
    names: Sequence[str],
    options: SiftOptions,
    *,
    threads: Callable[[], int] | None = None,
    mask_dir: Path | None = None,
) -> None:
    """SIFT on the CPU for the images of the database that have no keypoints yet.

    ``mask_dir``: COLMAP's masks (``<image name>.png``, 0 where features are ignored), as the capture wrote
    them from ``--masks``; None: every pixel.

    ``threads``: when the cores are shared (:meth:`ffrecon.concurrency.CoreShare.step`), the images are
    extracted in up to four calls, each with at most the threads ``threads()`` gives as it starts (it may
    raise to stop between calls), so that cores freed part-way are used for the rest. Without it, one
    call per octave group with ``options.num_threads``.
    """
    for first_octave, group in _octave_groups(image_dir, names, options).items():
        size = len(group) if threads is None else max(8, -(-len(group) // 4))
        for start in range(0, len(group), size):
            extraction = pycolmap.FeatureExtractionOptions()
            asked = options.num_threads
            extraction.num_threads = asked if threads is None else threads_at_most(asked, threads())
            extraction.max_image_size = options.max_image_size
            extraction.sift.max_num_features = options.max_num_features
            extraction.sift.first_octave = first_octave
            extraction.use_gpu = False
            reader = pycolmap.ImageReaderOptions()
            if mask_dir is not None:
                reader.mask_path = str(mask_dir)
            with colmap_log_level():
                pycolmap.extract_features(
                    str(db_path),
                    str(image_dir),
                    image_names=group[start : start + size],
                    reader_options=reader,
                    extraction_options=extraction,
                    device=pycolmap.Device.cpu,
                )


def threads_at_most(asked: int, free: int) -> int:
    """COLMAP's thread count ``asked`` (<= 0: all cores), capped at ``free``.

    >>> threads_at_most(-1, 2), threads_at_most(4, 2), threads_at_most(1, 2)
    (2, 2, 1)
    """
    return free if asked <= 0 else min(asked, free)


def _octave_groups(image_dir: Path, names: Sequence[str], options: SiftOptions) -> dict[int, list[str]]:
    """``{first octave: names}``: ``options.first_octave``, or -1 for images below ``options.upsample_below_px``, and
    one octave higher for the others in a capture of ``options.coarse_from_images`` images or more."""
    if options.first_octave < 0 or options.upsample_below_px <= 0:
        return {options.first_octave: list(names)}
    coarse = 0 < options.coarse_from_images <= len(names)
    groups: dict[int, list[str]] = {}
    for name, size in zip(names, image_sizes_wh(image_dir, names)):
        side = min(max(size), options.max_image_size) if size is not None else options.max_image_size
        octave = -1 if side < options.upsample_below_px else options.first_octave + int(coarse)
        groups.setdefault(octave, []).append(name)
    return groups


def copy_features(src_db: Path, dst_db: Path, names: Sequence[str]) -> list[str]:
    """Copy keypoints and descriptors by image name; returns the names that were copied.

    Images of ``dst_db`` missing from ``src_db`` (or with no features there) are left for
    :func:`extract_sift`. The image sizes must agree (same files), which is checked.
    """
    src = pycolmap.Database.open(str(src_db))
    dst = pycolmap.Database.open(str(dst_db))
    copied = []
    try:
        src_images = {image.name: image for image in src.read_all_images()}
        for image in dst.read_all_images():
            if image.name not in names or image.name not in src_images:
                continue
            src_image = src_images[image.name]
            src_cam, dst_cam = src.read_camera(src_image.camera_id), dst.read_camera(image.camera_id)
            if (src_cam.width, src_cam.height) != (dst_cam.width, dst_cam.height):
                continue
            if not src.exists_keypoints(src_image.image_id) or dst.exists_keypoints(image.image_id):
                continue
            dst.write_keypoints(image.image_id, src.read_keypoints(src_image.image_id))
            dst.write_descriptors(image.image_id, src.read_descriptors(src_image.image_id))
            copied.append(image.name)
    finally:
        src.close()
        dst.close()
    return copied


def copy_verified_matches(src_db: Path, dst_db: Path, pairs: Collection[tuple[str, str]]) -> list[tuple[str, str]]:
    """Copy the raw matches and two-view geometries of those ``pairs`` (either order) verified in ``src_db``.

    Only valid when both images' keypoints were copied from ``src_db`` (:func:`copy_features`): match
    indices refer to them. Returns the copied pairs (database order); pairs already in ``dst_db`` are
    left alone. Matching a pair costs far more than reading it, and COLMAP's verification does not
    depend on any pose, so the cross-check's matches are as good as fresh ones.
    """
    src = pycolmap.Database.open(str(src_db))
    dst = pycolmap.Database.open(str(dst_db))
    copied: list[tuple[str, str]] = []
    try:
        src_names = {image.image_id: image.name for image in src.read_all_images()}
        dst_ids = {image.name: image.image_id for image in dst.read_all_images()}
        wanted = {frozenset(pair) for pair in pairs}
        pair_ids, geometries = src.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries):
            id_a, id_b = pycolmap.pair_id_to_image_pair(pair_id)
            name_a, name_b = src_names[id_a], src_names[id_b]
            if frozenset((name_a, name_b)) not in wanted or len(geometry.inlier_matches) == 0:
                continue
            a, b = dst_ids[name_a], dst_ids[name_b]
            if dst.exists_two_view_geometry(a, b):
                continue
            matches = np.asarray(src.read_matches(id_a, id_b))
            inliers = np.asarray(geometry.inlier_matches)
            if a > b:  # COLMAP stores a pair once, smaller image id first
                matches, inliers = matches[:, ::-1], inliers[:, ::-1]
                geometry.invert()
            geometry.inlier_matches = np.ascontiguousarray(inliers, dtype=np.uint32)
            dst.write_matches(min(a, b), max(a, b), np.ascontiguousarray(matches, dtype=np.uint32))
            dst.write_two_view_geometry(min(a, b), max(a, b), geometry)
            copied.append((name_a, name_b))
    finally:
        src.close()
        dst.close()
    return copied


def matching_options(options: SiftOptions) -> tuple[pycolmap.FeatureMatchingOptions, pycolmap.TwoViewGeometryOptions]:
    """pycolmap matching and verification options for ``options`` (CPU, seeded RANSAC)."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    matching.use_gpu = False
    matching.sift.max_ratio = options.max_ratio
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = options.min_num_inliers
    verification.ransac.random_seed = 0
    return matching, verification


def write_pairs(pairs_path: Path, pairs: Sequence[tuple[str, str]]) -> Path:
    """COLMAP's pair list: one ``name_a name_b`` per line."""
    pairs_path = Path(pairs_path)
    pairs_path.parent.mkdir(parents=True, exist_ok=True)
    pairs_path.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    return pairs_path


def match_pairs(
    db_path: Path, pairs: Sequence[tuple[str, str]], options: SiftOptions, pairs_path: Path, *, verify: bool = True
) -> None:
    """Match exactly the given image pairs (listed in ``pairs_path``), verified unless ``verify=False``."""
    write_pairs(pairs_path, pairs)
    matching, verification = matching_options(options)
    matching.skip_geometric_verification = not verify
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(pairs_path)
    with colmap_log_level():
        pycolmap.match_image_pairs(
            str(db_path),
            matching_options=matching,
            pairing_options=pairing,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )


def verify_pairs(db_path: Path, pairs_path: Path, options: SiftOptions) -> None:
    """Geometric verification (two-view geometry) of the raw matches of the pairs in ``pairs_path``."""
    _, verification = matching_options(options)
    with colmap_log_level():
        pycolmap.verify_matches(str(db_path), str(pairs_path), verification)


def feature_stats(db_path: Path, names: Sequence[str]) -> FeatureStats:
    """Keypoints, verified pairs and inlier matches per image, read back from the database."""
    db = pycolmap.Database.open(str(db_path))
    try:
        images = {image.image_id: image.name for image in db.read_all_images()}
        index = {name: k for k, name in enumerate(names)}
        keypoints = np.zeros(len(names), int)
        for image_id, name in images.items():
            if name in index:
                keypoints[index[name]] = db.num_keypoints_for_image(image_id)
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        verified = np.zeros(len(names), int)
        matches = np.zeros(len(names), int)
        num_verified = 0
        for pair_id, count in zip(pair_ids, inliers):
            if count <= 0:
                continue
            num_verified += 1
            for image_id in pycolmap.pair_id_to_image_pair(pair_id):
                k = index.get(images.get(image_id, ""))
                if k is not None:
                    verified[k] += 1
                    matches[k] += count
        num_matched = db.num_matched_image_pairs()
    finally:
        db.close()
    return FeatureStats(tuple(names), keypoints, verified, matches, int(num_matched), num_verified)
