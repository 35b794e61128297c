"""Mapping for the COLMAP cross-check: COLMAP's incremental and global mappers with every solver bounded,
the weak-image rule, the choice of model, and ffrecon's two-view reconstruction as a mapper run.

:func:`ffrecon.sfm.crosscheck.run.run_colmap` calls :func:`map_images` once features are matched.
"""

from __future__ import annotations

import logging
import shutil
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.sfm.crosscheck.options import ColmapOptions, MapperKind
from ffrecon.sfm.crosscheck.two_view import TwoViewOptions, two_view_reconstruction

logger = logging.getLogger("ffrecon.sfm")

# Iteration limits written out (COLMAP's own defaults) so that every solver in mapping is bounded.
_INCREMENTAL_LOCAL_BA_ITERATIONS = 25
_INCREMENTAL_GLOBAL_BA_ITERATIONS = 50
_GLOBAL_BA_ITERATIONS = 200  # per bundle adjustment; the global mapper runs ``ba_num_iterations`` (3) of them


@dataclass(frozen=True)
class MapperRun:
    """What one mapper built: its number of models and the best one's size and error."""

    mapper: MapperKind  # INCREMENTAL, GLOBAL or TWO_VIEW
    num_models: int
    num_registered: int  # images in its best model (most images, then lowest error); 0 without a model
    num_points: int
    mean_reprojection_error_px: float  # of its best model; nan without a model
    num_weak_dropped: int  # images it placed on fewer than ``min_points_per_image`` points, left out (all models)
    seconds: float

    def to_report(self) -> dict:
        error = self.mean_reprojection_error_px
        return {
            "mapper": self.mapper.value,
            "num_models": self.num_models,
            "num_registered": self.num_registered,
            "num_points": self.num_points,
            "mean_reprojection_error_px": float(error) if np.isfinite(error) else None,
            "num_weak_dropped": self.num_weak_dropped,
            "seconds": round(self.seconds, 4),
        }


def _incremental_options(options: ColmapOptions, num_images: int) -> pycolmap.IncrementalPipelineOptions:
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.mapper_num_threads
    mapping.random_seed = options.seed
    mapping.min_model_size = min(3, num_images)
    # Every track of a two-image capture is a two-view track, which COLMAP skips by default.
    mapping.triangulation.ignore_two_view_tracks = num_images > 2
    mapping.max_runtime_seconds = int(options.max_mapping_seconds)
    mapping.ba_local_max_num_iterations = _INCREMENTAL_LOCAL_BA_ITERATIONS
    mapping.ba_global_max_num_iterations = _INCREMENTAL_GLOBAL_BA_ITERATIONS
    return mapping


def _global_options(options: ColmapOptions, num_images: int) -> pycolmap.GlobalPipelineOptions:
    """The global mapper on the CPU, every stage bounded.

    Rotation averaging (5 L1 and 100 IRLS iterations) and global positioning (100 iterations) keep
    COLMAP's limits; each bundle adjustment gets ``_GLOBAL_BA_ITERATIONS`` and a quarter of
    ``max_mapping_seconds``. Cameras are positioned on ``options.global_tracks_per_view`` tracks per image
    (the longest), every track is triangulated afterwards.
    """
    mapping = pycolmap.GlobalPipelineOptions()
    mapping.num_threads = options.mapper_num_threads
    mapping.random_seed = options.seed
    mapping.min_model_size = min(3, num_images)
    mapper = mapping.mapper
    if options.global_tracks_per_view > 0:
        mapper.track_required_tracks_per_view = options.global_tracks_per_view
    mapper.global_positioning.use_gpu = False
    mapper.bundle_adjustment.ceres.use_gpu = False
    solver = mapper.bundle_adjustment.ceres.solver_options
    solver.max_num_iterations = _GLOBAL_BA_ITERATIONS
    solver.max_solver_time_in_seconds = options.max_mapping_seconds / 4
    return mapping


def _run_mapper(
    kind: MapperKind, db_path: Path, image_dir: Path, work_dir: Path, options: ColmapOptions, num_images: int
) -> tuple[list[pycolmap.Reconstruction], MapperRun]:
    """One mapper on the database: its non-empty models and a summary (errors of each model updated)."""
    work_dir = work_dir / kind.value
    shutil.rmtree(work_dir, ignore_errors=True)
    work_dir.mkdir(parents=True)
    start = time.perf_counter()
    if kind is MapperKind.INCREMENTAL:
        mapping = _incremental_options(options, num_images)
        built = pycolmap.incremental_mapping(str(db_path), str(image_dir), str(work_dir), mapping)
    else:
        mapping = _global_options(options, num_images)
        private = _private_copy(db_path, work_dir / "database.db")
        built = pycolmap.global_mapping(str(private), str(image_dir), str(work_dir), mapping)
    seconds = time.perf_counter() - start
    shutil.rmtree(work_dir, ignore_errors=True)
    dropped = sum(drop_weak_images(rec, options.min_points_per_image) for rec in built.values())
    models = [rec for rec in built.values() if rec.num_reg_images() > 0]
    for rec in models:
        rec.update_point_3d_errors()
    best = max(models, key=_model_rank, default=None)
    run = MapperRun(
        mapper=kind,
        num_models=len(models),
        num_registered=0 if best is None else best.num_reg_images(),
        num_points=0 if best is None else best.num_points3D(),
        mean_reprojection_error_px=float("nan") if best is None else float(best.compute_mean_reprojection_error()),
        num_weak_dropped=dropped,
        seconds=seconds,
    )
    return models, run


