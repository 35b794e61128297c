"""Fused, coloured point clouds from depth maps (open3d for downsampling and PLY I/O)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ffrecon.checks import check_number
from ffrecon.geometry.projection import flat_pixel_centers, unproject_pixels
from ffrecon.types import Prediction

log = logging.getLogger("ffrecon.export")


@dataclass(frozen=True, kw_only=True)
class FuseOptions:
    conf_quantile: float = 0.3  # drop the least confident 30% of each frame's valid pixels
    min_conf: float = 1.0
    voxel_fraction: float = 1 / 250  # voxel size as a fraction of the cloud's robust extent
    # A frame's pixels fused, at most (evenly thinned). 100,000, not 200,000 (issue 40): the voxel (voxel_fraction of
    # the extent) holds a dozen pixels or more where a frame sees a surface closely, and the fusion is most of the
    # feed-forward stage's own CPU. On 24 frames of 640x480 (the bench_run scene) it took 1.47 -> 1.12 CPU s and
    # kept 98.4 % of the voxels (206,749 -> 203,527 points)
    max_points_per_frame: int = 100_000
    remove_outliers: bool = True

    def __post_init__(self) -> None:
        check_number("FuseOptions.conf_quantile", self.conf_quantile, low=0, high=1)
        check_number("FuseOptions.min_conf", self.min_conf, low=0)
        check_number("FuseOptions.voxel_fraction", self.voxel_fraction, low=0, low_open=True)
        check_number("FuseOptions.max_points_per_frame", self.max_points_per_frame, low=1, integer=True)


def fuse_prediction(
    prediction: Prediction, images: Sequence[np.ndarray], options: FuseOptions = FuseOptions()
) -> tuple[np.ndarray, np.ndarray]:
    """Confidence-filtered points of every frame in the world frame.

    Returns ``(xyz [M, 3] float64 world, rgb [M, 3] float32 in [0, 1])``, voxel-downsampled, the same points
    as :func:`downsample` of every frame's points, but made in passes so that memory does not grow with the
    frames: the points picked per frame are counted, then the voxel size is taken from an even sample of
    them (as :func:`downsample` does), then each frame's points are made and reduced to that grid one frame
    at a time. At 120 frames of 640x480, collecting them all first took the feed-forward stage from 1.29 to
    2.41 GB for a 16 MB result.
    """
    xyz, rgb, _ = fuse_prediction_frames(prediction, images, options)
    return xyz, rgb


@dataclass(frozen=True)
class FrameClouds:
    """The first pass of :func:`fuse_prediction`: each frame's points reduced alone to the fusion's voxel grid
    (about 1/20 of its pixels), kept so that the same frames can be fused again with other cameras without
    their depth maps and photos (see :func:`merge_frames`)."""

    frames: tuple[int, ...]  # the prediction's frame indices
    xyz: tuple[np.ndarray, ...]  # per frame [M_k, 3] float64, world frame of the prediction's cameras
    rgb: tuple[np.ndarray, ...]  # per frame [M_k, 3] float32 in [0, 1]
    voxel: float

    @property
    def nbytes(self) -> int:
        return sum(x.nbytes + c.nbytes for x, c in zip(self.xyz, self.rgb))


def fuse_prediction_frames(
    prediction: Prediction, images: Sequence[np.ndarray], options: FuseOptions = FuseOptions()
) -> tuple[np.ndarray, np.ndarray, FrameClouds | None]:
    """:func:`fuse_prediction`'s ``(xyz, rgb)`` and its frames reduced alone (None: no voxel grid, no frame)."""
    floors = [_conf_floor(prediction, k, options) for k in range(len(prediction))]  # each frame's quantile once

    def picked(k: int) -> np.ndarray:
        return _picked(prediction, k, options, floors[k])

    counts = [len(picked(k)) for k in range(len(prediction))]
    frames = [k for k, count in enumerate(counts) if count]
    if not frames:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32), None
    step = max(1, sum(counts) // 1_000_000)
    sample = np.concatenate([_frame_xyz(prediction, k, picked(k)[::step]) for k in frames])
    voxel = _voxel_size(sample, options)
    if voxel <= 0:
        parts = [_frame_points(prediction, images, k, picked(k)) for k in frames]
        return (*_cleaned(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), options), None)
    parts = [_voxel_means(*_frame_points(prediction, images, k, picked(k)), voxel) for k in frames]
    clouds = FrameClouds(tuple(frames), tuple(p[0] for p in parts), tuple(p[1] for p in parts), voxel)
    return (*merge_frames(clouds.xyz, clouds.rgb, voxel, options), clouds)


