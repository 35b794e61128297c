"""The refinement's options, quick mode's preset, its inputs and its result types
(:func:`ffrecon.sfm.refine.run.run_refine`)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.checks import check_number
from ffrecon.geometry.alignment import Sim3
from ffrecon.geometry.overlap import OverlapGraph, OverlapOptions
from ffrecon.sfm.features import FeatureStats, SiftOptions
from ffrecon.sfm.refine.bundle import BundleOptions, BundleSummary
from ffrecon.sfm.refine.carry import Carry
from ffrecon.sfm.refine.dense import DenseOptions, DenseStats
from ffrecon.sfm.refine.guided import GuidanceOptions, GuidanceStats
from ffrecon.sfm.refine.links import LinkOptions
from ffrecon.sfm.refine.relocalize import Relocalized, RelocalizeOptions
from ffrecon.sfm.refine.screen import ScreenOptions, Suspect
from ffrecon.timing import Timings
from ffrecon.types import PinholeCamera

# Quick mode's refinement (RefineOptions.quick); measured in docs/pipeline.md, "Quick mode".
QUICK_SIFT = SiftOptions(
    first_octave=0, upsample_below_px=500, coarse_from_images=48, max_image_size=1600, max_num_features=4096
)
QUICK_OVERLAP = OverlapOptions(max_pairs_per_image=4)
QUICK_BUNDLE = BundleOptions(max_refinements=1, fine_function_tolerance=1e-6)


class RefineStatus(enum.Enum):
    SUCCESS = "success"  # every frame refined
    PARTIAL = "partial"  # some frames flagged and kept out, the others refined
    FAILED = "failed"  # fewer than two frames could be refined: the feed-forward cameras are returned


class WeakReason(enum.Enum):
    FEW_FEATURES = "few_features"  # too few SIFT keypoints (textureless, blurred, dark)
    FEW_MATCHES = "few_matches"  # features, but too few verified matches with overlapping frames
    FEW_OBSERVATIONS = "few_observations"  # too few triangulated observations survive refinement
    WEAK_LINK = "weak_link"  # held to the other refined frames only by weak links or ones the model contradicts
    LOST_CENTRE = "lost_centre"  # its refined centre ended further from the model's than the cameras' extent


@dataclass(frozen=True)
class WeakFrame:
    name: str
    reason: WeakReason
    value: int  # keypoints, verified matches, observations or shared points
    threshold: int

    def describe(self) -> str:
        if self.reason is WeakReason.LOST_CENTRE:
            return (
                f"{self.name}: its refined centre ended {self.value} % of the cameras' extent from the model's "
                f"(> {self.threshold} %): the adjustment lost its position; kept out of the refinement"
            )
        if self.reason is WeakReason.WEAK_LINK:
            return (
                f"{self.name}: held to the other refined frames only by links of under {self.threshold} shared 3D "
                "points or links whose relative rotation the model's contradicts (its strongest such link: "
                f"{self.value} points); kept out of the refinement"
            )
        what = {
            WeakReason.FEW_FEATURES: "SIFT keypoints",
            WeakReason.FEW_MATCHES: "verified matches",
            WeakReason.FEW_OBSERVATIONS: "triangulated observations",
        }[self.reason]
        return f"{self.name}: {self.value} {what} (< {self.threshold}); kept out of the refinement"


@dataclass(frozen=True, kw_only=True)
class RefineOptions:
    enabled: bool = True  # False: the stage is skipped (and the report says so)
    overlap: OverlapOptions = OverlapOptions()
    sift: SiftOptions = SiftOptions()
    bundle: BundleOptions = BundleOptions()
    guidance: GuidanceOptions = GuidanceOptions()
    dense: DenseOptions = DenseOptions()  # model-guided correspondences for the frames SIFT leaves short
    # Frames the first adjustment leaves out placed again from their neighbours' renderings (with dense evidence)
    relocalize: RelocalizeOptions = RelocalizeOptions()
    # Frames held to the others only by weak links, or by links the model contradicts, are left out (refine/links.py)
    links: LinkOptions = LinkOptions()
    # Frames whose verified pairs agree on a rotation far from the model's start the adjustment from it
    screen: ScreenOptions = ScreenOptions()
    single_camera: bool = True  # one shared camera (median feed-forward intrinsics) if all images share a size
    square_pixels: bool = True  # one focal length per camera (fx = fy)
    min_features: int = 100
    min_matches: int = 50  # verified matches summed over the frame's pairs
    min_observations: int = 40
    seed: int = 0
    # With given poses (--poses): the adjustment keeps the camera centres near them, with this std (a fraction
    # of the extent of the centres), instead of letting the feed-forward ones move freely.
    given_pose_std: float = 0.002

    def __post_init__(self) -> None:
        for name in ("min_features", "min_matches", "min_observations"):
            check_number(f"RefineOptions.{name}", getattr(self, name), low=0, integer=True)
        check_number("RefineOptions.given_pose_std", self.given_pose_std, low=0, low_open=True)

    @classmethod
    def quick(cls, **overrides) -> RefineOptions:
        """The refinement of quick mode (``--quick``), where there is no cross-check's SIFT to reuse.

        It extracts SIFT itself, lighter than COLMAP's default: no 2x upsampled first octave (unless
        the image's long side is under 500 px), images at most 1600 px, 4096 features. It matches fewer
        overlapping pairs (at most 4 well-overlapping ones chosen per image, instead of 12) and runs one
        round of the fine pass (instead of up to 5). On the 48-frame 640 x 480 demo scene it takes about
        a third of the time COLMAP alone takes on the same images (2.8-3.0x faster), as accurate
        (docs/pipeline.md, "Quick mode").
        ``overrides`` replace fields of the preset.
        """
        preset = {"sift": QUICK_SIFT, "overlap": QUICK_OVERLAP, "bundle": QUICK_BUNDLE}
        return cls(**{**preset, **overrides})


def key_options(options: RefineOptions) -> object:
    """What the refinement's resume key hashes for ``options``: their repr as it read while the features to reuse
    were an option (``reuse_features_from=None``: a run never set it), so that moving them to
    :class:`RefineInputs` left the key of the same options the same."""
    text = repr(options)
    at = text.rfind(", single_camera=")
    return _Shown(text[:at] + ", reuse_features_from=None" + text[at:])


class _Shown:
    """An object whose repr is ``text`` (what a resume key hashes)."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __repr__(self) -> str:
        return self.text


