"""Rigid poses as ``[..., 3, 4]`` arrays ``[R | t]``; names carry the frames (``b_from_a``)."""

from __future__ import annotations

import numpy as np


def invert_pose(b_from_a: np.ndarray) -> np.ndarray:
    """``[..., 3, 4]`` b_from_a to a_from_b.

    >>> p = np.concatenate([np.eye(3), [[1.0], [2.0], [3.0]]], axis=1)
    >>> invert_pose(p)[:, 3]
    array([-1., -2., -3.])
    """
    rot = b_from_a[..., :3, :3]
    rot_t = np.swapaxes(rot, -1, -2)
    trans = -np.einsum("...ij,...j->...i", rot_t, b_from_a[..., :3, 3])
    return np.concatenate([rot_t, trans[..., None]], axis=-1)


def compose_poses(c_from_b: np.ndarray, b_from_a: np.ndarray) -> np.ndarray:
    """``c_from_a = c_from_b * b_from_a`` for ``[..., 3, 4]`` poses (broadcasting)."""
    rot = c_from_b[..., :3, :3] @ b_from_a[..., :3, :3]
    trans = np.einsum("...ij,...j->...i", c_from_b[..., :3, :3], b_from_a[..., :3, 3]) + c_from_b[..., :3, 3]
    return np.concatenate([rot, trans[..., None]], axis=-1)


def transform_points(b_from_a: np.ndarray, points_a: np.ndarray) -> np.ndarray:
    """Apply a ``[3, 4]`` pose to ``[..., 3]`` points."""
    return points_a @ b_from_a[:3, :3].T + b_from_a[:3, 3]


def camera_centers(cam_from_world: np.ndarray) -> np.ndarray:
    """``[N, 3, 4]`` cam_from_world to ``[N, 3]`` camera centres in the world frame."""
    return invert_pose(cam_from_world)[..., :3, 3]


def to_homogeneous(pose: np.ndarray) -> np.ndarray:
    """``[..., 3, 4]`` to ``[..., 4, 4]``."""
    bottom = np.zeros(pose.shape[:-2] + (1, 4))
    bottom[..., 0, 3] = 1.0
    return np.concatenate([pose, bottom], axis=-2)


def look_at_cam_from_world(
    center: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])
) -> np.ndarray:
    """OpenCV camera at ``center`` looking at ``target`` (y down, so ``up`` points image-up)."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    rot = np.stack([x, y, z])  # rows: camera axes in the world frame
    return np.concatenate([rot, (-rot @ center)[:, None]], axis=1)


def up_from_cameras(cam_from_world: np.ndarray) -> np.ndarray:
    """``[3]`` unit world direction of the mean image-up axis (-y of OpenCV cameras).

    >>> (up_from_cameras(np.eye(3, 4)[None]) + 0.0).tolist()  # identity camera: image-up is world -y
    [0.0, -1.0, 0.0]
    """
    up = -cam_from_world[:, 1, :3].sum(axis=0)  # row 1 of R is the camera y axis in world coordinates
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])
