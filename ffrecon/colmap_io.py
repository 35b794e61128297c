"""Bridge between ffrecon's arrays and pycolmap reconstructions (pycolmap 4.x API).

Images are named by their input file names so that COLMAP, pycolmap and nerfstudio find them.
Cameras are PINHOLE with COLMAP's pixel-centre rule, which ffrecon uses throughout.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.geometry.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from ffrecon.types import PinholeCamera


def rigid_from_pose(cam_from_world: np.ndarray) -> pycolmap.Rigid3d:
    """``[3, 4]`` array to ``pycolmap.Rigid3d``."""
    quat = matrix_to_quat_xyzw(cam_from_world[:3, :3])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(quat), np.asarray(cam_from_world[:3, 3], dtype=np.float64))


def pose_from_rigid(rigid: pycolmap.Rigid3d) -> np.ndarray:
    """``pycolmap.Rigid3d`` to a ``[3, 4]`` array."""
    rot = quat_xyzw_to_matrix(np.asarray(rigid.rotation.quat))
    return np.concatenate([rot, np.asarray(rigid.translation).reshape(3, 1)], axis=1)


def pinhole_to_colmap(camera: PinholeCamera, camera_id: int) -> pycolmap.Camera:
    return pycolmap.Camera(
        model="PINHOLE",
        width=camera.width,
        height=camera.height,
        params=[camera.fx, camera.fy, camera.cx, camera.cy],
        camera_id=camera_id,
    )


def colmap_to_pinhole(camera: pycolmap.Camera) -> PinholeCamera:
    """Any COLMAP camera model to a pinhole (distortion, if any, is dropped)."""
    K = np.asarray(camera.calibration_matrix())
    return PinholeCamera.from_K(K, camera.width, camera.height)


def reconstruction_from_cameras(
    names: Sequence[str],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    points_xyz: np.ndarray | None = None,
    points_rgb: np.ndarray | None = None,
    *,
    share_identical_cameras: bool = True,
) -> pycolmap.Reconstruction:
    """A reconstruction holding known cameras and poses, and optionally 3D points without tracks.

    Args:
        names: N image names (input file names).
        cam_from_world: ``[N, 3, 4]`` OpenCV poses.
        cameras: N pinhole cameras (original image pixels).
        points_xyz: ``[M, 3]`` world points; points_rgb: ``[M, 3]`` uint8 or float in [0, 1].
        share_identical_cameras: one COLMAP camera for frames whose intrinsics are equal.
    Image ids are 1..N in the order given.
    """
    rec = pycolmap.Reconstruction()
    add_posed_images(rec, names, cam_from_world, cameras, share_identical_cameras=share_identical_cameras)
    if points_xyz is not None:
        rgb = np.zeros((len(points_xyz), 3), np.uint8) if points_rgb is None else np.asarray(points_rgb)
        if rgb.dtype != np.uint8:
            rgb = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
        _add_points(rec, np.asarray(points_xyz, np.float64), rgb)
    return rec


def _add_points(rec: pycolmap.Reconstruction, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Add points without tracks (ids 1..M in order, colours uint8) through pycolmap's PLY import.

    pycolmap 4.2 has no call that adds points in a batch, and one ``add_point3D`` per point took 1.2 CPU s for the
    508,000 points of the two models of a ``--quick`` run at 96 frames of 640x480 (issue 40); a binary PLY written
    with numpy and read by COLMAP's own reader takes 0.05 s for 300,000. COLMAP's reader keeps coordinates as
    float32 (1e-7 of the scene's size): these points are the fused depth, whose own error is far larger."""
    if not len(xyz):
        return
    vertex = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    for name, column in zip(("x", "y", "z"), xyz.T):
        vertex[name] = column
    for name, column in zip(("r", "g", "b"), rgb.T):
        vertex[name] = column
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
        + "".join(f"property float {a}\n" for a in "xyz")
        + "".join(f"property uchar {c}\n" for c in ("red", "green", "blue"))
        + "end_header\n"
    )
    with tempfile.TemporaryDirectory(prefix="ffrecon-points-") as folder:
        path = Path(folder) / "points.ply"
        path.write_bytes(header.encode("ascii") + vertex.tobytes())
        rec.import_PLY(str(path))


def add_posed_images(
    rec: pycolmap.Reconstruction,
    names: Sequence[str],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    distortion: Sequence[tuple[float, float, float, float]] | None = None,
    *,
    share_identical_cameras: bool = False,
) -> list[str]:
    """Add to ``rec`` the images of ``names`` it lacks, posed by ``cam_from_world [N, 3, 4]`` with their
    ``cameras`` (OPENCV with ``distortion`` (k1, k2, p1, p2) where it is not zero, else PINHOLE) and no
    observations, e.g. frames the final cameras hold that a bundle adjustment did not (an unchecked
    frame's model camera). New image and camera ids follow the largest in ``rec``;
    ``share_identical_cameras``: one new camera for images with equal intrinsics and lens. Returns the
    names added."""
    have = {im.name for im in rec.images.values()}
    image_id, camera_id = max(rec.images, default=0), max(rec.cameras, default=0)
    shared: dict[tuple, int] = {}
    added = []
    lenses = distortion if distortion is not None else [(0.0, 0.0, 0.0, 0.0)] * len(names)
    for name, pose, cam, lens in zip(names, cam_from_world, cameras, lenses, strict=True):
        if name in have:
            continue
        image_id += 1
        key = (cam, tuple(lens))
        if not (share_identical_cameras and key in shared):
            camera_id += 1
            shared[key] = camera_id
            camera = pinhole_to_colmap(cam, camera_id)
            if any(lens):
                params = [cam.fx, cam.fy, cam.cx, cam.cy, *lens]
                camera = pycolmap.Camera(
                    model="OPENCV", width=cam.width, height=cam.height, params=params, camera_id=camera_id
                )
            rec.add_camera_with_trivial_rig(camera)
        image = pycolmap.Image(name=name, camera_id=shared[key], image_id=image_id)
        rec.add_image_with_trivial_frame(image, rigid_from_pose(pose))
        added.append(name)
    return added


def is_model_dir(folder: Path) -> bool:
    """Whether ``folder`` holds a COLMAP model (binary or text)."""
    return (Path(folder) / "images.bin").is_file() or (Path(folder) / "images.txt").is_file()


def write_reconstruction(rec: pycolmap.Reconstruction, path: Path, *, text: bool = False) -> Path:
    """Write a model in COLMAP's binary format (or text); creates the folder."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    if text:
        rec.write_text(str(path))
    else:
        rec.write_binary(str(path))
    return path


def cam_from_world_by_name(rec: pycolmap.Reconstruction, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Poses of ``names`` in ``rec``: ``([N, 3, 4] cam_from_world, [N] registered)``.

    Names absent from the model, or present but unregistered, get an identity pose and False.
    """
    by_name = {image.name: image for image in rec.images.values()}
    poses = np.tile(np.concatenate([np.eye(3), np.zeros((3, 1))], 1), (len(names), 1, 1))
    registered = np.zeros(len(names), bool)
    for k, name in enumerate(names):
        image = by_name.get(name)
        if image is not None and image.has_pose:
            poses[k] = pose_from_rigid(image.cam_from_world())
            registered[k] = True
    return poses, registered


def cameras_by_name(rec: pycolmap.Reconstruction, names: Sequence[str]) -> list[PinholeCamera | None]:
    """Pinhole intrinsics of ``names`` in ``rec`` (None where absent)."""
    by_name = {image.name: image for image in rec.images.values()}
    return [colmap_to_pinhole(rec.cameras[by_name[n].camera_id]) if n in by_name else None for n in names]
