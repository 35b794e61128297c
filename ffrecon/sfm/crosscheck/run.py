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
import numbers
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.capture import Capture
from ffrecon.colmap_io import cam_from_world_by_name, cameras_by_name, write_reconstruction
from ffrecon.errors import InputError
from ffrecon.geometry.overlap import OverlapGraph, overlap_graph
from ffrecon.sfm.crosscheck.mapping import MapperRun, map_images, two_view_run
from ffrecon.sfm.crosscheck.options import CameraSharing, ColmapOptions, MapperKind, PairingMode
from ffrecon.sfm.crosscheck.retrieval import check_vocab_tree, retrieval_pairs
from ffrecon.sfm.features import (
    FeatureStats,
    colmap_log_level,
    create_database,
    extract_sift,
    feature_stats,
    focal_prior_flags,
    image_sizes_wh,
    match_pairs,
    matching_options,
    threads_at_most,
)
from ffrecon.timing import StageTimer, Timings
from ffrecon.types import PinholeCamera, Prediction

logger = logging.getLogger("ffrecon.sfm")

# Focal priors closer than this (relative) are one lens setting: EXIF values of one camera are equal.
_SAME_FOCAL_RTOL = 1e-3


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


def resolve_pairing(options: ColmapOptions, num_images: int, *, model: bool = False) -> PairingMode:
    """The pairing the cross-check uses on ``num_images`` photos; ``model``: a feed-forward model runs.

    >>> resolve_pairing(ColmapOptions(), 500, model=True), resolve_pairing(ColmapOptions(), 500)
    (<PairingMode.MODEL: 'model'>, <PairingMode.SEQUENTIAL: 'sequential'>)
    """
    if options.pairing is PairingMode.MODEL and not model:
        raise InputError(
            "model pairing (--pairing model) chooses COLMAP's pairs from the model's cameras, but no model runs",
            "pass --model, or another --pairing (exhaustive, sequential)",
        )
    if options.pairing is not PairingMode.AUTO:
        return options.pairing
    if num_images <= options.exhaustive_max_images:
        return PairingMode.EXHAUSTIVE
    if model:
        return PairingMode.MODEL
    return PairingMode.VOCAB_TREE if options.vocab_tree_path is not None else PairingMode.SEQUENTIAL


def camera_groups(sizes_wh: Sequence[tuple[int, int] | None], focal_prior_px: Sequence[float | None]) -> np.ndarray:
    """``[N]`` int: images of one size and one focal prior (within 0.1 %) form a group, 0 the largest.

    A group stands for one camera at one zoom setting as far as the files tell; unknown sizes or
    priors form groups of their own.

    >>> camera_groups([(640, 480), (640, 480), (800, 600)], [500.0, 500.2, None]).tolist()
    [0, 0, 1]
    """
    keys = [
        (size, None if f is None else round(float(np.log(f)) / np.log1p(1e-3)))
        for size, f in zip(sizes_wh, focal_prior_px)
    ]
    order = sorted(set(keys), key=lambda k: (-keys.count(k), str(k)))
    return np.array([order.index(k) for k in keys], dtype=int)


def resolve_camera_sharing(
    sharing: CameraSharing, sizes_wh: Sequence[tuple[int, int] | None], focal_prior_px: Sequence[float | None]
) -> bool:
    """Whether one COLMAP camera serves all images.

    Args:
        sizes_wh: per image ``(width, height)`` in pixels, None where unreadable.
        focal_prior_px: per image focal prior in pixels, None where unknown.
    AUTO shares when all sizes are known and equal and the priors are either all unknown or all equal
    (within 0.1 %): one phone, one lens setting. Mixed known and unknown priors get a camera each.

    >>> resolve_camera_sharing(CameraSharing.AUTO, [(640, 480)] * 2, [500.0, None])
    False
    """
    one_size = None not in sizes_wh and len(set(sizes_wh)) <= 1
    if sharing is CameraSharing.PER_IMAGE:
        return False
    if sharing is CameraSharing.SHARED:
        if not one_size:
            raise InputError(
                f"one shared camera needs images of one size; these have {sorted(set(map(str, sizes_wh)))}",
                "use a camera per image (camera_sharing=PER_IMAGE) or resize the images alike",
            )
        return True
    known = [float(f) for f in focal_prior_px if f is not None]
    if not known:
        return one_size
    return one_size and len(known) == len(focal_prior_px) and max(known) <= min(known) * (1 + _SAME_FOCAL_RTOL)


