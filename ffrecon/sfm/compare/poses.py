"""Pose comparison of two camera sets (docs/contracts.md, "Pose error") and the images where they disagree.

Used for feed-forward vs COLMAP (the cross-check), and for any estimate vs ground truth (the
synthetic demo, or a reference COLMAP model passed with ``--reference``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.checks import check_number
from ffrecon.colmap_io import cam_from_world_by_name
from ffrecon.geometry.metrics import PoseErrors, pose_errors
from ffrecon.geometry.poses import camera_centers

logger = logging.getLogger("ffrecon.sfm")


@dataclass(frozen=True, kw_only=True)
class DisagreementOptions:
    """An image disagrees when, after the alignment (:func:`~ffrecon.geometry.metrics.pose_errors`), either error
    exceeds its threshold."""

    max_rotation_deg: float = 5.0
    max_center_error: float = 0.05  # as a fraction of the extent of the reference camera centres

    def __post_init__(self) -> None:
        check_number("DisagreementOptions.max_rotation_deg", self.max_rotation_deg, low=0, low_open=True, high=180)
        check_number("DisagreementOptions.max_center_error", self.max_center_error, low=0, low_open=True)


@dataclass(frozen=True)
class Disagreement:
    name: str
    rotation_deg: float  # nan if the estimate has no pose for it
    center_error: float  # reference units; nan if no pose
    reason: str


@dataclass(frozen=True)
class PoseComparison:
    """Errors of ``estimate`` against ``reference`` over the images the reference has.

    Per-image arrays are over all ``names`` (nan where either side has no pose).
    """

    estimate: str  # label, e.g. "feedforward"
    reference: str  # label, e.g. "colmap" or "ground_truth"
    names: tuple[str, ...]
    errors: PoseErrors  # over the images in the reference; estimate-unregistered ones count as failed
    in_reference: np.ndarray  # [N] bool
    registered: np.ndarray  # [N] bool, estimate has a pose
    per_image_rotation_deg: np.ndarray  # [N]
    per_image_center_error: np.ndarray  # [N], reference units
    aligned_centers: np.ndarray  # [N, 3] estimate centres mapped into the reference frame (nan if no pose)
    reference_centers: np.ndarray  # [N, 3] (nan where not in the reference)
    disagreements: tuple[Disagreement, ...]

    @property
    def disagreeing(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.disagreements)

    def to_report(self) -> dict:
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        metrics = self.errors.to_dict()
        for key in ("per_image_rotation_deg", "per_image_center_error"):
            metrics.pop(key)
        return {
            "estimate": self.estimate,
            "reference": self.reference,
            "metrics": metrics,
            "not_in_reference": [n for n, r in zip(self.names, self.in_reference) if not r],
            "per_image": {
                n: {"rotation_deg": num(r), "center_error": num(c), "registered": bool(g)}
                for n, r, c, g in zip(
                    self.names, self.per_image_rotation_deg, self.per_image_center_error, self.registered
                )
            },
            "disagreeing": [
                {
                    "name": d.name,
                    "rotation_deg": num(d.rotation_deg),
                    "center_error": num(d.center_error),
                    "reason": d.reason,
                }
                for d in self.disagreements
            ],
        }


def compare_poses(
    est_cam_from_world: np.ndarray,
    ref_cam_from_world: np.ndarray,
    names: Sequence[str],
    registered: np.ndarray | None,
    *,
    ref_registered: np.ndarray | None = None,
    estimate: str = "estimate",
    reference: str = "reference",
    options: DisagreementOptions = DisagreementOptions(),
    centers: bool = True,
) -> PoseComparison:
    """Sim(3)-align ``est`` to ``ref`` and compute section-5 metrics plus the disagreeing images.

    Args:
        est_cam_from_world, ref_cam_from_world: ``[N, 3, 4]`` OpenCV poses for the same ``names``.
        registered: ``[N]`` bool, estimate has a pose (None: all). Unregistered images count as
            failed in every pair and are listed as disagreeing.
        ref_registered: ``[N]`` bool, reference has a pose (None: all). Images missing from the
            reference are left out of the metrics (nothing to compare with) and reported as such.
        centers: whether a centre error alone makes an image disagree (False: rotations only, for a reference
            whose centres are not to be trusted; the centre errors are measured and reported all the same).
    """
    names = tuple(names)
    n = len(names)
    reg = np.ones(n, bool) if registered is None else np.asarray(registered, bool)
    in_ref = np.ones(n, bool) if ref_registered is None else np.asarray(ref_registered, bool)
    idx = np.flatnonzero(in_ref)
    if len(idx) == 0:
        raise ValueError(f"pose comparison needs images with a {reference} pose, got none")
    errors = pose_errors(est_cam_from_world[idx], ref_cam_from_world[idx], reg[idx])
    rot = np.full(n, np.nan)
    center = np.full(n, np.nan)
    rot[idx] = errors.per_image_rotation_deg
    center[idx] = errors.per_image_center_error
    aligned = np.full((n, 3), np.nan)
    aligned[reg] = errors.est_to_ref.apply(camera_centers(est_cam_from_world[reg]))
    ref_centers = np.full((n, 3), np.nan)
    ref_centers[in_ref] = camera_centers(ref_cam_from_world[in_ref])
    extent = float(np.linalg.norm(np.ptp(ref_centers[in_ref], axis=0))) if in_ref.any() else 0.0
    max_center = options.max_center_error * extent
    found = []
    for k in idx:
        if not reg[k]:
            found.append(Disagreement(names[k], np.nan, np.nan, f"not registered by {estimate}"))
            continue
        reasons = []
        if rot[k] > options.max_rotation_deg:
            reasons.append(f"rotation off by {rot[k]:.1f} deg (> {options.max_rotation_deg:g})")
        if centers and center[k] > max_center:
            reasons.append(
                f"centre off by {center[k] / extent:.1%} of the camera extent (> {options.max_center_error:.0%})"
            )
        if reasons:
            found.append(Disagreement(names[k], float(rot[k]), float(center[k]), "; ".join(reasons)))
    if found:
        logger.info("%s vs %s: %d images disagree", estimate, reference, len(found))
    return PoseComparison(
        estimate, reference, names, errors, in_ref, reg, rot, center, aligned, ref_centers, tuple(found)
    )


def compare_models(
    est_model: Path | pycolmap.Reconstruction,
    ref_model: Path | pycolmap.Reconstruction,
    names: Sequence[str],
    *,
    estimate: str = "estimate",
    reference: str = "reference",
    options: DisagreementOptions = DisagreementOptions(),
) -> PoseComparison:
    """:func:`compare_poses` on two COLMAP models (folders or loaded), matched by image name."""
    est = est_model if isinstance(est_model, pycolmap.Reconstruction) else pycolmap.Reconstruction(str(est_model))
    ref = ref_model if isinstance(ref_model, pycolmap.Reconstruction) else pycolmap.Reconstruction(str(ref_model))
    est_poses, est_reg = cam_from_world_by_name(est, names)
    ref_poses, ref_reg = cam_from_world_by_name(ref, names)
    return compare_poses(
        est_poses,
        ref_poses,
        names,
        est_reg,
        ref_registered=ref_reg,
        estimate=estimate,
        reference=reference,
        options=options,
    )
