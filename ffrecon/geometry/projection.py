"""Pinhole projection and unprojection.

Pixel-centre rule (the one place it is written down): ffrecon uses COLMAP's convention, where the
centre of the top-left pixel is at (0.5, 0.5) and the image spans [0, W] x [0, H]. The pixel in
row v, column u of an array therefore has its centre at ``(u + 0.5, v + 0.5)``; resizing by s maps
x to ``s * x`` and cropping c pixels maps x to ``x - c``, with no half-pixel terms.
"""

from __future__ import annotations

import numpy as np


def pixel_centers(height: int, width: int) -> np.ndarray:
    """``[H, W, 2]`` (x, y) coordinates of pixel centres, COLMAP convention."""
    ys, xs = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return np.stack([xs, ys], axis=-1)


def flat_pixel_centers(indices: np.ndarray, width: int) -> np.ndarray:
    """``[M, 2]`` (x, y) centres of the pixels at flat (row-major) ``indices`` of an image ``width`` wide: the rows
    of ``pixel_centers(h, width).reshape(-1, 2)[indices]`` without building the whole grid.

    >>> flat_pixel_centers(np.array([0, 5]), 4).tolist()
    [[0.5, 0.5], [1.5, 1.5]]
    """
    return np.stack([indices % width, indices // width], axis=-1) + 0.5


def unproject_depth(depth: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray | None = None) -> np.ndarray:
    """Back-project a z-depth map to 3D points.

    Args:
        depth: ``[H, W]`` z-depth (0 where unknown; those points come out at the camera centre).
        K: ``[3, 3]`` intrinsics for this image size, COLMAP pixel convention.
        cam_from_world: ``[3, 4]``; if given, points are returned in the world frame, else camera.
    Returns:
        ``[H, W, 3]`` float64 points.
    """
    h, w = depth.shape
    return unproject_pixels(pixel_centers(h, w), depth, K, cam_from_world)


def unproject_pixels(
    uv: np.ndarray, depth: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray | None = None
) -> np.ndarray:
    """Back-project pixels ``uv [..., 2]`` (COLMAP convention) at z-depths ``depth [...]`` to ``[..., 3]`` float64
    points, in the world frame when ``cam_from_world [3, 4]`` is given, else the camera's.

    >>> K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    >>> unproject_pixels(np.array([[150.0, 40.0]]), np.array([2.0]), K)
    array([[2., 0., 2.]])
    """
    x = (uv[..., 0] - K[0, 2]) / K[0, 0]
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    pts = np.stack([x * depth, y * depth, depth.astype(np.float64)], axis=-1)
    if cam_from_world is None:
        return pts
    rot, trans = cam_from_world[:3, :3], cam_from_world[:3, 3]
    return (pts - trans) @ rot  # R^T (p - t), row-vector form


def project_points(
    points_world: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Project ``[N, 3]`` world points; returns ``(uv [N, 2] COLMAP convention, depth [N])``."""
    pc = points_world @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = pc[:, 2]
    uv = pc[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
    uv = uv * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    return uv, z
