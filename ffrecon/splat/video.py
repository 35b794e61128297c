"""A fly-through video of a splat along a smooth path through the cameras (OpenCV ``mp4v``), and any
nerfstudio camera path (:mod:`ffrecon.formats.camera_path`) rendered the same way."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import cv2
import numpy as np

from ffrecon.formats.camera_path import CAMERA_PATH_FILE, CameraPath, vertical_fov_deg, write_camera_path
from ffrecon.gaussians import Gaussians
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from ffrecon.splat.render import RasterOptions
from ffrecon.splat.render_gsplat import render_view_on
from ffrecon.types import PinholeCamera

logger = logging.getLogger("ffrecon.splat")


def _smooth_keys(values: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of ``[N, D]`` keyframe values along N (edges renormalised)."""
    if sigma <= 0 or len(values) < 3:
        return values
    idx = np.arange(len(values))
    w = np.exp(-0.5 * ((idx[:, None] - idx[None, :]) / sigma) ** 2)
    return (w @ values) / w.sum(1, keepdims=True)


def _slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Row-wise spherical interpolation of unit quaternions ``[F, 4]`` by ``t [F]``."""
    dot = np.sum(q0 * q1, axis=1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    small = theta < 1e-6
    s = np.sin(np.where(small, 1.0, theta))
    a = np.where(small, 1 - t[:, None], np.sin((1 - t[:, None]) * theta) / s)
    b = np.where(small, t[:, None], np.sin(t[:, None] * theta) / s)
    q = a * q0 + b * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def smooth_camera_path(cam_from_world: np.ndarray, num_frames: int, *, smoothing: float = 1.0) -> np.ndarray:
    """``[F, 3, 4]`` cam_from_world poses along a smooth path through ``[N, 3, 4]`` cameras (in order).

    Keyframe centres and rotations are first smoothed (Gaussian, ``smoothing`` keyframes wide), then
    centres follow a Catmull-Rom spline and rotations a slerp between consecutive keyframes.

    >>> from ffrecon.geometry.poses import look_at_cam_from_world
    >>> angles = np.linspace(0, 2, 6)
    >>> centers = np.stack([np.cos(angles), np.sin(angles), np.full(6, 0.3)], axis=1)
    >>> keys = np.stack([look_at_cam_from_world(c, np.zeros(3)) for c in centers])
    >>> smooth_camera_path(keys, 40).shape
    (40, 3, 4)
    """
    poses = np.asarray(cam_from_world, np.float64)
    if len(poses) == 1:
        return np.repeat(poses, num_frames, axis=0)
    centers = _smooth_keys(camera_centers(poses), smoothing)
    quats = matrix_to_quat_xyzw(poses[:, :, :3])
    for i in range(1, len(quats)):  # one hemisphere, so averaging and slerp take the short way
        if np.dot(quats[i], quats[i - 1]) < 0:
            quats[i] = -quats[i]
    quats = _smooth_keys(quats, smoothing)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    s = np.linspace(0.0, len(poses) - 1, num_frames)
    i0 = np.minimum(np.floor(s).astype(int), len(poses) - 2)
    t = s - i0
    p = np.concatenate([centers[:1] * 2 - centers[1:2], centers, centers[-1:] * 2 - centers[-2:-1]])  # end tangents
    p0, p1, p2, p3 = p[i0], p[i0 + 1], p[i0 + 2], p[i0 + 3]
    tt = t[:, None]
    pos = 0.5 * (
        2 * p1 + (p2 - p0) * tt + (2 * p0 - 5 * p1 + 4 * p2 - p3) * tt**2 + (3 * p1 - p0 - 3 * p2 + p3) * tt**3
    )
    rot = quat_xyzw_to_matrix(_slerp(quats[i0], quats[i0 + 1], t))
    trans = -np.einsum("fij,fj->fi", rot, pos)
    return np.concatenate([rot, trans[..., None]], axis=2)


def flythrough_path(cam_from_world: np.ndarray, camera: PinholeCamera, *, num_frames: int, fps: float) -> CameraPath:
    """The automatic fly-through as a :class:`~ffrecon.formats.camera_path.CameraPath`: keyframes at the
    ``[N, 3, 4]`` cameras, frames along :func:`smooth_camera_path`, all with ``camera``'s vertical field of
    view at its size cropped to even sides (the codec's), square pixels and the principal point at the
    centre (what a nerfstudio camera path can say)."""
    width, height = camera.width - camera.width % 2, camera.height - camera.height % 2
    fov = vertical_fov_deg(dataclasses.replace(camera, width=width, height=height))
    keys = np.asarray(cam_from_world, np.float64)
    return CameraPath(
        keyframes=keys,
        keyframe_fov_deg=np.full(len(keys), fov),
        cam_from_world=smooth_camera_path(keys, num_frames),
        fov_deg=np.full(num_frames, fov),
        width=width,
        height=height,
        fps=float(fps),
        seconds=num_frames / float(fps),
    )


def path_frames(path: CameraPath) -> tuple[np.ndarray, np.ndarray]:
    """``([F, 3, 4] cam_from_world, [F] vertical fov in degrees)``: the path's frames, or, for a path with
    keyframes only, ``round(fps * seconds)`` frames through them (:func:`smooth_camera_path` without
    smoothing, so it passes through each keyframe; the field of view linear between keyframes)."""
    if path.cam_from_world is not None:
        return path.cam_from_world, path.fov_deg
    keys, fov = path.keyframes, path.keyframe_fov_deg
    if path.is_cycle and len(keys) > 1:
        keys, fov = np.concatenate([keys, keys[:1]]), np.concatenate([fov, fov[:1]])
    count = max(1, round(path.fps * path.seconds))
    s = np.linspace(0.0, len(keys) - 1, count)
    return smooth_camera_path(keys, count, smoothing=0.0), np.interp(s, np.arange(len(keys)), fov)


def render_camera_path(
    path_file: Path,
    gaussians: Gaussians,
    path: CameraPath,
    *,
    fps: float | None = None,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    raster: RasterOptions | None = None,
    device: str = "cpu",
) -> Path | None:
    """Render ``gaussians`` along ``path`` (see :func:`path_frames`) into an ``mp4v`` video at ``path_file``
    (on ``device``: ``"cuda"`` renders with gsplat, see :func:`~ffrecon.splat.render_gsplat.render_view_on`),
    at ``fps`` (default the path's). Frames are the path's size, cropped to even sides for the codec (the
    principal point stays where the path puts it). Returns the path, or None (with a warning) when OpenCV
    cannot open an MP4 writer on this system."""
    path_file = Path(path_file)
    path_file.parent.mkdir(parents=True, exist_ok=True)
    width, height = path.width - path.width % 2, path.height - path.height % 2
    fourcc = cv2.VideoWriter_fourcc(*"mp4v")
    writer = cv2.VideoWriter(str(path_file), fourcc, float(fps or path.fps), (width, height))
    if not writer.isOpened():
        logger.warning("OpenCV cannot write %s (no mp4v encoder): skipping the video", path_file)
        return None
    g = gaussians.detached().to(device)  # moved once, not per frame
    poses, fovs = path_frames(path)
    try:
        for pose, fov in zip(poses, fovs):
            camera = dataclasses.replace(path.camera(float(fov)), width=width, height=height)
            rgb = render_view_on(device, g, pose, camera, background=background, raster=raster)
            frame = (rgb.numpy() * 255 + 0.5).astype(np.uint8)
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    logger.debug("wrote %s (%d frames)", path_file, len(poses))
    return path_file


def write_flythrough(
    path: Path,
    gaussians: Gaussians,
    cam_from_world: np.ndarray,
    camera: PinholeCamera,
    *,
    num_frames: int = 90,
    fps: float = 30.0,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    raster: RasterOptions | None = None,
    device: str = "cpu",
) -> Path | None:
    """Render ``gaussians`` along :func:`flythrough_path` and write an ``mp4v`` video (on ``device``:
    ``"cuda"`` renders with gsplat), and the path itself as nerfstudio's ``camera_path.json`` beside it
    (``ffrecon render OUT --camera-path OUT/camera_path.json`` renders the same frames again).

    Returns the video's path, or None (with a warning) when OpenCV cannot open an MP4 writer on this system
    (the camera path is written all the same).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fly = flythrough_path(cam_from_world, camera, num_frames=num_frames, fps=fps)
    write_camera_path(path.with_name(CAMERA_PATH_FILE), fly)
    written = render_camera_path(path, gaussians, fly, background=background, raster=raster, device=device)
    if written is not None:
        logger.info("wrote %s (%d frames) and %s", path, num_frames, CAMERA_PATH_FILE)
    return written
