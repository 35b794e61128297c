"""The options of the COLMAP cross-check (:func:`ffrecon.sfm.crosscheck.run.run_colmap`) and the choices they
name, in a module of their own so that mapping (:mod:`ffrecon.sfm.crosscheck.mapping`) and the cross-check both read
them without importing each other."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path

from ffrecon.checks import check_number
from ffrecon.geometry.overlap import OverlapOptions
from ffrecon.sfm.crosscheck.retrieval import RetrievalOptions
from ffrecon.sfm.crosscheck.two_view import TwoViewOptions
from ffrecon.sfm.features import CameraModel, SiftOptions


class MapperKind(enum.Enum):
    # incremental (global from ``global_first_images`` images on), then the other one too when the first
    # leaves images out
    AUTO = "auto"
    INCREMENTAL = "incremental"
    GLOBAL = "global"  # GLOMAP, merged into COLMAP 4
    TWO_VIEW = "two_view"  # ffrecon's own, from COLMAP's verified geometry of two photos (sfm/crosscheck/two_view.py)


class PairingMode(enum.Enum):
    # exhaustive up to ``exhaustive_max_images``; past that the model's pairs when a model runs, else a vocabulary
    # tree if given, else sequential
    AUTO = "auto"
    EXHAUSTIVE = "exhaustive"
    # video order: each frame against its ``sequential_overlap`` successors and successors 2^k apart
    # (quadratic overlap), and against similar-looking frames (loop candidates): by COLMAP's vocabulary tree
    # with ``vocab_tree_path``, else by VLAD over the frames' own SIFT (``retrieval``, ffrecon.sfm.crosscheck.retrieval)
    SEQUENTIAL = "sequential"
    SPATIAL = "spatial"  # nearest GPS positions (needs position priors in the database, e.g. from EXIF)
    VOCAB_TREE = "vocab_tree"  # image retrieval; needs ``vocab_tree_path``
    # The pairs the feed-forward geometry predicts to overlap (ffrecon.geometry.overlap, as the refinement's, loop
    # candidates included): COLMAP still matches, verifies and maps on its own; only the choice of pairs is the
    # model's. The cross-check then waits for the model instead of running beside it.
    MODEL = "model"


class CameraSharing(enum.Enum):
    AUTO = "auto"  # one camera when all images have one size and one focal prior (or none is known)
    SHARED = "shared"  # one camera for all images (they must have one size)
    PER_IMAGE = "per_image"


@dataclass(frozen=True, kw_only=True)
class ColmapOptions:
    enabled: bool = True  # False: the stage is skipped (and the report says so)
    pairing: PairingMode = PairingMode.AUTO
    exhaustive_max_images: int = 150
    sequential_overlap: int = 10
    vocab_tree_path: Path | None = None  # COLMAP vocabulary tree: retrieval pairing, loop detection
    model_pairs: OverlapOptions = OverlapOptions()  # how MODEL pairing picks pairs from the model's geometry
    # SEQUENTIAL without a vocabulary tree: loop candidates from VLAD over the frames' own SIFT
    retrieval: RetrievalOptions = RetrievalOptions()
    mapper: MapperKind = MapperKind.AUTO
    # AUTO maps this many images or more with the global mapper first: on one orbit with the model's pairs,
    # incremental took 16 s at 120 images and 161 s at 400, global 31 s and 160 s (tools/bench_pairing.py)
    global_first_images: int = 400
    # The global mapper positions the cameras on the longest tracks until every image has this many (GLOMAP's
    # track_required_tracks_per_view; 0: every track), then triangulates every track and adjusts them all. On the
    # looped 500-frame bench scene's model pairs (16,714 tracks, 1,757 kept): global positioning 58 -> 11 s,
    # mapping 294 -> 152 s, rotations as accurate (0.016 deg median against the truth either way).
    global_tracks_per_view: int = 200
    camera_model: CameraModel = CameraModel.SIMPLE_RADIAL
    camera_sharing: CameraSharing = CameraSharing.AUTO
    sift: SiftOptions = SiftOptions()
    max_mapping_seconds: int = 600  # per mapper; the incremental mapper stops, global bundle adjustment is capped
    # An image counts as registered when it sees this many model points (COLMAP's incremental mapper
    # registers an image on 30 2D-3D inliers; the global mapper places every connected image, however weak).
    min_points_per_image: int = 30
    num_threads: int = -1  # feature extraction and matching; -1: all cores
    # Two photos that COLMAP's mappers refuse (forward step, small angles) but that verify many matches:
    # ffrecon builds their reconstruction itself from the verified geometry and the EXIF focal prior.
    two_view: TwoViewOptions = TwoViewOptions()
    mapper_num_threads: int = 1  # 1 makes mapping repeatable (COLMAP's multi-threaded solvers are not); -1: all
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("exhaustive_max_images", "min_points_per_image", "global_first_images", "global_tracks_per_view"):
            check_number(f"ColmapOptions.{name}", getattr(self, name), low=0, integer=True)
        check_number("ColmapOptions.sequential_overlap", self.sequential_overlap, low=1, integer=True)
        # COLMAP takes whole seconds, and 0 there means no bound
        check_number("ColmapOptions.max_mapping_seconds", self.max_mapping_seconds, low=1)