@dataclass(frozen=True)
class RefineInputs:
    """What the refinement runs on besides the prediction: the run's files and what the stages before it made.
    Not options: they are not in its resume key (the keys of the stages that made them are)."""

    image_dir: Path  # the images named in the prediction
    mask_dir: Path | None = None  # COLMAP's masks of those images (``<name>.png``, 0: no features there); None: none
    reuse_features_from: Path | None = None  # a COLMAP database with SIFT of the same images (the cross-check's)
    # Frames whose poses (the user's, --poses) stay as the prediction holds them: never reseeded, relocalised
    # or registered again, constant in every adjustment.
    fixed: frozenset[str] = frozenset()
    # The prediction's overlap graph when already made under ``RefineOptions.overlap`` (the cross-check's model
    # pairing: 28 s at 500 frames); None: made by the refinement.
    graph: OverlapGraph | None = None


@dataclass(frozen=True)
class RefineResult:
    """Refined cameras in the prediction's world frame (same scale and origin, up to the fit)."""

    status: RefineStatus
    names: tuple[str, ...]
    cam_from_world: np.ndarray  # [N, 3, 4] float64; flagged frames keep their feed-forward pose
    registered: np.ndarray  # [N] bool, True where refined
    cameras: tuple[PinholeCamera, ...]  # refined intrinsics (feed-forward ones where not refined)
    # Per frame OpenCV (k1, k2, p1, p2) of the refined lens (zeros where not refined); None: no distortion kept.
    distortion: tuple[tuple[float, float, float, float], ...] | None
    flagged: tuple[WeakFrame, ...]
    points_xyz: np.ndarray  # [M, 3] float64, prediction's world frame
    points_rgb: np.ndarray  # [M, 3] uint8
    num_pairs: int  # image pairs matched
    features: FeatureStats
    guidance: GuidanceStats | None  # None without feed-forward guidance of the matching
    screened: tuple[Suspect, ...]  # frames whose verified pairs put them far from the model's rotation
    dense: DenseStats | None  # None: no frame was short of SIFT matches (or dense evidence is off)
    relocalized: tuple[Relocalized, ...]  # frames placed again from their neighbours' renderings
    bundle: BundleSummary | None
    mean_reprojection_error_px: float
    ff_from_refined: Sim3 = field(repr=False)
    timings: Timings
    model_path: Path | None  # out_dir/refine/model: the refined frames and points (sparse/0 adds the others)
    database_path: Path | None  # the refinement's COLMAP database (SIFT and dense matches), out_dir/refine
    observations: np.ndarray | None  # [N] int, triangulated observations per frame in the refined model
    reconstruction: pycolmap.Reconstruction | None = field(default=None, repr=False, compare=False)
    # [N] each frame's largest overlap with another frame, as the model's cameras and depth predict it (the larger
    # direction, OverlapGraph.reach); empty where the refinement did not build the graph
    overlap_reach: tuple[float, ...] = ()
    # The refined frames grouped into parts that share no 3D point, largest first, where there are two or more:
    # each part was placed by the model's cameras of its frames (refine/components.py); empty: one part
    parts: tuple[tuple[str, ...], ...] = ()
    # [N] how firmly the matches fix each frame's rotation against the other refined frames: the median standard
    # deviation (deg) of its relative rotations at one pixel per observation (refine/rigidity.py); nan where not
    # refined; empty where not estimated
    rotation_spread_deg: tuple[float, ...] = ()
    # How the frames not refined were placed: carried along with their refined neighbours, or at the model's
    # cameras (refine/carry.py); None where nothing was chosen (none left out, or too few refined)
    carry: Carry | None = None

    def to_report(self) -> dict:
        err = self.mean_reprojection_error_px
        return {
            "status": self.status.value,
            "num_images": len(self.names),
            "num_refined": int(self.registered.sum()),
            "flagged": [
                {
                    "name": w.name,
                    "reason": w.reason.value,
                    "value": w.value,
                    "threshold": w.threshold,
                    "message": w.describe(),
                }
                for w in self.flagged
            ],
            "num_points": int(len(self.points_xyz)),
            "num_pairs_matched": self.num_pairs,
            "mean_reprojection_error_px": float(err) if np.isfinite(err) else None,
            "lens_k1": None if self.distortion is None else _median_k1(self.distortion, self.registered),
            "match_guidance": None if self.guidance is None else self.guidance.to_report(),
            "screened": [s.to_report(self.names) for s in self.screened],
            "dense_evidence": None if self.dense is None else self.dense.to_report(),
            "relocalized": [r.to_report(self.names) for r in self.relocalized],
            "bundle_adjustment": None if self.bundle is None else self.bundle.to_report(),
            "sim3_ff_from_refined_scale": self.ff_from_refined.scale,
            "model_path": None if self.model_path is None else str(self.model_path),
            "timings_s": self.timings.to_report(),
            "cpu_s": self.timings.cpu_report(),
            "features": self.features.to_report(),
            "overlap_reach": {n: round(float(r), 3) for n, r in zip(self.names, self.overlap_reach)},
            "parts": [list(p) for p in self.parts],
            "rotation_spread_deg": {
                n: round(s, 3) for n, s in zip(self.names, self.rotation_spread_deg) if np.isfinite(s)
            },
            "carry": None if self.carry is None else self.carry.to_report(self.names),
        }


def _median_k1(distortion: tuple[tuple[float, ...], ...], registered: np.ndarray) -> float:
    return float(np.median([d[0] for d, r in zip(distortion, registered) if r]))
