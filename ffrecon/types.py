"""Frozen dataclasses passed between stages.

Shapes, dtypes, units and frames are in the field comments. Intrinsics always belong to a stated
image size and follow COLMAP's pixel-centre rule (see :mod:`ffrecon.geometry.projection`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ffrecon.geometry.projection import unproject_depth


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels of an image of ``width`` x ``height``."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        """``[3, 3]`` float64 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @staticmethod
    def from_K(K: np.ndarray, width: int, height: int) -> "PinholeCamera":
        return PinholeCamera(int(width), int(height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))

    def scaled(self, sx: float, sy: float) -> "PinholeCamera":
        """The same camera for an image resized by (sx, sy) (no half-pixel terms: COLMAP rule)."""
        return PinholeCamera(
            round(self.width * sx), round(self.height * sy), self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy
        )

    def fov_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view in degrees."""
        return (
            float(np.degrees(2 * np.arctan(self.width / 2 / self.fx))),
            float(np.degrees(2 * np.arctan(self.height / 2 / self.fy))),
        )


@dataclass(frozen=True)
class Frame:
    """One input image."""

    name: str  # file name, kept through the pipeline (COLMAP image name)
    image: np.ndarray = field(repr=False)  # [H, W, 3] uint8 RGB, EXIF orientation applied
    focal_prior_px: float | None = None  # focal length in pixels of this image (EXIF), if known
    path: Path | None = None  # where the pixels came from (None for video frames until written)

    @property
    def size_wh(self) -> tuple[int, int]:
        return (int(self.image.shape[1]), int(self.image.shape[0]))


class ModelFamily(enum.Enum):
    """Model contracts ffrecon decodes (docs/models.md). The value is the ``ffrecon.contract`` metadata."""

    MULTIVIEW = "multiview"  # VGGT contract (CONTRACTS.md section 1)
    DA3 = "da3"  # Depth Anything 3: depth, depth_conf, extrinsics (cam_from_world), intrinsics
    PI3 = "pi3"  # Pi3: local_points, conf (logit), camera_poses (world_from_cam); no reference frame
    MAPANYTHING = "mapanything"  # MapAnything: per-view rays, depth along ray, cam_trans/cam_quats
    MONODEPTH = "monodepth"  # one image in, relative inverse depth or metric depth out
    PAIRWISE = "pairwise"  # DUSt3R / MASt3R contract (CONTRACTS.md section 2)

    @property
    def is_pairwise(self) -> bool:
        return self is ModelFamily.PAIRWISE


@dataclass(frozen=True)
class ModelInfo:
    """What produced a prediction."""

    path: str
    family: ModelFamily
    simulated: bool = False  # True for ffrecon's simulated model: reports must say so
    description: str = ""
    metadata: dict[str, str] = field(default_factory=dict, repr=False, compare=False)  # the file's ffrecon.* metadata


@dataclass(frozen=True)
class Prediction:
    """Feed-forward output for N frames, in original-photo pixels.

    The world frame is the model's (VGGT: the first frame; scale not metric).
    """

    names: tuple[str, ...]
    cam_from_world: np.ndarray  # [N, 3, 4] float64, OpenCV
    cameras: tuple[PinholeCamera, ...]  # per frame, original photo size
    # Depth maps cover the original photo; for large photos they may be stored on a uniformly
    # downscaled grid (long side capped), see depth_camera().
    depth: tuple[np.ndarray, ...]  # per frame [h_i, w_i] float32 z-depth; 0 where unknown (cropped away)
    depth_conf: tuple[np.ndarray, ...]  # per frame [h_i, w_i] float32; >= 1 where known, 0 where unknown
    model: ModelInfo

    def __len__(self) -> int:
        return len(self.names)

    def depth_camera(self, i: int) -> PinholeCamera:
        """Intrinsics of frame i for the grid its depth map is stored on."""
        cam = self.cameras[i]
        h, w = self.depth[i].shape
        return cam if (w, h) == (cam.width, cam.height) else cam.scaled(w / cam.width, h / cam.height)

    def world_points(self, i: int) -> np.ndarray:
        """``[h_i, w_i, 3]`` float64 points of frame i in the world frame (depth unprojected)."""
        return unproject_depth(self.depth[i], self.depth_camera(i).K, self.cam_from_world[i])

    def valid_mask(self, i: int, min_conf: float = 1.0) -> np.ndarray:
        """``[H_i, W_i]`` bool: depth known, positive and with confidence >= ``min_conf``."""
        return (self.depth[i] > 0) & (self.depth_conf[i] >= min_conf)