def _check_vocab_tree(options: ColmapOptions, what: str) -> str:
    if options.vocab_tree_path is None or not Path(options.vocab_tree_path).is_file():
        raise InputError(
            f"{what} needs a vocabulary tree file (got {options.vocab_tree_path})",
            "download one of COLMAP's vocabulary trees and pass its path, or use sequential pairing",
        )
    return str(check_vocab_tree(options.vocab_tree_path))  # before COLMAP's threads, where a bad tree aborts


def _sequential_pairing(options: ColmapOptions) -> pycolmap.SequentialPairingOptions:
    """Consecutive frames, frames 2^k apart, and, given a vocabulary tree, loop closures."""
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = options.sequential_overlap
    pairing.quadratic_overlap = True
    pairing.num_threads = options.num_threads
    if options.vocab_tree_path is not None:
        pairing.loop_detection = True
        pairing.vocab_tree_path = _check_vocab_tree(options, "loop detection")
    return pairing


def _match(
    db_path: Path,
    mode: PairingMode,
    options: ColmapOptions,
    names: Sequence[str],
    model_pairs: Sequence[tuple[str, str]] | None,
) -> int:
    """Match with ``mode``; returns how many loop candidates retrieval added (sequential without a tree)."""
    matching, verification = matching_options(options.sift)
    common = dict(matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu)
    if mode is PairingMode.MODEL:
        match_pairs(db_path, model_pairs or (), options.sift, db_path.parent / "model_pairs.txt")
    elif mode is PairingMode.EXHAUSTIVE:
        pycolmap.match_exhaustive(str(db_path), **common)
    elif mode is PairingMode.SEQUENTIAL:
        pycolmap.match_sequential(str(db_path), pairing_options=_sequential_pairing(options), **common)
        if options.vocab_tree_path is None:
            loops = retrieval_pairs(db_path, names, options.retrieval)
            if loops:
                match_pairs(db_path, loops, options.sift, db_path.parent / "loop_pairs.txt")
            return len(loops)
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
        pairing = pycolmap.VocabTreePairingOptions()
        pairing.vocab_tree_path = _check_vocab_tree(options, "retrieval pairing")
        pairing.num_threads = options.num_threads
        pycolmap.match_vocabtree(str(db_path), pairing_options=pairing, **common)
    else:
        raise ValueError(f"unresolved pairing mode {mode}")
    return 0


def _as_priors(focal_prior_px: float | Sequence[float | None] | None, n: int) -> list[float | None]:
    """``n`` focal priors in pixels, None where unknown (a non-finite or non-positive value counts as unknown)."""
    if focal_prior_px is None or isinstance(focal_prior_px, numbers.Real):
        values = [focal_prior_px] * n
    else:
        values = list(focal_prior_px)
        if len(values) != n:
            raise ValueError(f"focal_prior_px: expected {n} values, got {len(values)}")
    return [float(f) if f is not None and np.isfinite(f) and f > 0 else None for f in values]


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
    out_dir = Path(out_dir)
    names = tuple(names)
    timer = StageTimer()
    db_path = out_dir / "database.db"
    pairing = resolve_pairing(options, len(names), model=model_pairs is not None)
    if pairing is PairingMode.VOCAB_TREE or (pairing is PairingMode.SEQUENTIAL and options.vocab_tree_path):
        _check_vocab_tree(options, "loop detection" if pairing is PairingMode.SEQUENTIAL else "retrieval pairing")
    priors = _as_priors(focal_prior_px, len(names))
    sizes = image_sizes_wh(image_dir, names)
    shared = resolve_camera_sharing(options.camera_sharing, sizes, priors)
    stats = _features_and_matches(
        db_path, image_dir, names, options, (pairing, model_pairs), priors, shared, timer, step, mask_dir
    )
    if step is not None:
        step()  # mapping keeps its own threads (options.mapper_num_threads)
    with timer.stage("mapping"), colmap_log_level():
        best, run, runs = (None, None, ())
        if stats.num_pairs_verified:
            best, run, runs = map_images(db_path, image_dir, out_dir / "mapper", options, len(names))
        if best is None and len(names) == 2 and options.two_view.enabled:
            best, run = two_view_run(db_path, names, options.two_view)
            runs = runs + (run,)
    model_dir = out_dir / "sparse" / "0"
    shutil.rmtree(model_dir, ignore_errors=True)
    provenance = dict(
        num_models=0 if run is None else run.num_models,
        pairing=pairing,
        mapper=None if run is None else run.mapper,
        mapper_runs=runs,
        shared_camera=shared,
        focal_prior=focal_prior_flags(db_path, names),
        camera_groups=camera_groups(sizes, priors),
        features=stats,
        timings=timer.freeze(),
        database_path=db_path,
    )
    if best is None:
        logger.warning("COLMAP built no model from %d images (%d verified pairs)", len(names), stats.num_pairs_verified)
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


