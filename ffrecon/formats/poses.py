"""Known poses the user gives (``--poses``): a COLMAP model folder, or a nerfstudio ``transforms.json``.

Poses are read by photo name (a COLMAP image's name; the file name of a transforms.json frame's
``file_path``), as ``cam_from_world`` 3x4 OpenCV in the file's own world frame and scale (transforms.json's
camera-to-world OpenGL matrices are converted; its ``applied_transform``, if any, is the file's business:
the poses are taken in the frame the file writes them in).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ffrecon.checks import GB, MB, check_model_files, path_kind, read_option_text
from ffrecon.colmap_io import is_model_dir
from ffrecon.errors import InputError

FIX = "pass a COLMAP model folder (cameras, images, points3D .bin or .txt) or a nerfstudio transforms.json"
JSON_LIMIT_BYTES = 256 * MB  # a transforms.json frame is ~500 bytes: half a million frames
MODEL_LIMIT_BYTES = 32 * GB  # a COLMAP model file (images.bin holds every 2D point)
ROTATION_TOLERANCE = 1e-3  # max |R^T R - I| of a rotation as written (6 decimals, float32); closer ones are projected
SAME_PLACE = 1e-6  # camera centres within this of each other, relative to max(1, their distance from the origin)
_OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class KnownPoses:
    """Given ``cam_from_world [3, 4]`` by photo name."""

    path: Path
    by_name: tuple[tuple[str, np.ndarray], ...]

    def get(self, name: str) -> np.ndarray | None:
        return dict(self.by_name).get(name)


def _from_transforms(path: Path) -> list[tuple[str, np.ndarray]]:
    text = read_option_text("--poses", path, limit_bytes=JSON_LIMIT_BYTES, fix=FIX)
    try:
        frames = json.loads(text)["frames"]
        poses = []
        for frame in frames:
            world_from_cam_gl = np.asarray(frame["transform_matrix"], np.float64)[:3, :4]  # OpenGL camera axes
            world_from_cam_rot = world_from_cam_gl[:, :3] @ _OPENGL_FROM_OPENCV  # to OpenCV's axes
            cam_from_world_rot = world_from_cam_rot.T
            cam_from_world = np.hstack([cam_from_world_rot, -cam_from_world_rot @ world_from_cam_gl[:, 3:]])
            poses.append((Path(frame["file_path"]).name, cam_from_world))
        return poses
    except (OSError, ValueError, KeyError, TypeError, IndexError) as err:
        raise InputError(f"--poses {path} cannot be read as a transforms.json ({err})", FIX) from None


def _from_colmap(folder: Path) -> list[tuple[str, np.ndarray]]:
    import pycolmap

    check_model_files("--poses", folder, limit_bytes=MODEL_LIMIT_BYTES, fix=FIX)  # no FIFO, device or giant file
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as err:  # pycolmap raises ValueError, RuntimeError or MemoryError on bad files
        raise InputError(f"--poses {folder}: COLMAP cannot read the model ({err})", FIX) from None
    return [
        (im.name, np.asarray(im.cam_from_world().matrix(), np.float64)) for im in rec.images.values() if im.has_pose
    ]


def read_poses(path: Path) -> KnownPoses:
    """The poses of ``path`` (see the module's docstring); an :class:`InputError` for anything unusable: not
    finite 3x4 matrices, rotations that are not (see :func:`_rotations`), every camera at one place."""
    path = Path(path)
    if path.is_dir() and is_model_dir(path):
        poses = _from_colmap(path)
    elif path.suffix == ".json" and not path.is_dir():
        poses = _from_transforms(path)  # a FIFO or a device is refused there, on the open file
    else:
        what = "a folder without images.bin or images.txt" if path.is_dir() else path_kind(path)
        raise InputError(f"--poses {path} is neither a COLMAP model folder nor a .json file ({what})", FIX)
    bad = [name for name, p in poses if p.shape != (3, 4) or not np.isfinite(p).all()]
    if bad:
        raise InputError(f"--poses {path}: the poses of {bad[:5]} are not finite 3x4 matrices", FIX)
    if len(poses) < 3:
        raise InputError(f"--poses {path} holds {len(poses)} poses", "give the poses of three photos or more")
    poses = _rotations(path, poses)
    _check_spread(path, poses)
    return KnownPoses(path, tuple(poses))


def _rotations(path: Path, poses: list[tuple[str, np.ndarray]]) -> list[tuple[str, np.ndarray]]:
    """The poses with rotations projected onto the nearest rotation (SVD); an :class:`InputError` naming the
    frames whose 3x3 part is not a rotation within :data:`ROTATION_TOLERANCE` (max |R^T R - I|) or is a
    reflection (determinant -1)."""
    rotations = np.stack([p[:, :3] for _, p in poses])
    off = np.abs(np.swapaxes(rotations, 1, 2) @ rotations - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rotations)
    bad = [
        f"{name} (|R^T R - I| {e:.2g}, det {d:.3g})"
        for (name, _), e, d in zip(poses, off, det)
        if not (e <= ROTATION_TOLERANCE and d > 0)
    ]
    if bad:
        raise InputError(
            f"--poses {path}: {len(bad)} poses are not rotations (orthonormal within {ROTATION_TOLERANCE:g}, "
            f"determinant +1): {', '.join(bad[:3])}{' ...' if len(bad) > 3 else ''}",
            "give rigid camera poses (no scale, shear or mirror in the rotation part); " + FIX,
        )
    u, _, vt = np.linalg.svd(rotations)
    nearest = u @ vt  # the nearest rotation (det +1 here: the input's is positive and close to 1)
    return [(name, np.hstack([r, p[:, 3:]])) for (name, p), r in zip(poses, nearest)]


def _check_spread(path: Path, poses: list[tuple[str, np.ndarray]]) -> None:
    """An :class:`InputError` when every camera centre is at one place: no scale, no parallax to reconstruct
    from (the comparisons would divide by a zero extent). One place: within :data:`SAME_PLACE` x max(1, the
    centres' distance from the origin) of their median."""
    centres = np.stack([-p[:, :3].T @ p[:, 3] for _, p in poses])
    spread = np.linalg.norm(centres - np.median(centres, axis=0), axis=1).max()
    if spread <= SAME_PLACE * max(1.0, float(np.linalg.norm(centres, axis=1).max())):
        names = [name for name, _ in poses]
        raise InputError(
            f"--poses {path}: all {len(poses)} cameras ({', '.join(names[:3])}{' ...' if len(names) > 3 else ''}) "
            f"are at one place {np.round(centres[0], 6).tolist()}",
            "give each camera's own position (a camera turning on one spot has no parallax to reconstruct from)",
        )
