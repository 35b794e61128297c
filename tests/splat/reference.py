"""Brute-force per-pixel reference renderer (numpy, float64) for the splat renderer tests.

Written independently of ffrecon.splat.render: it loops over the Gaussians front to back and
evaluates every one at every pixel centre, with the compositing rule stated in ffrecon.splat.raster.

Also the pose-refinement check shared by the CPU and gsplat tests (:func:`check_turned_view_comes_back`).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from ffrecon.geometry.projection import pixel_centers
from ffrecon.geometry.rotations import quat_xyzw_to_matrix, rotation_angle_deg
from ffrecon.splat.optimize import OptimizeOptions, optimize, scene_scale


def random_scene(rng: np.random.Generator, n: int, width: int, height: int, *, sh_bases: int = 1) -> dict:
    """Gaussians in front of an identity camera, spread over the image; K for width x height."""
    f = 0.9 * width
    K = np.array([[f, 0.0, width / 2], [0.0, f * 1.05, height / 2], [0.0, 0.0, 1.0]])
    z = rng.uniform(2.0, 5.0, n)
    xy = rng.uniform(-0.45, 0.45, (n, 2)) * np.array([width / f, height / f]) * z[:, None]
    return {
        "means": np.concatenate([xy, z[:, None]], 1),
        "quats_wxyz": rng.normal(size=(n, 4)),
        "log_scales": np.log(rng.uniform(0.02, 0.12, (n, 3)) * z[:, None] / 4),
        "opacity_logits": rng.normal(0.5, 1.0, n),
        "colors": rng.uniform(0, 1, (n, 3)) if sh_bases == 1 else rng.normal(0, 0.5, (n, sh_bases, 3)),
        "K": K,
    }


def reference_render(
    means,
    quats_wxyz,
    log_scales,
    opacity_logits,
    rgb,
    cam_from_world,
    K,
    width,
    height,
    background,
    *,
    near=0.01,
    eps2d=0.3,
):
    """Returns (rgb [H, W, 3], alpha [H, W], depth [H, W]) in float64."""
    quat_xyzw = np.concatenate([quats_wxyz[:, 1:], quats_wxyz[:, :1]], 1)
    rot_g = quat_xyzw_to_matrix(quat_xyzw)
    cov3 = rot_g @ np.einsum("ni,ij->nij", np.exp(2 * log_scales), np.eye(3)) @ np.swapaxes(rot_g, 1, 2)
    rot, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    pc = means @ rot.T + t
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_x = (cx / fx + 0.15 * width / fx, (width - cx) / fx + 0.15 * width / fx)
    lim_y = (cy / fy + 0.15 * height / fy, (height - cy) / fy + 0.15 * height / fy)
    opacity = 1 / (1 + np.exp(-opacity_logits))
    uv = pixel_centers(height, width)
    color = np.zeros((height, width, 3))
    depth = np.zeros((height, width))
    trans = np.ones((height, width))
    for k in np.argsort(pc[:, 2], kind="stable"):
        x, y, z = pc[k]
        if z <= near:
            continue
        tx, ty = z * np.clip(x / z, -lim_x[0], lim_x[1]), z * np.clip(y / z, -lim_y[0], lim_y[1])
        jac = np.array([[fx / z, 0, -fx * tx / z**2], [0, fy / z, -fy * ty / z**2]])
        cov2 = jac @ rot @ cov3[k] @ rot.T @ jac.T + eps2d * np.eye(2)
        conic = np.linalg.inv(cov2)
        d = uv - np.array([fx * x / z + cx, fy * y / z + cy])
        sigma = 0.5 * np.einsum("hwi,ij,hwj->hw", d, conic, d)
        alpha = np.minimum(0.999, opacity[k] * np.exp(-sigma))
        alpha = np.where(opacity[k] * np.exp(-sigma) > 1 / 255, alpha, 0.0)
        color += (trans * alpha)[..., None] * rgb[k]
        depth += trans * alpha * z
        trans = trans * (1 - alpha)
    color += trans[..., None] * background
    return color, 1 - trans, depth


def turned(cam_from_world: np.ndarray, degrees: float, axis=(0.3, 1.0, 0.2)) -> np.ndarray:
    """The pose rotated by ``degrees`` about ``axis`` (camera frame), the centre kept."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    delta, _ = cv2.Rodrigues(axis * math.radians(degrees))
    rot = delta @ cam_from_world[:, :3]
    center = -cam_from_world[:, :3].T @ cam_from_world[:, 3]
    return np.concatenate([rot, (-rot @ center)[:, None]], axis=1)


def check_turned_view_comes_back(scene, seed, xyz: np.ndarray, device: str = "cpu") -> None:
    """View 3 of ``scene`` turned 2 deg, optimised alone from the Gaussians ``seed`` (views 1.. train): it
    comes back within 1 deg of the truth and every other camera is returned exactly as given. Shared by the
    CPU test (tests/splat/test_pose_refinement.py) and the gsplat one (tests/splat/test_gsplat.py)."""
    poses = np.array(scene.cam_from_world, np.float64)
    poses[3] = turned(poses[3], 2.0)
    images = [torch.from_numpy(im).float() / 255 for im in scene.images]
    Ks = np.stack([scene.camera.K] * len(scene))
    options = OptimizeOptions.brief(
        iterations=240, max_seconds=1e9, densify=None, sh_degree=0, progress=False, device=device
    )
    train = list(range(1, len(scene)))
    result = optimize(seed, images, poses, Ks, train, options, scale=scene_scale(poses, xyz), pose_views=[3])
    before = rotation_angle_deg(poses[3][:, :3] @ scene.cam_from_world[3][:, :3].T)
    after = rotation_angle_deg(result.cam_from_world[3][:, :3] @ scene.cam_from_world[3][:, :3].T)
    assert result.pose_views == (3,)
    assert before == pytest.approx(2.0) and after < 1.0, after
    others = [i for i in range(len(scene)) if i != 3]
    assert np.array_equal(result.cam_from_world[others], poses[others])
