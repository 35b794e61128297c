"""The COLMAP cross-check's first half: the database (cameras with the focal priors), SIFT and matching with a
pairing strategy (:func:`match_colmap`). Mapping is the second half (:mod:`ffrecon.sfm.crosscheck.run`); the run
keeps them apart so that the refinement, which reuses these matches, runs beside COLMAP's mapper."""

from __future__ import annotations

import dataclasses
import logging
import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.capture import Capture
from ffrecon.errors import InputError
from ffrecon.geometry.overlap import OverlapGraph, overlap_graph
from ffrecon.sfm.crosscheck.options import CameraSharing, ColmapOptions, PairingMode
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
from ffrecon.types import Prediction

logger = logging.getLogger("ffrecon.sfm")

# Focal priors closer than this (relative) are one lens setting: EXIF values of one camera are equal.
_SAME_FOCAL_RTOL = 1e-3


@dataclass(frozen=True)
class ColmapMatches:
    """COLMAP's database of ``names`` with SIFT and verified matches: what mapping and the refinement read."""

    names: tuple[str, ...]
    database_path: Path
    pairing: PairingMode  # the pairing that ran (AUTO resolved)
    shared_camera: bool  # one COLMAP camera for all images
    focal_prior: np.ndarray  # [N] bool: the image's database camera carried a focal-length prior
    camera_groups: np.ndarray  # [N] int: photos of one size and focal prior share a group; 0 is the largest
    features: FeatureStats
    timings: Timings  # feature_extraction, matching
    # MODEL pairing: the model's overlap graph that chose the pairs (the refinement reuses it; not saved)
    model_overlap: OverlapGraph | None = field(default=None, repr=False, compare=False)

    def to_report(self) -> dict:
        return {
            "pairing": self.pairing.value,
            "database_path": str(self.database_path),
            "timings_s": self.timings.to_report(),
            "cpu_s": self.timings.cpu_report(),  # the whole process's CPU (beside the feed-forward stage, its too)
            "features": self.features.to_report(),
        }


def match_colmap(
    image_dir: Path,
    names: Sequence[str],
    options: ColmapOptions,
    out_dir: Path,
    *,
    focal_prior_px: float | Sequence[float | None] | None,
    step: Callable[[], int] | None = None,
    mask_dir: Path | None = None,
    model_pairs: Sequence[tuple[str, str]] | None = None,
) -> ColmapMatches:
    """The database ``out_dir/database.db`` of ``names`` in ``image_dir``: SIFT and verified matches (see
    :func:`ffrecon.sfm.crosscheck.run.run_colmap` for the arguments)."""
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
    return ColmapMatches(
        names=names,
        database_path=db_path,
        pairing=pairing,
        shared_camera=shared,
        focal_prior=focal_prior_flags(db_path, names),
        camera_groups=camera_groups(sizes, priors),
        features=stats,
        timings=timer.freeze(),
    )


def match_colmap_on(
    capture: Capture,
    options: ColmapOptions,
    out_dir: Path,
    *,
    step: Callable[[], int] | None = None,
    prediction: Prediction | None = None,
) -> ColmapMatches:
    """:func:`match_colmap` on a capture's photos. The focal prior of each photo is the given intrinsics' (the
    user's, ``--intrinsics``), else its EXIF focal where known (else COLMAP's own guess), never the model's:
    the cross-check must stay independent evidence of the model's cameras. ``prediction``: the model's, when
    the pairing takes its pairs (:func:`pairs_from_model`); the only thing the cross-check takes from it."""
    pairs = graph = None
    if prediction is not None and pairs_from_model(options, len(capture.names), model=True):
        graph = overlap_graph(prediction, options.model_pairs)
        pairs = [(capture.names[i], capture.names[j]) for i, j in graph.pairs]
    matches = match_colmap(
        capture.image_dir,
        capture.names,
        options,
        out_dir,
        focal_prior_px=capture.focal_priors_px,
        step=step,
        mask_dir=capture.mask_dir,
        model_pairs=pairs,
    )
    return matches if graph is None else dataclasses.replace(matches, model_overlap=graph)


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


def pairs_from_model(options: ColmapOptions, num_images: int, *, model: bool) -> bool:
    """Whether the cross-check matches the pairs the model chooses (and so runs after it, not beside it)."""
    return resolve_pairing(options, num_images, model=model) is PairingMode.MODEL
