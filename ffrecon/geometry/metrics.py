"""Pose error as the field reports it (docs/contracts.md, "Pose error").

Relative errors over all pairs i < j: rotation error is the angle of ``R_ij_est^T R_ij_ref``;
translation error the angle between unit relative translations (sign-sensitive, in degrees).
A frame that one side did not register counts as failed (error 180 degrees) in every pair it is in.
ATE is the RMSE of camera centres after a Sim(3) Umeyama fit of estimate to reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ffrecon.geometry.alignment import Sim3, umeyama
from ffrecon.geometry.poses import camera_centers, compose_poses, invert_pose
from ffrecon.geometry.rotations import rotation_angle_deg

THRESHOLDS_DEG = (5, 15, 30)
FAILED_DEG = 180.0


def relative_pose_errors(
    est_cam_from_world: np.ndarray, ref_cam_from_world: np.ndarray, registered: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Relative rotation and translation-direction errors over all pairs i < j.

    Args:
        est_cam_from_world, ref_cam_from_world: ``[N, 3, 4]``.
        registered: ``[N]`` bool, False where the estimate has no pose (counted as failed).
    Returns:
        ``(pairs [M, 2], rot_err_deg [M], trans_err_deg [M])``.
    """
    n = len(ref_cam_from_world)
    reg = np.ones(n, bool) if registered is None else np.asarray(registered, bool)
    i, j = np.triu_indices(n, k=1)
    # cam_j_from_cam_i = cam_j_from_world * world_from_cam_i
    rel_est = compose_poses(est_cam_from_world[j], invert_pose(est_cam_from_world[i]))
    rel_ref = compose_poses(ref_cam_from_world[j], invert_pose(ref_cam_from_world[i]))
    rot_err = rotation_angle_deg(np.swapaxes(rel_est[:, :, :3], 1, 2) @ rel_ref[:, :, :3])
    t_est, t_ref = rel_est[:, :, 3], rel_ref[:, :, 3]
    norm = np.linalg.norm(t_est, axis=1) * np.linalg.norm(t_ref, axis=1)
    cos = np.sum(t_est * t_ref, axis=1) / np.maximum(norm, 1e-15)
    trans_err = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    trans_err = np.where(norm > 1e-15, trans_err, FAILED_DEG)
    failed = ~(reg[i] & reg[j])
    rot_err = np.where(failed, FAILED_DEG, rot_err)
    trans_err = np.where(failed, FAILED_DEG, trans_err)
    return np.stack([i, j], 1), rot_err, trans_err


def auc(max_err_deg: np.ndarray, threshold_deg: int) -> float:
    """Mean over k = 1..threshold of the fraction of pairs with error under k degrees.

    >>> auc(np.array([0.5, 0.5]), 30)
    1.0
    """
    ks = np.arange(1, threshold_deg + 1)
    return float(np.mean([(max_err_deg < k).mean() for k in ks])) if len(max_err_deg) else 0.0


@dataclass(frozen=True)
class PoseErrors:
    """Pose error of an estimate against a reference; angles in degrees."""

    num_images: int
    num_registered: int
    rra: dict[int, float]  # threshold -> fraction of pairs
    rta: dict[int, float]
    auc: dict[int, float]
    ate: float  # RMSE of centres after Sim(3), reference units
    ate_relative: float  # ate / extent of the reference camera centres
    per_image_rotation_deg: np.ndarray  # [N], after the Sim(3) alignment; nan if unregistered
    per_image_center_error: np.ndarray  # [N], reference units; nan if unregistered
    median_rotation_deg: float
    est_to_ref: Sim3 = field(repr=False)

    def to_dict(self) -> dict:
        return {
            "num_images": self.num_images,
            "num_registered": self.num_registered,
            **{f"RRA@{k}": v for k, v in self.rra.items()},
            **{f"RTA@{k}": v for k, v in self.rta.items()},
            **{f"AUC@{k}": v for k, v in self.auc.items()},
            "ATE": self.ate,
            "ATE_relative": self.ate_relative,
            "median_rotation_deg": self.median_rotation_deg,
            "per_image_rotation_deg": [None if not np.isfinite(x) else float(x) for x in self.per_image_rotation_deg],
            "per_image_center_error": [None if not np.isfinite(x) else float(x) for x in self.per_image_center_error],
            "sim3_ref_from_est": {
                "scale": self.est_to_ref.scale,
                "rotation": self.est_to_ref.rotation.tolist(),
                "translation": self.est_to_ref.translation.tolist(),
            },
        }


def pose_errors(
    est_cam_from_world: np.ndarray,
    ref_cam_from_world: np.ndarray,
    registered: np.ndarray | None = None,
    thresholds: tuple[int, ...] = THRESHOLDS_DEG,
) -> PoseErrors:
    """All metrics of docs/contracts.md ("Pose error") for ``[N, 3, 4]`` estimate vs reference.

    ``registered`` marks estimated frames that exist; unregistered ones fail every pair and are left
    out of the Sim(3) fit and the ATE (which is then over registered frames, as is usual).
    """
    n = len(ref_cam_from_world)
    reg = np.ones(n, bool) if registered is None else np.asarray(registered, bool)
    _, rot_err, trans_err = relative_pose_errors(est_cam_from_world, ref_cam_from_world, reg)
    max_err = np.maximum(rot_err, trans_err)
    c_est, c_ref = camera_centers(est_cam_from_world), camera_centers(ref_cam_from_world)
    per_rot = np.full(n, np.nan)
    per_center = np.full(n, np.nan)
    if reg.sum() >= 3:
        sim = umeyama(c_est[reg], c_ref[reg])
    elif reg.sum() >= 1:  # too few centres for Sim(3): align rotation and position of the first frame
        k = int(np.flatnonzero(reg)[0])
        ref_from_est = compose_poses(invert_pose(ref_cam_from_world[k]), est_cam_from_world[k])
        sim = Sim3(1.0, ref_from_est[:, :3], ref_from_est[:, 3])
    else:
        sim = Sim3.identity()
    if reg.any():
        aligned = sim.transform_cam_from_world(est_cam_from_world[reg])
        per_rot[reg] = rotation_angle_deg(np.swapaxes(aligned[:, :, :3], 1, 2) @ ref_cam_from_world[reg][:, :, :3])
        per_center[reg] = np.linalg.norm(sim.apply(c_est[reg]) - c_ref[reg], axis=1)
    ate = float(np.sqrt(np.nanmean(per_center**2))) if reg.any() else float("nan")
    extent = float(np.linalg.norm(c_ref.max(0) - c_ref.min(0)))
    return PoseErrors(
        num_images=n,
        num_registered=int(reg.sum()),
        rra={k: float((rot_err < k).mean()) for k in thresholds},
        rta={k: float((trans_err < k).mean()) for k in thresholds},
        auc={k: auc(max_err, k) for k in thresholds},
        ate=ate,
        ate_relative=ate / extent if extent > 0 else float("nan"),
        per_image_rotation_deg=per_rot,
        per_image_center_error=per_center,
        median_rotation_deg=float(np.nanmedian(per_rot)) if reg.any() else float("nan"),
        est_to_ref=sim,
    )
