"""The independent COLMAP reconstruction used to cross-check the feed-forward cameras.

``run_colmap`` is plain COLMAP on the same images (SIFT on the CPU, a pairing strategy, incremental
or global mapping), with one deliberate help: a focal-length prior (from EXIF or the feed-forward
model) is written into the database cameras, because two images with no prior form an
uncalibrated pair that default incremental mapping cannot initialise from.
"""

from __future__ import annotations

import enum
import logging
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.errors import InputError
from ffrecon.sfm.colmap_io import cam_from_world_by_name, cameras_by_name, write_reconstruction
from ffrecon.sfm.features import (
    CameraModel,
    FeatureStats,
    SiftOptions,
    colmap_log_level,
    create_database,
    extract_sift,
    feature_stats,
    matching_options,
)
from ffrecon.timing import StageTimer, Timings
from ffrecon.types import PinholeCamera

logger = logging.getLogger("ffrecon.sfm")


class PairingMode(enum.Enum):
    AUTO = "auto"  # exhaustive up to ``exhaustive_max_images``, then vocabulary tree if given, else sequential
    EXHAUSTIVE = "exhaustive"
    SEQUENTIAL = "sequential"  # video order: each frame against its ``sequential_overlap`` successors
    SPATIAL = "spatial"  # nearest GPS positions (needs position priors in the database, e.g. from EXIF)
    VOCAB_TREE = "vocab_tree"  # image retrieval; needs ``vocab_tree_path``


class MapperKind(enum.Enum):
    INCREMENTAL = "incremental"
    GLOBAL = "global"  # GLOMAP, merged into COLMAP 4


class ColmapStatus(enum.Enum):
    SUCCESS = "success"
    NO_MODEL = "no_model"  # mapping built no model (nothing registered)


@dataclass(frozen=True, kw_only=True)
class ColmapOptions:
    enabled: bool = True  # False: the stage is skipped (and the report says so)
    pairing: PairingMode = PairingMode.AUTO
    exhaustive_max_images: int = 150
    sequential_overlap: int = 10
    vocab_tree_path: Path | None = None
    mapper: MapperKind = MapperKind.INCREMENTAL
    camera_model: CameraModel = CameraModel.SIMPLE_RADIAL
    single_camera: bool = True  # one camera for all images (a phone video, one lens)
    sift: SiftOptions = SiftOptions()
    num_threads: int = -1
    seed: int = 0


@dataclass(frozen=True)
class ColmapResult:
    """COLMAP's answer for ``names``; poses are cam_from_world in COLMAP's own world frame."""

    status: ColmapStatus
    names: tuple[str, ...]
    cam_from_world: np.ndarray  # [N, 3, 4] float64; identity where not registered
    registered: np.ndarray  # [N] bool
    cameras: tuple[PinholeCamera | None, ...]  # pinhole part of COLMAP's cameras; None if not registered
    num_points: int
    mean_reprojection_error_px: float  # nan without a model
    num_models: int  # disconnected models COLMAP built; the largest is the one kept
    pairing: PairingMode  # the pairing that ran (AUTO resolved)
    mapper: MapperKind
    features: FeatureStats
    timings: Timings
    database_path: Path
    model_path: Path | None  # out_dir/sparse/0
    reconstruction: pycolmap.Reconstruction | None = field(default=None, repr=False, compare=False)

    @property
    def num_registered(self) -> int:
        return int(self.registered.sum())

    @property
    def registration_ratio(self) -> float:
        return self.num_registered / max(len(self.names), 1)

    def to_report(self) -> dict:
        return {
            "status": self.status.value,
            "num_images": len(self.names),
            "num_registered": self.num_registered,
            "registration_ratio": self.registration_ratio,
            "unregistered": [n for n, r in zip(self.names, self.registered) if not r],
            "num_points": self.num_points,
            "mean_reprojection_error_px": None
            if not np.isfinite(self.mean_reprojection_error_px)
            else self.mean_reprojection_error_px,
            "num_models": self.num_models,
            "pairing": self.pairing.value,
            "mapper": self.mapper.value,
            "model_path": None if self.model_path is None else str(self.model_path),
            "timings_s": self.timings.to_report(),
            "features": self.features.to_report(),
        }


