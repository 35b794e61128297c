"""Checks on decoded model outputs: cameras, depth and confidence must be usable before anything uses them.

Raw outputs are checked for NaN/inf where they are decoded; this module checks what they *mean*.
An untrained or wrongly exported head can give finite numbers that decode to nonsense: VGGT's
field-of-view ReLU outputs 0 for untrained weights, which is an infinite focal length; downstream,
such a camera turns guided matching into NaNs and can make LAPACK spin forever. So every
prediction is checked here, and a bad one stops the run with a :class:`ModelError` (exit code 3)
that names the output, the frames and the likely cause.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ffrecon.errors import ModelError
from ffrecon.types import Prediction

MIN_FOV_DEG = 1.0  # narrower than any lens photos come from (a 1000 mm lens on full frame is ~2 deg)
MAX_FOV_DEG = 170.0  # wider than a pinhole model can represent usefully (fisheyes need undistortion first)
ROTATION_TOLERANCE = 1e-3  # |R^T R - I| and |det R - 1|
MAX_DEPTH_RATIO = 1e5  # largest / median positive depth of a frame: beyond it, "points at infinity"


@dataclass(frozen=True)
class FrameProblem:
    frame: str
    what: str  # e.g. "focal length fx = inf px (horizontal field of view 0.0 deg)"


def _frames(problems: list[FrameProblem], total: int) -> str:
    shown = ", ".join(f"{p.frame} ({p.what})" for p in problems[:3])
    more = f" and {len(problems) - 3} more" if len(problems) > 3 else ""
    return f"{len(problems)} of {total} frames: {shown}{more}"


def camera_problems(prediction: Prediction) -> list[FrameProblem]:
    """Frames whose intrinsics are not a plausible pinhole camera."""
    problems = []
    for name, cam in zip(prediction.names, prediction.cameras):
        values = np.array([cam.fx, cam.fy, cam.cx, cam.cy], dtype=np.float64)
        if not np.isfinite(values).all() or cam.fx <= 0 or cam.fy <= 0:
            fov = 2 * np.degrees(np.arctan2(cam.width / 2, cam.fx)) if np.isfinite(cam.fx) else 0.0
            problems.append(
                FrameProblem(
                    name,
                    f"focal length fx = {cam.fx:.4g} px, fy = {cam.fy:.4g} px (horizontal field of view {fov:.1f} deg)",
                )
            )
            continue
        fov_w, fov_h = cam.fov_deg()
        if not (MIN_FOV_DEG <= fov_w <= MAX_FOV_DEG and MIN_FOV_DEG <= fov_h <= MAX_FOV_DEG):
            problems.append(
                FrameProblem(
                    name,
                    f"focal length fx = {cam.fx:.4g} px gives a field of view of {fov_w:.2f} x {fov_h:.2f} deg, "
                    f"outside {MIN_FOV_DEG:g}-{MAX_FOV_DEG:g} deg",
                )
            )
    return problems


def pose_problems(prediction: Prediction) -> list[FrameProblem]:
    """Frames whose cam_from_world is not finite or not a rotation plus translation."""
    problems = []
    for name, pose in zip(prediction.names, np.asarray(prediction.cam_from_world, dtype=np.float64)):
        if not np.isfinite(pose).all():
            problems.append(FrameProblem(name, "pose has NaN/inf entries"))
            continue
        rot = pose[:3, :3]
        err = max(float(np.abs(rot.T @ rot - np.eye(3)).max()), abs(float(np.linalg.det(rot)) - 1.0))
        if err > ROTATION_TOLERANCE:
            problems.append(
                FrameProblem(name, f"rotation is not orthonormal (error {err:.2g}; a zero or non-unit quaternion?)")
            )
    return problems


def depth_problems(prediction: Prediction, *, allow_empty: bool = False) -> list[FrameProblem]:
    """Frames with unusable depth or confidence maps (``allow_empty``: a frame with no positive depth is not
    one: the user's masks can clear a whole frame, and it then simply has no depth)."""
    problems = []
    for name, depth, conf in zip(prediction.names, prediction.depth, prediction.depth_conf):
        if not (np.isfinite(depth).all() and np.isfinite(conf).all()):
            problems.append(FrameProblem(name, "depth or confidence has NaN/inf values"))
            continue
        positive = depth[depth > 0]
        if positive.size == 0 and allow_empty:
            continue
        if positive.size == 0:
            problems.append(FrameProblem(name, "depth is zero or negative everywhere"))
            continue
        if float(conf.min()) < 0:
            problems.append(
                FrameProblem(
                    name,
                    f"confidence down to {float(conf.min()):.3g} "
                    "(expected >= 0; a logit exported without its activation?)",
                )
            )
            continue
        ratio = float(positive.max() / max(np.median(positive), 1e-30))
        if ratio > MAX_DEPTH_RATIO:
            problems.append(FrameProblem(name, f"largest depth is {ratio:.3g} times the median (points at infinity)"))
    return problems


def validate_prediction(
    prediction: Prediction,
    *,
    camera_outputs: str = "the camera outputs",
    depth_outputs: str = "depth",
    allow_empty_depth: bool = False,
) -> None:
    """Raise :class:`ModelError` unless every frame has a plausible camera, a rigid pose and usable depth.

    Args:
        camera_outputs, depth_outputs: the model's output names the cameras and depth came from,
            so the message can name them (e.g. ``"pose_enc"``).
        allow_empty_depth: a frame whose depth is zero everywhere passes (the later stages check a prediction
            after the user's masks, which may clear a whole frame; the model's own output was checked whole).
    """
    total = len(prediction)
    model = prediction.model.path
    cams = camera_problems(prediction)
    if cams:
        raise ModelError(
            f"model output '{camera_outputs}' of {model} decodes to an unusable focal length in {_frames(cams, total)}",
            "an untrained or wrongly exported camera head does this "
            "(VGGT's untrained field-of-view ReLU outputs 0, i.e. an infinite focal): "
            "export the model from a trained checkpoint with `ffrecon export-model`, "
            "and check it with `ffrecon inspect-model`",
        )
    poses = pose_problems(prediction)
    if poses:
        raise ModelError(
            f"model output '{camera_outputs}' of {model} decodes to invalid poses in {_frames(poses, total)}",
            "check that the model follows its family's contract (docs/models.md) "
            "and was exported from a trained checkpoint",
        )
    depths = depth_problems(prediction, allow_empty=allow_empty_depth)
    if depths:
        raise ModelError(
            f"model output '{depth_outputs}' of {model} is unusable in {_frames(depths, total)}",
            "re-export the model in fp32 from a trained checkpoint; leave out frames that are blank or overexposed",
        )
