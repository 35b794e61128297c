"""Seed points for the splat: from feed-forward point maps or from a sparse COLMAP model.

Both helpers return ``(xyz [M, 3] float64 world, rgb [M, 3] float32 in [0, 1])``;
:func:`initial_gaussians` turns them into Gaussians the 3DGS way (isotropic, identity rotation,
scale = mean distance to the 3 nearest neighbours, opacity 0.1).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from ffrecon.checks import check_shape
from ffrecon.errors import InputError
from ffrecon.types import Prediction

if TYPE_CHECKING:
    from ffrecon.gaussians import Gaussians

logger = logging.getLogger("ffrecon.splat")


def voxel_downsample(xyz: np.ndarray, rgb: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Average points and colours per voxel (open3d). ``xyz [M, 3]``, ``rgb [M, 3]`` in [0, 1]."""
    import open3d as o3d  # 0.45 s: here, so that the exports' import of this module does not load it

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz, np.float64)))
    pcd.colors = o3d.utility.Vector3dVector(np.asarray(rgb, np.float64))
    down = pcd.voxel_down_sample(float(voxel_size))
    return np.asarray(down.points), np.asarray(down.colors, dtype=np.float32)


def reduce_points(
    xyz: np.ndarray, rgb: np.ndarray, *, voxel_size: float | None, max_points: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Voxel-downsample (automatic voxel size when None) and cap the count at ``max_points``.

    The automatic size starts at 1/500 of the robust extent and is rescaled until 85-100 % of
    ``max_points`` voxels are occupied (point maps sample surfaces, so the count goes like
    1/size^2); what is still over the cap is randomly subsampled with ``seed``.
    """
    if len(xyz) == 0:
        return xyz.reshape(0, 3), rgb.reshape(0, 3).astype(np.float32)
    if voxel_size is not None:
        xyz, rgb = voxel_downsample(xyz, rgb, voxel_size)
    elif len(xyz) > max_points:
        lo, hi = np.percentile(xyz, [2, 98], axis=0)
        size = max(float(np.linalg.norm(hi - lo)) / 500.0, 1e-9)
        down = voxel_downsample(xyz, rgb, size)
        for _ in range(8):
            if 0.85 * max_points <= len(down[0]) <= max_points:
                break
            size *= math.sqrt(len(down[0]) / max_points) * 1.01
            down = voxel_downsample(xyz, rgb, size)
        xyz, rgb = down
        logger.debug("seed voxel size %.4g -> %d points", size, len(xyz))
    if len(xyz) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    return np.asarray(xyz, np.float64), np.asarray(rgb, np.float32)


def seed_from_prediction(
    prediction: Prediction,
    images: Sequence[np.ndarray],
    min_conf: float = 1.0,
    voxel_size: float | None = None,
    max_points: int = 60_000,
    *,
    frames: Sequence[int] | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Fuse the feed-forward depth maps into a coloured seed cloud.

    Args:
        prediction: per-frame depth, confidence and cameras in original-photo pixels.
        images: per frame ``[H_i, W_i, 3]`` uint8 RGB, the same sizes as ``prediction.depth``.
        min_conf: keep pixels with ``depth_conf >= min_conf`` (VGGT confidences are >= 1).
        voxel_size: world units; None picks one so that about ``max_points`` remain.
        max_points: cap on the returned count.
        frames: use only these frames (e.g. the training views, so that held-out views stay unseen).
    Returns:
        ``(xyz [M, 3] float64 world, rgb [M, 3] float32 in [0, 1])``.
    """
    if len(images) != len(prediction):
        raise InputError(
            f"seed_from_prediction: {len(images)} images for {len(prediction)} predicted frames",
            "pass one image per predicted frame",
        )
    use = list(range(len(prediction))) if frames is None else [int(i) for i in frames]
    per_frame = max(1, 8 * max_points // max(len(use), 1))  # bound memory on large photos
    xyz_parts, rgb_parts = [], []
    for i in use:
        image = images[i]
        depth = prediction.depth[i]
        check_shape(f"image {prediction.names[i]}", image, (depth.shape[0], depth.shape[1], 3))
        stride = max(1, math.ceil(math.sqrt(depth.size / per_frame)))
        mask = prediction.valid_mask(i, min_conf)
        sub = np.zeros_like(mask)
        sub[stride // 2 :: stride, stride // 2 :: stride] = True
        mask &= sub
        xyz_parts.append(prediction.world_points(i)[mask])
        rgb_parts.append(image[mask].astype(np.float32) / 255.0)
    xyz, rgb = np.concatenate(xyz_parts), np.concatenate(rgb_parts)
    finite = np.isfinite(xyz).all(1)
    xyz, rgb = xyz[finite], rgb[finite]
    if len(xyz) == 0:
        raise InputError(
            f"no depth pixels with confidence >= {min_conf} to seed the splat",
            "lower min_conf, or seed from the refined sparse model",
        )
    logger.info("seed: %d confident pixels from %d frames", len(xyz), len(use))
    return reduce_points(xyz, rgb, voxel_size=voxel_size, max_points=max_points, seed=seed)


def no_seed_reason(prediction: Prediction, frames: Sequence[int], min_conf: float = 1.0) -> str | None:
    """Why the depth maps of ``frames`` give :func:`seed_from_prediction` no point (no pixel with positive depth
    and confidence >= ``min_conf``: every pixel masked out, or the model unsure everywhere), or None. A
    verdict, not an error: the splat is then skipped with this reason."""
    if any(prediction.valid_mask(int(i), min_conf).any() for i in frames):
        return None
    return (
        f"no point to seed the splat: no depth pixel of the {len(frames)} final frames has confidence >= {min_conf:g}"
    )


def seed_from_reconstruction(rec: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """The 3D points of a COLMAP model: ``(xyz [M, 3] float64, rgb [M, 3] float32 in [0, 1])``."""
    points = list(rec.points3D.values())
    if not points:
        raise InputError(
            "the sparse model has no 3D points to seed the splat", "seed from the feed-forward point maps instead"
        )
    xyz = np.array([p.xyz for p in points], dtype=np.float64)
    rgb = np.array([p.color for p in points], dtype=np.float32) / 255.0
    return xyz, rgb


def nearest_neighbour_log_scales(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """``[M]`` log of the mean distance to the ``k`` nearest other points (open3d KD search).

    Duplicates would give a zero scale, so distances are floored at 1e-3 of the median.
    """
    import open3d as o3d  # 0.45 s: here, so that the exports' import of this module does not load it

    pts = o3d.core.Tensor(np.ascontiguousarray(xyz, dtype=np.float32))
    nns = o3d.core.nns.NearestNeighborSearch(pts)
    nns.knn_index()
    kk = min(k + 1, len(xyz))
    _, dist2 = nns.knn_search(pts, kk)
    dist = np.sqrt(np.maximum(dist2.numpy()[:, 1:].astype(np.float64), 0.0))
    mean = dist.mean(1) if dist.shape[1] else np.ones(len(xyz))
    floor = max(float(np.median(mean)) * 1e-3, 1e-9)
    return np.log(np.maximum(mean, floor))


def initial_gaussians(xyz: np.ndarray, rgb: np.ndarray, *, sh_degree: int, opacity: float = 0.1) -> Gaussians:
    """3DGS initialisation: identity rotations, isotropic nearest-neighbour scales, ``opacity``."""
    from ffrecon.gaussians import Gaussians  # torch: here, only the splat makes Gaussians

    check_shape("seed_xyz", xyz, (None, 3))
    check_shape("seed_rgb", rgb, (len(xyz), 3))
    if len(xyz) < 4:
        raise InputError(
            f"only {len(xyz)} seed points: a splat needs at least 4", "check the depth confidences or the sparse model"
        )
    return Gaussians.from_points(
        xyz, np.clip(rgb, 0.0, 1.0), nearest_neighbour_log_scales(xyz), opacity=opacity, sh_degree=sh_degree
    )