def _private_copy(db_path: Path, copy_path: Path) -> Path:
    """A copy of the database for COLMAP's global mapper, which writes to the database it is given (its view-graph
    steps rewrite two-view geometries): the refinement reads the same matches in the thread beside the mapping, and
    a write there made the refinement's open fail ("database is locked", reported by pycolmap as "No registered
    database factory succeeded": 2 of about 1,100 sweep runs, exit 1) and could change what it read. SQLite's own
    backup makes the copy, a consistent snapshot however the database is journaled."""
    source = sqlite3.connect(f"{Path(db_path).resolve().as_uri()}?mode=ro", uri=True)
    copy = sqlite3.connect(copy_path)
    try:
        source.backup(copy)
    finally:
        source.close()
        copy.close()
    return copy_path


def drop_weak_images(rec: pycolmap.Reconstruction, min_points: int) -> int:
    """De-register (in place) every image that sees fewer than ``min_points`` 3D points of ``rec``.

    Dropping an image removes its observations, which can leave others short in turn, so this
    repeats until every registered image passes (at most once per image). Returns how many were dropped.
    """
    dropped = 0
    while True:
        weak = {image.frame_id for image in rec.images.values() if image.has_pose and image.num_points3D < min_points}
        if not weak:
            return dropped
        for frame_id in weak:
            rec.deregister_frame(frame_id)
        dropped += len(weak)


def _model_rank(rec: pycolmap.Reconstruction) -> tuple[int, float]:
    """Most registered images first, then the lower mean reprojection error (errors must be updated)."""
    error = float(rec.compute_mean_reprojection_error())
    return rec.num_reg_images(), -error if np.isfinite(error) else -np.inf


def map_images(
    db_path: Path, image_dir: Path, work_dir: Path, options: ColmapOptions, num_images: int
) -> tuple[pycolmap.Reconstruction | None, MapperRun | None, tuple[MapperRun, ...]]:
    """Run the mapper(s) ``options.mapper`` asks for: ``(kept model, the run that built it, all runs)``.

    AUTO runs the incremental mapper (the global one from ``options.global_first_images`` images on) and,
    unless it registered every image in one model, the other mapper too; the model with most registered
    images (then the lower error) is kept.
    """
    if options.mapper is MapperKind.AUTO:
        kinds = (MapperKind.INCREMENTAL, MapperKind.GLOBAL)
        if num_images >= options.global_first_images:
            kinds = kinds[::-1]
            logger.info("%d images: the global mapper first (ColmapOptions.global_first_images)", num_images)
    else:
        kinds = (options.mapper,)
    runs: list[MapperRun] = []
    kept: tuple[pycolmap.Reconstruction, MapperRun] | None = None
    for kind in kinds:
        models, run = _run_mapper(kind, db_path, image_dir, work_dir, options, num_images)
        runs.append(run)
        best = max(models, key=_model_rank, default=None)
        if best is not None and (kept is None or _model_rank(best) > _model_rank(kept[0])):
            kept = (best, run)
        if run.num_models == 1 and run.num_registered == num_images:
            break
        if kind is not kinds[-1]:
            logger.info(
                "%s mapping registered %d/%d images in %d model(s); trying the %s mapper",
                kind.value,
                run.num_registered,
                num_images,
                run.num_models,
                kinds[-1].value,
            )
    shutil.rmtree(work_dir, ignore_errors=True)
    return (None, None, tuple(runs)) if kept is None else (*kept, tuple(runs))


def two_view_run(
    db_path: Path, names: tuple[str, ...], options: TwoViewOptions
) -> tuple[pycolmap.Reconstruction | None, MapperRun]:
    """:func:`~ffrecon.sfm.crosscheck.two_view.two_view_reconstruction` as a mapper run."""
    start = time.perf_counter()
    rec = two_view_reconstruction(db_path, names, options)
    found = rec is not None
    run = MapperRun(
        mapper=MapperKind.TWO_VIEW,
        num_models=int(found),
        num_registered=rec.num_reg_images() if found else 0,
        num_points=rec.num_points3D() if found else 0,
        mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()) if found else float("nan"),
        num_weak_dropped=0,
        seconds=time.perf_counter() - start,
    )
    return rec, run
