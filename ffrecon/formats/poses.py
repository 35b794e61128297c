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

from ffrecon.colmap_io import is_model_dir
from ffrecon.errors import InputError

FIX = "pass a COLMAP model folder (cameras, images, points3D .bin or .txt) or a nerfstudio transforms.json"
_OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class KnownPoses:
    """Given ``cam_from_world [3, 4]`` by photo name."""

    path: Path
    by_name: tuple[tuple[str, np.ndarray], ...]

    def get(self, name: str) -> np.ndarray | None:
        return dict(self.by_name).get(name)


def _from_transforms(path: Path) -> list[tuple[str, np.ndarray]]:
    try:
        frames = json.loads(path.read_text())["frames"]
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

    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as err:  # pycolmap raises ValueError, RuntimeError or MemoryError on bad files
        raise InputError(f"--poses {folder}: COLMAP cannot read the model ({err})", FIX) from None
    return [
        (im.name, np.asarray(im.cam_from_world().matrix(), np.float64)) for im in rec.images.values() if im.has_pose
    ]


def read_poses(path: Path) -> KnownPoses:
    """The poses of ``path`` (see the module's docstring); an :class:`InputError` for anything unusable."""
    path = Path(path)
    if path.is_dir() and is_model_dir(path):
        poses = _from_colmap(path)
    elif path.is_file() and path.suffix == ".json":
        poses = _from_transforms(path)
    else:
        raise InputError(f"--poses {path} is neither a COLMAP model folder nor a .json file", FIX)
    bad = [name for name, p in poses if p.shape != (3, 4) or not np.isfinite(p).all()]
    if bad:
        raise InputError(f"--poses {path}: the poses of {bad[:5]} are not finite 3x4 matrices", FIX)
    if len(poses) < 3:
        raise InputError(f"--poses {path} holds {len(poses)} poses", "give the poses of three photos or more")
    return KnownPoses(path, tuple(poses))
