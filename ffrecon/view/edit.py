"""What ``ffrecon view``'s editing tools write, apart from the browser: the cropped splat with its box, and the
camera path recorded from keyframes. Everything is in the viewer's frame, the final cameras' (``sparse/0``).

- The crop box writes ``splat_cropped.ply``, ``splat_cropped.spz`` and ``crop_box.json`` (read by
  ``ffrecon run --crop-box FILE``) into the output folder; ``splat.ply`` and ``splat.spz`` are never changed.
- The keyframes (the browser's camera, when a person presses "add keyframe") write
  ``camera_path_recorded.json``, nerfstudio's format, which ``ffrecon render OUT --camera-path`` renders.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ffrecon.errors import InputError
from ffrecon.formats.camera_path import CameraPath, write_camera_path
from ffrecon.formats.splat_ply import read_splat_ply, write_splat_ply
from ffrecon.formats.web import write_splat_spz
from ffrecon.geometry.poses import invert_pose
from ffrecon.geometry.rotations import quat_xyzw_to_matrix
from ffrecon.splat.clean import CropBox, check_crop_box, write_crop_box
from ffrecon.splat.video import path_frames

logger = logging.getLogger("ffrecon.view")

CROPPED_PLY, CROPPED_SPZ, CROP_BOX_FILE = "splat_cropped.ply", "splat_cropped.spz", "crop_box.json"
RECORDED_PATH = "camera_path_recorded.json"


@dataclass(frozen=True)
class CroppedSplat:
    ply: Path
    spz: Path
    box_file: Path
    kept: int
    total: int


def inside_box(points: np.ndarray, box: CropBox) -> np.ndarray:
    """``[N]`` bool: ``[N, 3]`` points inside the closed box ``(lo, hi)``."""
    lo, hi = np.asarray(box[0]), np.asarray(box[1])
    return np.all((points >= lo) & (points <= hi), axis=1)


def write_cropped_splat(out_dir: Path, box: CropBox) -> CroppedSplat:
    """The Gaussians of ``OUT/splat.ply`` whose centres lie in ``box``, written as ``splat_cropped.ply`` and
    ``.spz`` (the same SH degree), and the box as ``crop_box.json``; ``splat.ply`` itself is left as it is."""
    out_dir = Path(out_dir)
    box = check_crop_box(box[0], box[1], "the crop box", "drag its corners apart")
    gaussians = read_splat_ply(out_dir / "splat.ply")
    keep = inside_box(gaussians.means.double().numpy(), box)
    if not keep.any():
        raise InputError(f"no Gaussian of {len(keep)} lies in the crop box", "move or grow the box over the splat")
    cropped = gaussians.subset(torch.from_numpy(keep))
    ply = write_splat_ply(out_dir / CROPPED_PLY, cropped, sh_degree=gaussians.sh_degree)
    spz = write_splat_spz(out_dir / CROPPED_SPZ, cropped, sh_degree=gaussians.sh_degree)
    box_file = write_crop_box(out_dir / CROP_BOX_FILE, box)
    logger.info("wrote %s (%d of %d Gaussians), %s and %s", ply, int(keep.sum()), len(keep), spz, box_file)
    return CroppedSplat(ply, spz, box_file, int(keep.sum()), len(keep))


@dataclass
class KeyframeRecorder:
    """Keyframes of a camera path: ``[3, 4]`` OpenCV cam_from_world and vertical fov (degrees) each."""

    cam_from_world: list[np.ndarray] = field(default_factory=list)
    fov_deg: list[float] = field(default_factory=list)

    def add_viser_camera(self, position, wxyz, fov_rad: float) -> int:
        """Add the browser's camera (viser's: OpenCV axes, ``wxyz`` and ``position`` of world_from_cam, vertical
        fov in radians); returns how many keyframes there are."""
        w, x, y, z = (float(v) for v in wxyz)
        rot = quat_xyzw_to_matrix(np.array([x, y, z, w]))
        world_from_cam = np.concatenate([rot, np.asarray(position, np.float64).reshape(3, 1)], axis=1)
        self.cam_from_world.append(invert_pose(world_from_cam))
        self.fov_deg.append(float(np.degrees(fov_rad)))
        return len(self.cam_from_world)

    def clear(self) -> None:
        self.cam_from_world.clear()
        self.fov_deg.clear()

    def camera_path(self, size_wh: tuple[int, int], fps: float, seconds: float) -> CameraPath:
        """The keyframes as a path of ``round(fps * seconds)`` frames through each of them, ``size_wh`` pixels."""
        if not self.cam_from_world:
            raise InputError("no keyframes recorded", "press 'add keyframe' at each view the path should pass")
        keys = CameraPath(
            np.stack(self.cam_from_world), np.array(self.fov_deg), None, None, *size_wh, float(fps), float(seconds)
        )
        poses, fov = path_frames(keys)
        return CameraPath(keys.keyframes, keys.keyframe_fov_deg, poses, fov, *size_wh, float(fps), float(seconds))

    def write(self, out_dir: Path, size_wh: tuple[int, int], fps: float, seconds: float) -> Path:
        """Write the path as ``OUT/camera_path_recorded.json``; returns its path."""
        return write_camera_path(Path(out_dir) / RECORDED_PATH, self.camera_path(size_wh, fps, seconds))
