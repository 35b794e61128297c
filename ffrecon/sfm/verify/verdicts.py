"""The evidence's words and options: a frame's verdict and status, what decided it, and the result of judging
the final cameras (:func:`ffrecon.sfm.verify.evidence.judge_final_cameras`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from ffrecon.checks import check_number
from ffrecon.sfm.compare.poses import DisagreementOptions
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.verify.photometric import PhotometricOptions


class FrameVerdict(enum.Enum):
    CONFIRMED = "confirmed"  # independent evidence agrees with the model's camera
    CONTRADICTED = "contradicted"  # the evidence disagrees: its own pose replaces the model's, or the frame is left out
    UNCHECKED = "unchecked"  # no evidence either way: the model's camera, marked as such


class CameraStatus(enum.Enum):
    CONFIRMED = "confirmed by COLMAP"  # refined, and COLMAP registered it at an agreeing pose
    REFINED = "refined on image matches"  # bundle-adjusted on its matches; COLMAP did not register it
    COLMAP_ONLY = "COLMAP only"  # not refined, but COLMAP registered it: its pose, moved into the refined frame
    CORRECTED = "corrected by the evidence"  # refined or COLMAP's pose, far from the model's: it replaces it
    DISAGREES = "disagrees with COLMAP"  # refined, but COLMAP placed it elsewhere: left out
    CONTRADICTED = "contradicted by its matches"  # its verified pairs' rotations disagree with its pose: left out
    UNCHECKED = "unchecked"  # no evidence either way: keeps the model's camera
    PLANAR_PAIR = "refined on one planar pair"  # placed by one pair whose matches lie on a plane: ambiguous
    GUIDED = "refined on guided matches"  # look-alike surfaces: its matches were chosen by the model's cameras
    PHOTO_MISFIT = "contradicted by the photos"  # the confirmed frames, seen from its camera, do not look like it
    PART = "refined in a part placed by the model"  # its part shares no point with the rest: placed by the model
    LOOSE = "refined, loosely held"  # its matches let it turn against the other frames at almost no cost
    # refined, and COLMAP registered it a few degrees away (more than EvidenceOptions.max_confirm_gap_deg, not enough
    # to disagree): one of the two is off by more than their noise, and nothing says which; kept, not confirmed
    COLMAP_NEAR = "refined, COLMAP a few degrees away"
    # look-alike surfaces: SIFT left it short and dense tracks moved it a few degrees beyond the model's noise;
    # left out unless the photos fit it there (then GUIDED)
    DENSE_MOVED = "moved by look-alike dense tracks"
    DEPTH_MISFIT = "contradicted by the model's depth"  # its depth, placed with its camera, disagrees with the others'
    # its matches moved it or disputed the model's camera (look-alike surfaces, a relocalisation the adjustment did
    # not keep, pairs far from it), but the photos fit the model's camera as the confirmed frames fit theirs and its
    # depth agrees with the others': it keeps the model's camera (unrefined, without points in sparse/0)
    MODEL_FITS = "the model's camera, which the photos fit"

    @property
    def verdict(self) -> FrameVerdict:
        if self in (CameraStatus.CONFIRMED, CameraStatus.REFINED, CameraStatus.COLMAP_ONLY):
            return FrameVerdict.CONFIRMED
        unchecked = self in (
            CameraStatus.UNCHECKED,
            CameraStatus.PLANAR_PAIR,
            CameraStatus.GUIDED,
            CameraStatus.PART,
            CameraStatus.LOOSE,
            CameraStatus.COLMAP_NEAR,
            CameraStatus.MODEL_FITS,
        )
        return FrameVerdict.UNCHECKED if unchecked else FrameVerdict.CONTRADICTED

    @property
    def kept(self) -> bool:
        """Whether the frame is among the final cameras (the splat's, ``sparse/0``, ``transforms.json``)."""
        left_out = (
            CameraStatus.DISAGREES,
            CameraStatus.CONTRADICTED,
            CameraStatus.PHOTO_MISFIT,
            CameraStatus.DENSE_MOVED,
            CameraStatus.DEPTH_MISFIT,
        )
        return self not in left_out


@dataclass(frozen=True, kw_only=True)
class EvidenceOptions:
    min_refined_ratio: float = 0.85  # images refined with enough inlier observations
    max_reprojection_px: float = 2.0  # mean reprojection error of the refined model
    min_track_length: float = 2.2  # mean observations per refined 3D point
    min_colmap_agreement: float = 0.8  # share of the images both registered on which they agree
    min_common_images: int = 3  # fewer images registered by both: agreement is not judged
    unsuited_share: float = 0.5  # a healthy COLMAP model disagreeing with the model on more: unsuited
    # The evidence moving a frame's rotation further than this from the model's contradicts the model
    # there (feed-forward errors are a few degrees; a frame off by more is a failure of the model).
    max_correction_deg: float = 10.0
    # A refined frame COLMAP registered is confirmed where their rotations, after the alignment over the frames both
    # hold, are at most this far apart; beyond it (up to the disagreement, 5 deg) it is kept unconfirmed
    # (COLMAP_NEAR). On object seed 322 (scale errors) a frame refined 6.5 deg from the truth on weak dense links was
    # 4.3 deg from COLMAP's after the alignment over COLMAP's three frames, and was called confirmed
    max_confirm_gap_deg: float = 2.0
    # On look-alike surfaces, a frame SIFT left short and the dense correspondences (tracked from the model's
    # prediction) moved further than this from the model's rotation is left out: such tracks lock onto the
    # pattern's period nearest the prediction. Good frames moved 1.0-4.0 deg on the repeated-tile street (seed
    # 201, --quick), the frame 25 deg off 7.6 deg (to 15.9 deg from the truth).
    max_lookalike_dense_change_deg: float = 5.0
    # A frame nothing else checks is contradicted when dense tracking from the model's prediction
    # (sfm/refine/dense.py) found almost none of the corners the prediction put inside its overlapping frames,
    # where the other frames tracked found theirs: at least min_dense_predicted corners tried, and a share
    # verified at most dense_misfit_ratio times the median share of the others (at least two of them). On tuning
    # seeds 201-206 (--quick) good frames' share was at least 0.16 of the others' median; frames 25 deg off that
    # dense tracking reached, 0.00-0.06 in half the cases (the rest are judged by the other rules).
    min_dense_predicted: int = 200
    dense_misfit_ratio: float = 0.1
    # A weaker dense sign, counted only beside a photometric one (sfm/verify/unmatched.py, _photometric): at least
    # min_dense_doubt_predicted corners tried, a share verified at most dense_doubt_ratio times the others' median.
    # Held-out room seeds 333 and 337 (session 55): frames 25 deg off tracked 0 of 122 and 84 of 1,810 (0.0 and 0.42
    # times the others' median) where nothing else covered them.
    min_dense_doubt_predicted: int = 100
    dense_doubt_ratio: float = 0.5
    # A frame nothing checks (no verified pair agrees with its camera) is contradicted when the model's own depth,
    # placed with its camera, disagrees with the other frames' depth where they look at the same space
    # (geometry.overlap.view_agreement): its points land in the other frames' views (at least min_view_share of
    # them, summed over the frames) but agree with their depth at most depth_misfit_ratio times as often as the
    # median frame's do. Tuning cases (seeds 201-249): frames 25 deg off 0.01-0.09 of what lands in view agrees
    # (6 of 16; the rest 0.27-0.82), good frames 0.19 at least (184 frames), the median frame 0.3-0.6.
    min_view_share: float = 1.0
    depth_misfit_ratio: float = 0.35
    # Two weak signs agreeing: a frame the depth rule judges whose depth agrees at most depth_doubt_ratio times as
    # often as the median frame's, and whose photo fits the frames around it poorly (PhotometricCheck.poor: what is
    # left to correlate at least poor_factor times the references'), is contradicted. Neither sign alone is enough
    # (good frames the neighbours cover in part fit poorly; good frames' depth agreed down to 0.44 of the median).
    # Measured with every frame at the model's camera on tuning seeds 201-263 (3 families, one frame 25 deg off or
    # drift: 2,835 good frames, 189 bad): both signs on 58 bad frames (33 the depth rule alone misses) and no good
    # one; the good frames fitting poorly agreed at 0.73 of the median at least.
    depth_doubt_ratio: float = 0.6
    min_pair_inliers: int = 10  # verified matches of a pair whose relative rotation counts as evidence
    # A pair with this many verified matches is decisive alone (COLMAP's own bar for an initial pair); a weaker
    # one counts in proportion. A frame the refinement did not hold is contradicted by its pairs only when
    # those that disagree with its model pose outweigh those that agree, and one of them is decisive or
    # there are two or more: one weak pair never removes a frame.
    decisive_pair_inliers: int = 100
    # A refined frame with fewer observations in tracks beyond its main partner hangs on that one pair;
    # if the pair's matches are planar it is unchecked, not confirmed (sfm/verify/support.py)
    min_independent_observations: int = 40
    # A refined frame whose rotation against the other refined frames the matches fix only to more than this (the
    # median standard deviation of its relative rotations at one pixel per observation, sfm/refine/rigidity.py)
    # is unchecked, not confirmed: the adjustment could turn it that far at almost no cost.
    max_rotation_spread_deg: float = 0.6
    max_contradicted_share: float = 0.5  # more frames contradicted: the model fails on this capture (blocks)
    # On look-alike surfaces, more of the refined frames than this moved beyond max_correction_deg: the refinement
    # sits a pattern's period off as a whole and every frame keeps the model's camera (frames.period_off)
    max_period_off_share: float = 0.25
    disagreement: DisagreementOptions = DisagreementOptions()
    photometric: PhotometricOptions = PhotometricOptions()  # frames no match checks, against the photos

    def __post_init__(self) -> None:
        for name in (
            "min_refined_ratio",
            "min_colmap_agreement",
            "unsuited_share",
            "max_contradicted_share",
            "max_period_off_share",
        ):
            check_number(f"EvidenceOptions.{name}", getattr(self, name), low=0, high=1)
        check_number("EvidenceOptions.max_reprojection_px", self.max_reprojection_px, low=0, low_open=True)
        check_number("EvidenceOptions.min_track_length", self.min_track_length, low=0)
        for name in ("min_common_images", "min_independent_observations"):
            check_number(f"EvidenceOptions.{name}", getattr(self, name), low=0, integer=True)
        check_number("EvidenceOptions.min_pair_inliers", self.min_pair_inliers, low=5, integer=True)
        check_number("EvidenceOptions.min_dense_predicted", self.min_dense_predicted, low=1, integer=True)
        check_number("EvidenceOptions.dense_misfit_ratio", self.dense_misfit_ratio, low=0, high=1)
        check_number("EvidenceOptions.min_dense_doubt_predicted", self.min_dense_doubt_predicted, low=1, integer=True)
        check_number("EvidenceOptions.dense_doubt_ratio", self.dense_doubt_ratio, low=0, high=1)
        check_number("EvidenceOptions.depth_misfit_ratio", self.depth_misfit_ratio, low=0, high=1)
        check_number("EvidenceOptions.depth_doubt_ratio", self.depth_doubt_ratio, low=0, high=1)
        check_number("EvidenceOptions.min_view_share", self.min_view_share, low=0)
        check_number("EvidenceOptions.decisive_pair_inliers", self.decisive_pair_inliers, low=1, integer=True)
        check_number("EvidenceOptions.max_rotation_spread_deg", self.max_rotation_spread_deg, low=0, low_open=True)
        for name in ("max_correction_deg", "max_lookalike_dense_change_deg", "max_confirm_gap_deg"):
            check_number(f"EvidenceOptions.{name}", getattr(self, name), low=0, low_open=True, high=180)


@dataclass(frozen=True)
class CameraEvidence:
    name: str
    status: CameraStatus
    why: str
    correction_deg: float = float("nan")  # how far the evidence's rotation is from the model's (nan: no pose)
    # left out on its image matches alone (a pose they gave that is distrusted, or pairs disputing the model's
    # camera), or held loosely by them far from the model (LOOSE), the model's camera not judged by itself: the photos
    # and the depth may keep it (MODEL_FITS)
    matches_only: bool = False

    @property
    def pose_in_doubt(self) -> bool:
        """Whether the photos choose between the model's camera and the pose the matches gave (:attr:`matches_only`)."""
        return self.matches_only and (not self.status.kept or self.status is CameraStatus.LOOSE)

    @property
    def verdict(self) -> FrameVerdict:
        return self.status.verdict

    def to_report(self) -> dict:
        change = self.correction_deg
        return {
            "name": self.name,
            "verdict": self.verdict.value,
            "status": self.status.value,
            "kept": self.status.kept,
            "why": self.why,
            "correction_deg": round(float(change), 4) if np.isfinite(change) else None,
        }


@dataclass(frozen=True)
class EvidenceResult:
    """Verdicts on the final cameras, per-image evidence, and whether the model was set aside."""

    gates: GatesResult
    per_image: tuple[CameraEvidence, ...]
    model_unsuited: bool  # True: COLMAP's cameras are final, the model's were set aside
    unsuited_reason: str = ""
    refinement_set_aside: str = ""  # why the refined cameras were set aside for the model's ("": they were not)

    def count(self, status: CameraStatus | FrameVerdict) -> int:
        if isinstance(status, FrameVerdict):
            return sum(e.verdict is status for e in self.per_image)
        return sum(e.status is status for e in self.per_image)

    def of(self, verdict: FrameVerdict) -> tuple[str, ...]:
        """The names of the frames with that verdict."""
        return tuple(e.name for e in self.per_image if e.verdict is verdict)
