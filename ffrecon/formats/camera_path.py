"""nerfstudio's ``camera_path.json``: the camera path its viewer records and ``ns-render camera-path`` renders.

The file (docs/camera_paths.md):

- ``keyframes``: the poses a person chose, each ``{"matrix": [16], "fov": deg, "aspect": w/h, ...}``;
- ``camera_path``: the interpolated frames, each ``{"camera_to_world": [16], "fov": deg, "aspect": w/h}``;
- ``render_width``, ``render_height`` (pixels), ``fps``, ``seconds``, ``camera_type`` (``perspective``),
  ``is_cycle``, ``smoothness_value``, ``default_fov``, ``default_transition_sec``.

Each matrix is a 4x4 world_from_cam flattened row by row, in the OpenGL camera convention (x right, y up,
z backward), as ``transforms.json``'s ``transform_matrix``; ``fov`` is the *vertical* field of view in degrees
(three.js's). nerfstudio's loader makes ``fx = fy = (render_height / 2) / tan(fov / 2)`` with the principal
point at the image centre; so does :meth:`CameraPath.camera`. ffrecon writes and reads the poses in the world
of the run's final cameras (``sparse/0``, ``transforms.json``, ``splat.ply``): ``"frame": "sparse/0"``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ffrecon.errors import InputError
from ffrecon.formats.nerfstudio import OPENCV_TO_OPENGL, world_from_cam_opengl
from ffrecon.geometry.poses import invert_pose
from ffrecon.types import PinholeCamera

CAMERA_PATH_FILE = "camera_path.json"
FRAME = "sparse/0"  # the world the poses are in: the run's final cameras (transforms.json, splat.ply)
MAX_SIDE = 16384  # render_width / render_height at most this (pixels)
ROTATION_TOL = 1e-3  # a matrix's 3x3 block further than this from a rotation (max |R^T R - I|) is refused
_FIX = "pass a camera_path.json written by ffrecon (camera_path.json in a run folder) or nerfstudio's viewer"


@dataclass(frozen=True)
class CameraPath:
    """A camera path in ffrecon's conventions.

    ``cam_from_world``: ``[F, 3, 4]`` float64 OpenCV poses of the frames to render (None: the file had only
    keyframes, to be interpolated); ``fov_deg``: ``[F]`` vertical fields of view; ``keyframes``:
    ``[K, 3, 4]`` OpenCV cam_from_world, ``keyframe_fov_deg`` ``[K]``. All in the world of ``sparse/0``.
    """

    keyframes: np.ndarray
    keyframe_fov_deg: np.ndarray
    cam_from_world: np.ndarray | None
    fov_deg: np.ndarray | None
    width: int
    height: int
    fps: float
    seconds: float
    is_cycle: bool = False
    smoothness: float = 0.5

    def camera(self, fov_deg: float) -> PinholeCamera:
        """The pinhole camera of a frame whose vertical field of view is ``fov_deg``, as nerfstudio makes it.

        >>> path = CameraPath(np.eye(3, 4)[None], np.array([90.0]), None, None, 64, 48, 30.0, 1.0)
        >>> path.camera(90.0)
        PinholeCamera(width=64, height=48, fx=24.000000000000004, fy=24.000000000000004, cx=32.0, cy=24.0)
        """
        focal = (self.height / 2) / math.tan(math.radians(fov_deg) / 2)
        return PinholeCamera(self.width, self.height, focal, focal, self.width / 2, self.height / 2)


def vertical_fov_deg(camera: PinholeCamera) -> float:
    """The vertical field of view (degrees) of ``camera``: what a path frame of it records."""
    return camera.fov_deg()[1]


def cam_from_world_from_opengl(world_from_cam_gl: np.ndarray) -> np.ndarray:
    """``[N, 4, 4]`` OpenGL world_from_cam (nerfstudio's ``camera_to_world``) to ``[N, 3, 4]`` OpenCV
    cam_from_world; the inverse of :func:`~ffrecon.formats.nerfstudio.world_from_cam_opengl`.

    >>> pose = np.concatenate([np.eye(3), [[1.0], [2.0], [3.0]]], axis=1)[None]
    >>> bool(np.allclose(cam_from_world_from_opengl(world_from_cam_opengl(pose)), pose))
    True
    """
    world_from_cam = np.asarray(world_from_cam_gl, np.float64) @ OPENCV_TO_OPENGL  # the flip is its own inverse
    return invert_pose(world_from_cam[:, :3, :4])


def camera_path_to_json(path: CameraPath) -> dict:
    """The nerfstudio dictionary of ``path`` (``camera_path`` must be set)."""
    aspect = path.width / path.height
    keys = world_from_cam_opengl(path.keyframes)
    frames = world_from_cam_opengl(path.cam_from_world)
    transition = path.seconds / max(len(keys) - (0 if path.is_cycle else 1), 1)
    return {
        "frame": FRAME,
        "camera_type": "perspective",
        "render_width": path.width,
        "render_height": path.height,
        "fps": path.fps,
        "seconds": path.seconds,
        "is_cycle": path.is_cycle,
        "smoothness_value": path.smoothness,
        "default_fov": float(path.keyframe_fov_deg[0]),
        "default_transition_sec": transition,
        "keyframes": [
            {
                "matrix": m.flatten().tolist(),
                "fov": float(f),
                "aspect": aspect,
                "override_transition_enabled": False,
                "override_transition_sec": None,
            }
            for m, f in zip(keys, path.keyframe_fov_deg)
        ],
        "camera_path": [
            {"camera_to_world": m.flatten().tolist(), "fov": float(f), "aspect": aspect}
            for m, f in zip(frames, path.fov_deg)
        ],
    }


def write_camera_path(file: Path, path: CameraPath) -> Path:
    """Write ``path`` as nerfstudio's ``camera_path.json``; returns ``file``."""
    file = Path(file)
    file.write_text(json.dumps(camera_path_to_json(path), indent=1))
    return file


def read_camera_path(file: Path) -> CameraPath:
    """Read a ``camera_path.json`` (nerfstudio's viewer's, or ffrecon's); every problem an :class:`InputError`
    naming the file and the entry. A file without ``camera_path`` (keyframes only) gives
    ``cam_from_world = None``: the caller interpolates the keyframes."""
    file = Path(file)
    if not file.is_file():
        raise InputError(f"camera path {file} does not exist", _FIX)
    try:
        data = json.loads(file.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"camera path {file} is not JSON ({err})", _FIX) from None
    if not isinstance(data, dict):
        raise InputError(f"camera path {file} is a JSON {type(data).__name__}, not an object", _FIX)
    camera_type = str(data.get("camera_type", "perspective")).lower()
    if camera_type != "perspective":
        raise InputError(f"camera path {file} is of type {camera_type!r}", "record a perspective camera path")
    if data.get("frame", FRAME) != FRAME:
        raise InputError(
            f"camera path {file} is in frame {data['frame']!r}, not {FRAME!r}",
            f"set its poses in the world of the run's sparse/0 and its frame to {FRAME!r}",
        )
    width, height = (_whole(file, data, key) for key in ("render_width", "render_height"))
    fps = _positive(file, data, "fps")
    entries = data.get("keyframes")
    if not isinstance(entries, list) or not entries:
        raise InputError(f"camera path {file} has no keyframes", "record at least one keyframe; " + _FIX)
    keyframes, key_fov = _poses(file, entries, "keyframes", "matrix")
    frames, fov = (None, None)
    if data.get("camera_path") is not None:
        if not isinstance(data["camera_path"], list) or not data["camera_path"]:
            raise InputError(f"camera path {file} has an empty camera_path", "leave camera_path out, or give frames")
        frames, fov = _poses(file, data["camera_path"], "camera_path", "camera_to_world")
    count = len(frames) if frames is not None else 1
    seconds = _positive(file, data, "seconds") if "seconds" in data else count / fps
    return CameraPath(
        keyframes,
        key_fov,
        frames,
        fov,
        width,
        height,
        fps,
        seconds,
        bool(data.get("is_cycle", False)),
        float(data.get("smoothness_value", 0.5) or 0.5),
    )


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _whole(file: Path, data: dict, key: str) -> int:
    value = data.get(key)
    if not _number(value) or value != int(value) or not 1 <= value <= MAX_SIDE:
        raise InputError(f"camera path {file}: {key} is {value!r}", f"set {key} to a whole number 1 to {MAX_SIDE}")
    return int(value)


def _positive(file: Path, data: dict, key: str) -> float:
    value = data.get(key)
    if not _number(value) or value <= 0:
        raise InputError(f"camera path {file}: {key} is {value!r}", f"set {key} to a finite number > 0")
    return float(value)


def _poses(file: Path, entries: list, where: str, key: str) -> tuple[np.ndarray, np.ndarray]:
    """``([N, 3, 4] OpenCV cam_from_world, [N] vertical fov in degrees)`` of a list of path entries."""
    gl, fov = [], []
    for i, entry in enumerate(entries):
        name = f"{where}[{i}]"
        matrix = entry.get(key) if isinstance(entry, dict) else None
        if not isinstance(matrix, list) or len(matrix) != 16 or not all(_number(v) for v in matrix):
            got = f"{len(matrix)} values" if isinstance(matrix, list) else repr(matrix)[:40]
            raise InputError(
                f"camera path {file}: {name}.{key} is not 16 finite numbers ({got})",
                f"give {key} as a 4x4 camera-to-world matrix flattened row by row",
            )
        fov.append(_fov(file, entry, name))
        gl.append(_rigid(file, np.asarray(matrix, np.float64).reshape(4, 4), f"{name}.{key}"))
    return cam_from_world_from_opengl(np.stack(gl)), np.asarray(fov, np.float64)


def _fov(file: Path, entry: dict, name: str) -> float:
    value = entry.get("fov")
    if not _number(value) or not 0 < value < 180:
        raise InputError(f"camera path {file}: {name}.fov is {value!r}", "set fov to degrees between 0 and 180")
    return float(value)


def _rigid(file: Path, matrix: np.ndarray, name: str) -> np.ndarray:
    """``matrix`` with its 3x3 block made an exact rotation (the nearest, by SVD), when it is one within
    :data:`ROTATION_TOL` and its last row is ``0 0 0 1``; an InputError else."""
    rot = matrix[:3, :3]
    bottom_ok = np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-6)
    if not bottom_ok or np.abs(rot.T @ rot - np.eye(3)).max() > ROTATION_TOL or np.linalg.det(rot) <= 0:
        raise InputError(
            f"camera path {file}: {name} is not a rigid camera-to-world matrix (no scale, last row 0 0 0 1)",
            "give a rotation and a translation only",
        )
    u, _, vt = np.linalg.svd(rot)
    out = matrix.copy()
    out[:3, :3] = u @ vt
    return out