def merge_frames(
    xyz: Sequence[np.ndarray], rgb: Sequence[np.ndarray], voxel: float, options: FuseOptions = FuseOptions()
) -> tuple[np.ndarray, np.ndarray]:
    """The frames' reduced points (:class:`FrameClouds`) reduced together to the grid of ``voxel``, outliers
    dropped: :func:`fuse_prediction`'s last pass."""
    return _cleaned(*_voxel_means(np.concatenate(xyz), np.concatenate(rgb), voxel), options)


# The confidence quantile is taken over at most this many of a frame's valid pixels, evenly spaced: a full
# frame's quantile (a partition of 307,200 values at 640x480) was most of the fusion's pixel picking
_QUANTILE_SAMPLE = 65_536


def _conf_floor(prediction: Prediction, k: int, options: FuseOptions) -> float | None:
    """Frame ``k``'s confidence at ``options.conf_quantile`` of its valid pixels (None: no valid pixel)."""
    values = prediction.depth_conf[k][prediction.valid_mask(k, options.min_conf)]
    if not len(values):
        return None
    return float(np.quantile(values[:: max(1, len(values) // _QUANTILE_SAMPLE)], options.conf_quantile))


def _picked(prediction: Prediction, k: int, options: FuseOptions, floor: float | None = None) -> np.ndarray:
    """Flat indices into frame ``k``'s depth grid of the pixels fused: valid, at least at the frame's confidence
    quantile (``floor``: :func:`_conf_floor`, computed when not given), evenly thinned to at most about
    ``max_points_per_frame``."""
    floor = _conf_floor(prediction, k, options) if floor is None else floor
    if floor is None:
        return np.zeros(0, np.int64)
    valid = prediction.valid_mask(k, options.min_conf) & (prediction.depth_conf[k] >= floor)
    idx = np.flatnonzero(valid)
    return idx[:: max(1, len(idx) // options.max_points_per_frame)]


def _frame_xyz(prediction: Prediction, k: int, idx: np.ndarray) -> np.ndarray:
    """``[M, 3]`` world points of frame ``k``'s depth pixels ``idx``."""
    uv = flat_pixel_centers(idx, prediction.depth[k].shape[1])
    cam = prediction.depth_camera(k)
    return unproject_pixels(uv, prediction.depth[k].reshape(-1)[idx], cam.K, prediction.cam_from_world[k])


def _frame_points(
    prediction: Prediction, images: Sequence[np.ndarray], k: int, idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World points and colours (float32 in [0, 1]) of frame ``k``'s depth pixels ``idx``."""
    h, w = prediction.depth[k].shape
    image = images[k]
    colour = image if image.shape[:2] == (h, w) else cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    return _frame_xyz(prediction, k, idx), colour.reshape(-1, 3)[idx].astype(np.float32) / 255.0


def _voxel_size(sample: np.ndarray, options: FuseOptions) -> float:
    """The voxel: ``voxel_fraction`` of the diagonal of the points' 2-98 % extent."""
    lo, hi = np.quantile(sample, [0.02, 0.98], axis=0)
    return float(np.linalg.norm(hi - lo)) * options.voxel_fraction


def downsample(
    xyz: Sequence[np.ndarray], rgb: Sequence[np.ndarray], options: FuseOptions = FuseOptions()
) -> tuple[np.ndarray, np.ndarray]:
    """The union of clouds ``xyz[i] [M_i, 3]`` (colours ``rgb[i]`` in [0, 1]) voxel-downsampled (voxel from the
    2-98% extent) with statistical outliers dropped, with open3d.

    Each cloud (a frame's points) is first reduced alone on the same voxel grid as the union (open3d's
    tensor ``voxel_down_sample`` indexes voxels by ``floor(p / size)``, one grid for every call), so
    the voxels kept are exactly those of the whole union at once; a voxel's point is then the mean of
    the frames' means. The final pass sees about 1/20 of the points: at 96 frames of 640x480 (20 M
    points) the fusion took 8.4 s with one pass over everything, most of it converting and copying, and
    takes 4.9 s so; at 48 frames the union gives 372,190 points and the frames 372,192.
    """
    total = sum(len(x) for x in xyz)
    step = max(1, total // 1_000_000)
    voxel = _voxel_size(np.concatenate([x[::step] for x in xyz]), options)  # on <= 2 M points
    if voxel > 0:
        parts = [_voxel_means(x, c, voxel) for x, c in zip(xyz, rgb)]
        points, colours = _voxel_means(
            np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), voxel
        )
    else:
        points, colours = np.concatenate(xyz), np.concatenate(rgb)
    return _cleaned(points, colours, options)


def _cleaned(points: np.ndarray, colours: np.ndarray, options: FuseOptions) -> tuple[np.ndarray, np.ndarray]:
    """Statistical outliers dropped (``options.remove_outliers``), with open3d."""
    import open3d as o3d  # 0.45 s: here, so that loading the options does not load it

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    cloud.colors = o3d.utility.Vector3dVector(np.clip(colours, 0, 1).astype(np.float64))
    if options.remove_outliers and len(cloud.points) > 50:
        cloud, _ = cloud.remove_statistical_outlier(nb_neighbors=16, std_ratio=2.5)
    return np.asarray(cloud.points), np.asarray(cloud.colors, dtype=np.float32)


def _voxel_means(xyz: np.ndarray, rgb: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Per occupied voxel of the grid ``floor(p / voxel)``: the mean point (float64) and colour (float32), in
    the order of the voxel indices (x, then y, then z), so that a resumed run writes the same points.ply.

    numpy (sort the voxel keys, then sum per voxel): 14 ms for 200,000 points where open3d's tensor
    ``voxel_down_sample`` took 134 ms on the 2-core machine (the same voxels, means within 4e-7).

    >>> pts, rgb = _voxel_means(np.array([[0.1, 0, 0], [0.3, 0, 0], [1.5, 0, 0]]), np.ones((3, 3), np.float32), 1.0)
    >>> pts[:, 0].round(6).tolist(), rgb.dtype.name
    ([0.2, 1.5], 'float32')
    """
    if not len(xyz):
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    index = np.floor(np.asarray(xyz, np.float64) / voxel).astype(np.int64)
    index -= index.min(0)
    span = index.max(0) + 1
    if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**62:  # one int64 key per voxel, ordered as (x, y, z)
        keys = (index[:, 0] * span[1] + index[:, 1]) * span[2] + index[:, 2]
        inverse, counts = _sorted_groups(keys)
    else:  # a grid too wide for one key (far outliers): the rows themselves
        _, inverse, counts = np.unique(index, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)

    def means(values: np.ndarray) -> np.ndarray:
        sums = [np.bincount(inverse, values[:, d].astype(np.float64), len(counts)) for d in range(values.shape[1])]
        return np.stack(sums, 1) / counts[:, None]

    return means(xyz), means(rgb).astype(np.float32)


def _sorted_groups(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_inverse=True, return_counts=True)`` without the unique values: each key's group
    (groups in increasing key order) and each group's size.

    By hand because numpy's unique sorts with quicksort, where a stable sort (timsort: runs) is 3 times faster on
    these keys: a frame's pixels, in row order, fall into the same or neighbouring voxels, and the frames' reduced
    points are each already in key order when they are merged (10.6 against 3.6 ms for 100,000 points).

    >>> inverse, counts = _sorted_groups(np.array([5, 2, 5, 9, 2, 2]))
    >>> inverse.tolist(), counts.tolist()
    ([1, 0, 1, 2, 0, 0], [3, 2, 1])
    """
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    starts = np.empty(len(keys), bool)
    starts[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=starts[1:])
    group = np.cumsum(starts) - 1
    inverse = np.empty(len(keys), np.int64)
    inverse[order] = group
    return inverse, np.bincount(group)


def write_point_cloud(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> Path:
    """Binary PLY with float32 xyz and uchar colours (open3d writes it; trimesh and COLMAP read it)."""
    import open3d as o3d  # 0.45 s: here, so that loading the options does not load it

    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.asarray(xyz, np.float32)))
    cloud.point.colors = o3d.core.Tensor(np.clip(np.round(np.asarray(rgb) * 255), 0, 255).astype(np.uint8))
    if not o3d.t.io.write_point_cloud(str(path), cloud, write_ascii=False):
        raise OSError(f"open3d could not write {path}")
    return path


def write_depth_maps(folder: Path, prediction: Prediction) -> Path:
    """Per frame: ``<name>.npz`` with ``depth``, ``depth_conf``, ``K`` (for the depth grid) and ``cam_from_world``.

    Stored uncompressed: at 48 frames of 640x480 (the bench scene) zlib saved 16% (99 instead of 118 MB)
    for 3.8 s of CPU alone, 6-7 s while the feed-forward stage shares the cores with COLMAP."""
    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(prediction.names):
        np.savez(
            folder / f"{Path(name).stem}.npz",
            depth=prediction.depth[k],
            depth_conf=prediction.depth_conf[k],
            K=prediction.depth_camera(k).K,
            cam_from_world=prediction.cam_from_world[k],
        )
    return folder