def resolve_pairing(options: ColmapOptions, num_images: int) -> PairingMode:
    if options.pairing is not PairingMode.AUTO:
        return options.pairing
    if num_images <= options.exhaustive_max_images:
        return PairingMode.EXHAUSTIVE
    return PairingMode.VOCAB_TREE if options.vocab_tree_path is not None else PairingMode.SEQUENTIAL


def _match(db_path: Path, mode: PairingMode, options: ColmapOptions) -> None:
    matching, verification = matching_options(options.sift)
    common = dict(matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu)
    if mode is PairingMode.EXHAUSTIVE:
        pycolmap.match_exhaustive(str(db_path), **common)
    elif mode is PairingMode.SEQUENTIAL:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = options.sequential_overlap
        pairing.num_threads = options.num_threads
        pycolmap.match_sequential(str(db_path), pairing_options=pairing, **common)
    elif mode is PairingMode.SPATIAL:
        db = pycolmap.Database.open(str(db_path))
        has_priors = db.num_pose_priors() > 0
        db.close()
        if not has_priors:
            raise InputError(
                "spatial pairing needs GPS positions, and these images carry none",
                "use --pairing sequential or exhaustive",
            )
        pairing = pycolmap.SpatialPairingOptions()
        pairing.num_threads = options.num_threads
        pycolmap.match_spatial(str(db_path), pairing_options=pairing, **common)
    elif mode is PairingMode.VOCAB_TREE:
        if options.vocab_tree_path is None or not Path(options.vocab_tree_path).is_file():
            raise InputError(
                f"vocabulary-tree pairing needs a vocabulary tree file (got {options.vocab_tree_path})",
                "download one of COLMAP's vocabulary trees and pass its path, or use sequential pairing",
            )
        pairing = pycolmap.VocabTreePairingOptions()
        pairing.vocab_tree_path = str(options.vocab_tree_path)
        pairing.num_threads = options.num_threads
        pycolmap.match_vocabtree(str(db_path), pairing_options=pairing, **common)
    else:
        raise ValueError(f"unresolved pairing mode {mode}")


def _map(
    db_path: Path, image_dir: Path, work_dir: Path, options: ColmapOptions, num_images: int
) -> dict[int, pycolmap.Reconstruction]:
    if options.mapper is MapperKind.INCREMENTAL:
        mapping = pycolmap.IncrementalPipelineOptions()
        mapping.num_threads = options.num_threads
        mapping.random_seed = options.seed
        mapping.min_model_size = min(3, num_images)
        # Every track of a two-image capture is a two-view track, which COLMAP skips by default.
        mapping.triangulation.ignore_two_view_tracks = num_images > 2
        return pycolmap.incremental_mapping(str(db_path), str(image_dir), str(work_dir), mapping)
    mapping = pycolmap.GlobalPipelineOptions()
    mapping.num_threads = options.num_threads
    mapping.random_seed = options.seed
    mapping.min_model_size = min(3, num_images)
    mapping.mapper.global_positioning.use_gpu = False
    mapping.mapper.bundle_adjustment.ceres.use_gpu = False
    return pycolmap.global_mapping(str(db_path), str(image_dir), str(work_dir), mapping)


def _as_priors(focal_prior_px: float | Sequence[float | None] | None, n: int) -> list[float | None]:
    if focal_prior_px is None:
        return [None] * n
    if isinstance(focal_prior_px, (int, float)):
        return [float(focal_prior_px)] * n
    return list(focal_prior_px)


