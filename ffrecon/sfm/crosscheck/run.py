"""The independent COLMAP reconstruction used to cross-check the feed-forward cameras.

``run_colmap`` is plain COLMAP on the same images: SIFT on the CPU, a pairing strategy, then
mapping. Its choices aim at real captures:

- one shared SIMPLE_RADIAL camera when all images have one size and one focal prior (or none is
  known), a camera per image otherwise;
- focal priors are written as COLMAP *priors*: they calibrate two-view geometry and bundle
  adjustment still refines them. They should come from EXIF only, never from the feed-forward
  model, so that the check stays independent. Where none is given COLMAP reads the file's EXIF
  itself, or guesses 1.2 x the longest side;
- an image counts as registered only when it sees ``min_points_per_image`` model points;
- incremental mapping first, and COLMAP 4's global mapper too when incremental leaves images out
  (forward motion along a street gives small triangulation angles, the hard case for incremental
  SfM); the model with most registered images is kept.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.colmap_io import cam_from_world_by_name, cameras_by_name, write_reconstruction
from ffrecon.geometry.overlap import OverlapGraph
from ffrecon.sfm.crosscheck.mapping import MapperRun, map_images, two_view_run
from ffrecon.sfm.crosscheck.matching import ColmapMatches, match_colmap
from ffrecon.sfm.crosscheck.options import ColmapOptions, MapperKind, PairingMode
from ffrecon.sfm.features import FeatureStats, colmap_log_level
from ffrecon.timing import StageTimer, Timings
from ffrecon.types import PinholeCamera

logger = logging.getLogger("ffrecon.sfm")


class ColmapStatus(enum.Enum):
    SUCCESS = "success"
    NO_MODEL = "no_model"  # mapping built no model (nothing registered)


@dataclass(frozen=True)
class ColmapResult:
    """COLMAP's answer for ``names``; poses are cam_from_world in COLMAP's own world frame.

    Everything but ``reconstruction`` pickles; ``reconstruction`` is read back from ``model_path``.
    """

    status: ColmapStatus
    names: tuple[str, ...]
    cam_from_world: np.ndarray  # [N, 3, 4] float64; identity where not registered
    registered: np.ndarray  # [N] bool
    cameras: tuple[PinholeCamera | None, ...]  # pinhole part of COLMAP's cameras; None if not registered
    num_points: int
    mean_reprojection_error_px: float  # nan without a model
    num_models: int  # models the kept model's mapper built (0 without a model); the kept one is the largest
    pairing: PairingMode  # the pairing that ran (AUTO resolved)
    mapper: MapperKind | None  # the mapper that built the kept model (INCREMENTAL or GLOBAL); None without one
    mapper_runs: tuple[MapperRun, ...]  # every mapper that ran, in order
    shared_camera: bool  # one COLMAP camera for all images
    focal_prior: np.ndarray  # [N] bool: the image's database camera carried a focal-length prior
    camera_groups: np.ndarray  # [N] int: photos of one size and focal prior share a group; 0 is the largest
    features: FeatureStats
    timings: Timings
    database_path: Path
    model_path: Path | None  # out_dir/sparse/0
    reconstruction: pycolmap.Reconstruction | None = field(default=None, repr=False, compare=False)
    # MODEL pairing: the model's overlap graph that chose the pairs (the refinement reuses it; not saved)
    model_overlap: OverlapGraph | None = field(default=None, repr=False, compare=False)

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
            "mapper": None if self.mapper is None else self.mapper.value,
            "mapper_runs": [run.to_report() for run in self.mapper_runs],
            "shared_camera": self.shared_camera,
            "num_focal_priors": int(np.sum(self.focal_prior)),
            "num_camera_groups": int(len(set(self.camera_groups.tolist()))),
            "model_path": None if self.model_path is None else str(self.model_path),
            "timings_s": self.timings.to_report(),
            # user + system CPU seconds of each step: the whole process's, so beside the feed-forward stage
            # they count its CPU too (ffrecon.timing.cpu_seconds)
            "cpu_s": self.timings.cpu_report(),
            "features": self.features.to_report(),
        }


def run_colmap(
    image_dir: Path,
    names: Sequence[str],
    options: ColmapOptions,
    out_dir: Path,
    *,
    focal_prior_px: float | Sequence[float | None] | None,
    step: Callable[[], int] | None = None,
    mask_dir: Path | None = None,
    model_pairs: Sequence[tuple[str, str]] | None = None,
) -> ColmapResult:
    """COLMAP on ``names`` in ``image_dir``; writes ``out_dir/database.db`` and ``out_dir/sparse/0``.

    Args:
        focal_prior_px: focal length in pixels of the images as they are in ``image_dir`` (one value
            for all, or one per image, None where unknown), e.g. from EXIF. Written as a prior that
            bundle adjustment refines. Without it COLMAP reads the file's EXIF itself or guesses
            1.2 x the longest side.
        step: called at the start of each step (extraction, matching, mapping) when COLMAP shares the
            machine (:meth:`ffrecon.concurrency.CoreShare.step`): returns the threads for extraction and
            matching (instead of ``options.num_threads``), or raises to stop between steps.
    Returns:
        A :class:`ColmapResult`; ``status`` is NO_MODEL (not an exception) when nothing registered,
        so that the registration gate can explain why.
    """
    matches = match_colmap(
        image_dir,
        names,
        options,
        out_dir,
        focal_prior_px=focal_prior_px,
        step=step,
        mask_dir=mask_dir,
        model_pairs=model_pairs,
    )
    result = map_colmap(matches, image_dir, options, out_dir, step=step)
    both = Timings(matches.timings.stages + result.timings.stages, matches.timings.cpu + result.timings.cpu)
    return dataclasses.replace(result, timings=both)


def map_colmap(
    matches: ColmapMatches,
    image_dir: Path,
    options: ColmapOptions,
    out_dir: Path,
    *,
    step: Callable[[], int] | None = None,
) -> ColmapResult:
    """COLMAP's mapping of ``matches`` (:func:`ffrecon.sfm.crosscheck.matching.match_colmap`): writes
    ``out_dir/sparse/0``; the result's ``timings`` are the mapping's (``step``: see :func:`run_colmap`)."""
    out_dir, names, db_path = Path(out_dir), matches.names, matches.database_path
    timer = StageTimer()
    if step is not None:
        step()  # mapping keeps its own threads (options.mapper_num_threads)
    with timer.stage("mapping"), colmap_log_level():
        best, run, runs = (None, None, ())
        if matches.features.num_pairs_verified:
            best, run, runs = map_images(db_path, image_dir, out_dir / "mapper", options, len(names))
        if best is None and len(names) == 2 and options.two_view.enabled:
            best, run = two_view_run(db_path, names, options.two_view)
            runs = runs + (run,)
    model_dir = out_dir / "sparse" / "0"
    shutil.rmtree(model_dir, ignore_errors=True)
    provenance = dict(
        num_models=0 if run is None else run.num_models,
        pairing=matches.pairing,
        mapper=None if run is None else run.mapper,
        mapper_runs=runs,
        shared_camera=matches.shared_camera,
        focal_prior=matches.focal_prior,
        camera_groups=matches.camera_groups,
        features=matches.features,
        timings=timer.freeze(),
        database_path=db_path,
        model_overlap=matches.model_overlap,
    )
    if best is None:
        verified = matches.features.num_pairs_verified
        logger.warning("COLMAP built no model from %d images (%d verified pairs)", len(names), verified)
        return _no_model_result(names, **provenance)
    return _logged(_model_result(best, names, model_dir, **provenance))


def _logged(result: ColmapResult) -> ColmapResult:
    logger.info(
        "COLMAP (%s) registered %d/%d images, %d points, %.2f px reprojection error (%.1f s)",
        "ffrecon's two-view reconstruction of its verified matches"
        if result.mapper is MapperKind.TWO_VIEW
        else f"{result.mapper.value} mapper",
        result.num_registered,
        len(result.names),
        result.num_points,
        result.mean_reprojection_error_px,
        result.timings.total_s,
    )
    return result


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
