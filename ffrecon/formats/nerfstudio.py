"""nerfstudio ``transforms.json`` (docs/contracts.md, "Formats written").

``transform_matrix`` is world_from_cam in the OpenGL camera convention (x right, y up, z back):
the OpenCV camera's y and z axes flipped. nerfstudio's rays use pixel centres at +0.5, the same
rule as COLMAP's, so intrinsics pass through unchanged.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ffrecon.geometry.poses import invert_pose, to_homogeneous
from ffrecon.types import PinholeCamera

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def world_from_cam_opengl(cam_from_world: np.ndarray) -> np.ndarray:
    """``[N, 3, 4]`` OpenCV cam_from_world to ``[N, 4, 4]`` OpenGL world_from_cam."""
    return to_homogeneous(invert_pose(cam_from_world)) @ OPENCV_TO_OPENGL


def _intrinsics(cam: PinholeCamera) -> dict:
    return {"fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height}


def _coefficients(d: tuple[float, float, float, float]) -> dict:
    return dict(zip(("k1", "k2", "p1", "p2"), d))


def write_transforms(
    path: Path,
    file_paths: Sequence[str],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    *,
    ply_file_path: str | None = None,
    distortion: Sequence[tuple[float, float, float, float]] | None = None,
    mask_paths: Sequence[str] | None = None,
) -> Path:
    """Write transforms.json; ``file_paths`` (and ``mask_paths``, per frame: 0 where to ignore) are relative
    to the file's folder.

    The first camera's intrinsics go at the top level (tools that read only those still work);
    when cameras differ, each frame carries its own, which nerfstudio's dataparser prefers.
    ``distortion``: per frame OpenCV ``(k1, k2, p1, p2)`` of the (original, distorted) images; when any
    is non-zero the file says ``OPENCV`` and carries them, and nerfstudio undistorts the images itself.
    """
    coeffs = [tuple(float(x) for x in d) for d in distortion] if distortion is not None else None
    opencv = coeffs is not None and any(any(d) for d in coeffs)
    per_frame = [
        {**_intrinsics(c), **(_coefficients(d) if opencv else {})}
        for c, d in zip(cameras, coeffs or [None] * len(cameras), strict=True)
    ]
    shared = all(p == per_frame[0] for p in per_frame)
    out: dict = {"camera_model": "OPENCV" if opencv else "PINHOLE", **per_frame[0]}
    frames = []
    masks = mask_paths if mask_paths is not None else [None] * len(file_paths)
    for fp, mask, pose, own in zip(file_paths, masks, world_from_cam_opengl(cam_from_world), per_frame, strict=True):
        frame = {"file_path": fp, "transform_matrix": pose.tolist(), **({"mask_path": mask} if mask else {})}
        if not shared:
            frame.update(own)
        frames.append(frame)
    out["frames"] = frames
    if ply_file_path:
        out["ply_file_path"] = ply_file_path
    # The poses are in sparse/0's world, untransformed. Saying so stops nerfstudio's data parser from assuming
    # the axis swap of its own ns-process-data (which it does when it finds colmap/sparse/0 and no field).
    out["applied_transform"] = np.eye(3, 4).tolist()
    path.write_text(json.dumps(out, indent=2))
    return path