def run_colmap(
    image_dir: Path,
    names: Sequence[str],
    options: ColmapOptions,
    out_dir: Path,
    *,
    focal_prior_px: float | Sequence[float | None] | None,
) -> ColmapResult:
    """COLMAP on ``names`` in ``image_dir``; writes ``out_dir/database.db`` and ``out_dir/sparse/0``.

    Args:
        focal_prior_px: focal length in pixels of the original images (one value for all, or one per
            image, None where unknown). Without it COLMAP guesses 1.2 x the longest side.
    Returns:
        A :class:`ColmapResult`; ``status`` is NO_MODEL (not an exception) when nothing registered,
        so that the registration gate can explain why.
    """
    out_dir = Path(out_dir)
    names = tuple(names)
    timer = StageTimer()
    db_path = out_dir / "database.db"
    pairing = resolve_pairing(options, len(names))
    stats = _features_and_matches(db_path, image_dir, names, options, pairing, focal_prior_px, timer)
    work_dir = out_dir / "mapper"
    shutil.rmtree(work_dir, ignore_errors=True)
    with timer.stage("mapping"), colmap_log_level():
        models = _map(db_path, image_dir, work_dir, options, len(names)) if stats.num_pairs_verified else {}
    shutil.rmtree(work_dir, ignore_errors=True)
    model_dir = out_dir / "sparse" / "0"
    shutil.rmtree(model_dir, ignore_errors=True)
    best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), default=None)
    provenance = dict(
        num_models=len(models),
        pairing=pairing,
        mapper=options.mapper,
        features=stats,
        timings=timer.freeze(),
        database_path=db_path,
    )
    if best is None or best.num_reg_images() == 0:
        logger.warning("COLMAP built no model from %d images (%d verified pairs)", len(names), stats.num_pairs_verified)
        return _no_model_result(names, **provenance)
    result = _model_result(best, names, model_dir, **provenance)
    logger.info(
        "COLMAP registered %d/%d images, %d points, %.2f px reprojection error (%.1f s)",
        result.num_registered,
        len(names),
        result.num_points,
        result.mean_reprojection_error_px,
        result.timings.total_s,
    )
    return result


def _features_and_matches(
    db_path: Path,
    image_dir: Path,
    names: tuple[str, ...],
    options: ColmapOptions,
    pairing: PairingMode,
    focal_prior_px: float | Sequence[float | None] | None,
    timer: StageTimer,
) -> FeatureStats:
    """Create the database (cameras with the focal priors), extract SIFT and match with ``pairing``."""
    pycolmap.set_random_seed(options.seed)
    create_database(
        db_path,
        image_dir,
        names,
        camera_model=options.camera_model,
        single_camera=options.single_camera,
        focal_prior_px=_as_priors(focal_prior_px, len(names)),
    )
    logger.info(
        "COLMAP cross-check: %d images, %s pairing, %s mapping", len(names), pairing.value, options.mapper.value
    )
    with timer.stage("feature_extraction"):
        extract_sift(db_path, image_dir, names, options.sift)
    with timer.stage("matching"), colmap_log_level():
        _match(db_path, pairing, options)
    return feature_stats(db_path, names)


def _no_model_result(names: tuple[str, ...], **provenance) -> ColmapResult:
    """The NO_MODEL result: nothing registered (identity poses), no points, no model written."""
    n = len(names)
    return ColmapResult(
        status=ColmapStatus.NO_MODEL,
        names=names,
        cam_from_world=np.tile(np.eye(3, 4), (n, 1, 1)),
        registered=np.zeros(n, bool),
        cameras=(None,) * n,
        num_points=0,
        mean_reprojection_error_px=float("nan"),
        model_path=None,
        reconstruction=None,
        **provenance,
    )


def _model_result(best: pycolmap.Reconstruction, names: tuple[str, ...], model_dir: Path, **provenance) -> ColmapResult:
    """Write ``best`` to ``model_dir`` and read its cameras and errors back by image name."""
    write_reconstruction(best, model_dir)
    cam_from_world, registered = cam_from_world_by_name(best, names)
    cameras = tuple(c if r else None for c, r in zip(cameras_by_name(best, names), registered))
    best.update_point_3d_errors()
    return ColmapResult(
        status=ColmapStatus.SUCCESS,
        names=names,
        cam_from_world=cam_from_world,
        registered=registered,
        cameras=cameras,
        num_points=best.num_points3D(),
        mean_reprojection_error_px=float(best.compute_mean_reprojection_error()),
        model_path=model_dir,
        reconstruction=best,
        **provenance,
    )
