"""The final cameras judged on evidence: COLMAP is a witness, not the judge.

With a model, the refinement does not need COLMAP's model (it matches with the feed-forward
cameras' overlap, triangulates with them and bundle-adjusts), so COLMAP registering few images
does not stop a run. What decides is the evidence on the **final** cameras:

- the share of images refined with enough inlier observations,
- the mean reprojection error and the mean track length of the refined model,
- agreement with COLMAP on the images both registered (when COLMAP registered a few).

Each image is labelled: confirmed by COLMAP, resting on the model plus bundle adjustment only,
disagreeing with COLMAP, or rejected. A model whose cameras disagree with a healthy COLMAP model on
most images is called unsuited: the run goes on from COLMAP's cameras instead of failing.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ffrecon.checks import check_number
from ffrecon.sfm.compare import DisagreementOptions, compare_poses
from ffrecon.sfm.crosscheck import ColmapResult
from ffrecon.sfm.gates import GatesResult, GateStatus, GateVerdict
from ffrecon.sfm.refine import RefineResult


class CameraStatus(enum.Enum):
    CONFIRMED = "confirmed by COLMAP"  # refined, and COLMAP registered it at an agreeing pose
    MODEL_ONLY = "model + bundle adjustment only"  # refined; COLMAP did not register it
    DISAGREES = "disagrees with COLMAP"  # refined, but COLMAP placed it elsewhere
    COLMAP_ONLY = "COLMAP only"  # not refined, but COLMAP registered it: its pose, moved into the refined frame
    REJECTED = "rejected"  # not refined and not registered by COLMAP: keeps the feed-forward pose, unverified


@dataclass(frozen=True, kw_only=True)
class EvidenceOptions:
    min_refined_ratio: float = 0.85  # images refined with enough inlier observations
    max_reprojection_px: float = 2.0  # mean reprojection error of the refined model
    min_track_length: float = 2.2  # mean observations per refined 3D point
    min_colmap_agreement: float = 0.8  # share of the images both registered on which they agree
    min_common_images: int = 3  # fewer images registered by both: agreement is not judged
    unsuited_share: float = 0.5  # a healthy COLMAP model disagreeing with the model on more: unsuited
    disagreement: DisagreementOptions = DisagreementOptions()

    def __post_init__(self) -> None:
        for name in ("min_refined_ratio", "min_colmap_agreement", "unsuited_share"):
            check_number(f"EvidenceOptions.{name}", getattr(self, name), low=0, high=1)
        check_number("EvidenceOptions.max_reprojection_px", self.max_reprojection_px, low=0, low_open=True)
        check_number("EvidenceOptions.min_track_length", self.min_track_length, low=0)
        check_number("EvidenceOptions.min_common_images", self.min_common_images, low=0, integer=True)


@dataclass(frozen=True)
class CameraEvidence:
    name: str
    status: CameraStatus
    why: str


@dataclass(frozen=True)
class EvidenceResult:
    """Verdicts on the final cameras, per-image evidence, and whether the model was set aside."""

    gates: GatesResult
    per_image: tuple[CameraEvidence, ...]
    model_unsuited: bool  # True: COLMAP's cameras are final, the model's were set aside
    unsuited_reason: str = ""

    def count(self, status: CameraStatus) -> int:
        return sum(e.status is status for e in self.per_image)


def _verdict(name: str, ok: bool, value: float, threshold: float, reason: str, fix: str) -> GateVerdict:
    status = GateStatus.PASS if ok else GateStatus.FAIL
    return GateVerdict(name, status, float(value), float(threshold), reason, "" if ok else fix)


def _track_length(refine: RefineResult) -> float:
    rec = refine.reconstruction
    if rec is None or rec.num_points3D() == 0:
        return float("nan")
    return float(np.mean([p.track.length() for p in rec.points3D.values()]))


def _per_image(names: Sequence[str], refine: RefineResult, colmap: ColmapResult | None, options: EvidenceOptions):
    """Per-image labels, and the refined-vs-COLMAP comparison (None when too few images are shared)."""
    flagged = {w.name: w.describe() for w in refine.flagged}
    common = refine.registered & (colmap.registered if colmap is not None else False)
    comparison = None
    if colmap is not None and common.sum() >= options.min_common_images:
        comparison = compare_poses(
            refine.cam_from_world,
            colmap.cam_from_world,
            names,
            refine.registered,
            ref_registered=colmap.registered,
            estimate="refined",
            reference="COLMAP",
            options=options.disagreement,
        )
    off = {d.name: d.reason for d in comparison.disagreements} if comparison is not None else {}
    out = []
    for k, name in enumerate(names):
        if not refine.registered[k] and comparison is not None and colmap.registered[k]:
            why = f"{flagged.get(name, 'not refined')}; COLMAP registered it, its pose is used"
            out.append(CameraEvidence(name, CameraStatus.COLMAP_ONLY, why))
        elif not refine.registered[k]:
            out.append(CameraEvidence(name, CameraStatus.REJECTED, flagged.get(name, "not refined")))
        elif colmap is None:
            out.append(CameraEvidence(name, CameraStatus.MODEL_ONLY, "no COLMAP cross-check ran"))
        elif not colmap.registered[k]:
            out.append(CameraEvidence(name, CameraStatus.MODEL_ONLY, "COLMAP did not register it"))
        elif name in off:
            out.append(CameraEvidence(name, CameraStatus.DISAGREES, off[name]))
        elif comparison is None:
            out.append(CameraEvidence(name, CameraStatus.MODEL_ONLY, "too few images shared with COLMAP to compare"))
        else:
            out.append(CameraEvidence(name, CameraStatus.CONFIRMED, "COLMAP's pose agrees"))
    return tuple(out), comparison


def _unsuited(
    names: Sequence[str], ff_cam_from_world: np.ndarray, colmap: ColmapResult | None, witness: GatesResult, options
) -> str:
    """Why the model is unsuited ("" if it is not): a healthy COLMAP model disagrees with it on most images."""
    healthy = colmap is not None and not any(v.failed for v in witness.verdicts if v.name != "depth_coverage")
    if not healthy or colmap.num_registered < options.min_common_images:
        return ""
    comp = compare_poses(
        ff_cam_from_world,
        colmap.cam_from_world,
        names,
        None,
        ref_registered=colmap.registered,
        estimate="feed-forward",
        reference="COLMAP",
        options=options.disagreement,
    )
    share = len(comp.disagreements) / max(int(colmap.registered.sum()), 1)
    if share <= options.unsuited_share:
        return ""
    return (
        f"the model's cameras disagree with a healthy COLMAP model on {share:.0%} of the images it registered "
        f"(> {options.unsuited_share:.0%}): the model does not suit these photos, COLMAP's cameras are used"
    )


def judge_final_cameras(
    names: Sequence[str],
    ff_cam_from_world: np.ndarray,
    refine: RefineResult,
    colmap: ColmapResult | None,
    witness: GatesResult,
    options: EvidenceOptions = EvidenceOptions(),
    *,
    force: bool = False,
    colmap_skipped: str = "",
) -> EvidenceResult:
    """Judge the refined cameras on their own evidence and against COLMAP (see the module docstring).

    Args:
        names: the run's images, in order.
        ff_cam_from_world: ``[N, 3, 4]`` the model's cameras (to call the model unsuited).
        refine: the feed-forward-seeded refinement; colmap: the cross-check (None when it did not run).
        witness: the gates on COLMAP's model (a healthy COLMAP model is one that passed them).
        colmap_skipped: why the cross-check did not run (with ``colmap`` None): the agreement verdict
            is SKIPPED, saying so.
    """
    unsuited = _unsuited(names, ff_cam_from_world, colmap, witness, options)
    per_image, comparison = _per_image(names, refine, colmap, options)
    verdicts = _verdicts(len(names), refine, colmap, per_image, comparison is not None, options)
    if colmap is None:
        why = f"COLMAP cross-check not run: {colmap_skipped}" if colmap_skipped else "COLMAP cross-check not run"
        threshold = options.min_colmap_agreement
        verdicts.append(GateVerdict("colmap_agreement", GateStatus.SKIPPED, None, threshold, why))
    if unsuited:  # reported, not blocking: the run goes on from COLMAP's cameras
        verdicts = [
            GateVerdict("model_suited", GateStatus.FAIL, None, options.unsuited_share, unsuited, blocking=False)
        ]
    return EvidenceResult(GatesResult(tuple(verdicts), force), per_image, bool(unsuited), unsuited)


def _verdicts(n, refine: RefineResult, colmap, per_image, compared: bool, options: EvidenceOptions) -> list:
    refined = int(refine.registered.sum())
    err = refine.mean_reprojection_error_px
    track = _track_length(refine)
    verdicts = [
        _verdict(
            "refined_share",
            refined >= options.min_refined_ratio * n,
            refined / max(n, 1),
            options.min_refined_ratio,
            f"{refined} of {n} images refined with enough inlier observations",
            "the rejected images (see the per-image table) lack features or matches: retake them, or drop them",
        ),
        _verdict(
            "reprojection",
            bool(np.isfinite(err) and err <= options.max_reprojection_px),
            err,
            options.max_reprojection_px,
            f"mean reprojection error of the refined model {err:.2f} px",
            "the cameras and points do not fit the matches: check for moving objects or a lens the model misjudged",
        ),
        _verdict(
            "track_length",
            bool(np.isfinite(track) and track >= options.min_track_length),
            track,
            options.min_track_length,
            f"mean track length {track:.2f} observations per point",
            "points are seen in too few images: take photos that overlap more",
        ),
    ]
    if compared:
        both = int((refine.registered & colmap.registered).sum())
        agree = sum(e.status is CameraStatus.CONFIRMED for e in per_image)
        verdicts.append(
            _verdict(
                "colmap_agreement",
                agree >= options.min_colmap_agreement * both,
                agree / max(both, 1),
                options.min_colmap_agreement,
                f"the refined cameras agree with COLMAP on {agree} of the {both} images both registered",
                "the model and COLMAP place the cameras differently: look at the per-image table and the camera plot",
            )
        )
    return verdicts
