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
    per_image_rotation_deg: np.ndarray  # [N], after the best common rotation (not the Sim(3)'s); nan if unregistered
    per_image_center_error: np.ndarray  # [N], reference units, after the Sim(3) fit of centres; nan if unregistered
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


def aligned_rotation_errors_deg(est_R: np.ndarray, ref_R: np.ndarray) -> np.ndarray:
    """``[N]`` angles between ``[N, 3, 3]`` camera rotations (cam_from_world) after the best common world rotation.

    The world rotation is the chordal L2 mean of ``est_R_i^T ref_R_i`` (SVD projection onto SO(3)), the
    usual alignment of rotation-averaging evaluations, refitted without images over three times the median
    error. The rotation of the centres' Sim(3) fit is not used:
    when the centres are nearly collinear (a walk down a street) it is undetermined about the line of
    travel, and the per-image errors would measure the fit instead of the cameras.

    >>> R = np.stack([np.eye(3), np.diag([1.0, -1.0, -1.0])])
    >>> Q = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # a common world rotation
    >>> np.round(aligned_rotation_errors_deg(R @ Q, R), 6).tolist()
    [0.0, 0.0]
    """
    use = np.ones(len(est_R), bool)
    for _ in range(3):  # bounded: the fit, then refits without the images far off (one bad frame must not tilt it)
        u, _, vt = np.linalg.svd(np.einsum("nji,njk->ik", est_R[use], ref_R[use]))
        world = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt  # est world from ref world
        errors = rotation_angle_deg(np.swapaxes(est_R @ world, 1, 2) @ ref_R)
        keep = errors <= 3 * np.median(errors) + 1e-9
        if keep.sum() < 3 or np.array_equal(keep, use):
            break
        use = keep
    return errors


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
        per_rot[reg] = aligned_rotation_errors_deg(est_cam_from_world[reg, :, :3], ref_cam_from_world[reg, :, :3])
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