def _features_and_matches(
    db_path: Path,
    image_dir: Path,
    names: tuple[str, ...],
    options: ColmapOptions,
    pairing: tuple[PairingMode, Sequence[tuple[str, str]] | None],
    focal_prior_px: list[float | None],
    shared_camera: bool,
    timer: StageTimer,
    step: Callable[[], int] | None = None,
    mask_dir: Path | None = None,
) -> FeatureStats:
    """Create the database (cameras with the focal priors), extract SIFT and match with ``pairing`` (the mode,
    and the model's pairs for MODEL).

    ``step`` (see :func:`run_colmap`) gives the threads of each of the two steps as it starts.
    """
    pycolmap.set_random_seed(options.seed)
    create_database(
        db_path,
        image_dir,
        names,
        camera_model=options.camera_model,
        single_camera=shared_camera,
        focal_prior_px=focal_prior_px,
    )
    logger.info(
        "COLMAP cross-check: %d images, %s camera, %d focal priors, %s pairing, %s mapping",
        len(names),
        "one shared" if shared_camera else "one per image",
        sum(f is not None for f in focal_prior_px),
        pairing[0].value,
        options.mapper.value,
    )
    with timer.stage("feature_extraction"):
        extract_sift(db_path, image_dir, names, options.sift, threads=step, mask_dir=mask_dir)
    with timer.stage("matching"), colmap_log_level():
        loops = _match(db_path, pairing[0], _with_threads(options, step), names, pairing[1])
    return dataclasses.replace(feature_stats(db_path, names), num_loop_candidates=loops)


def _with_threads(options: ColmapOptions, step: Callable[[], int] | None) -> ColmapOptions:
    """``options`` with at most the threads ``step()`` gives for extraction and matching (unchanged without it).

    >>> _with_threads(ColmapOptions(num_threads=4), lambda: 2).num_threads
    2
    >>> _with_threads(ColmapOptions(), lambda: 1).sift.num_threads  # -1 (all cores) capped
    1
    """
    if step is None:
        return options
    free = step()
    sift = dataclasses.replace(options.sift, num_threads=threads_at_most(options.sift.num_threads, free))
    return dataclasses.replace(options, num_threads=threads_at_most(options.num_threads, free), sift=sift)


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


def pairs_from_model(options: ColmapOptions, num_images: int, *, model: bool) -> bool:
    """Whether the cross-check matches the pairs the model chooses (and so runs after it, not beside it)."""
    return resolve_pairing(options, num_images, model=model) is PairingMode.MODEL


def run_colmap_on(
    capture: Capture,
    options: ColmapOptions,
    out_dir: Path,
    *,
    step: Callable[[], int] | None = None,
    prediction: Prediction | None = None,
) -> ColmapResult:
    """:func:`run_colmap` on a capture's photos. The focal prior of each photo is the given intrinsics' (the
    user's, ``--intrinsics``), else its EXIF focal where known (else COLMAP's own guess), never the model's:
    the cross-check must stay independent evidence of the model's cameras. ``prediction``: the model's, when
    the pairing takes its pairs (:func:`pairs_from_model`); the only thing the cross-check takes from it."""
    priors, masks = capture.focal_priors_px, capture.mask_dir
    pairs = graph = None
    if prediction is not None and pairs_from_model(options, len(capture.names), model=True):
        graph = overlap_graph(prediction, options.model_pairs)
        pairs = [(capture.names[i], capture.names[j]) for i, j in graph.pairs]
    result = run_colmap(
        capture.image_dir,
        capture.names,
        options,
        out_dir,
        focal_prior_px=priors,
        step=step,
        mask_dir=masks,
        model_pairs=pairs,
    )
    return result if graph is None else dataclasses.replace(result, model_overlap=graph)
