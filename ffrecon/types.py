"""Frozen dataclasses passed between stages.

Shapes, dtypes, units and frames are in the field comments. Intrinsics always belong to a stated
image size and follow COLMAP's pixel-centre rule (see :mod:`ffrecon.geometry.projection`).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ffrecon.geometry.projection import unproject_depth


def capped_size(width: int, height: int, max_size: int | None) -> tuple[int, int]:
    """``(width, height)`` scaled so that the long side is at most ``max_size`` (None or 0: unchanged); the one rule
    for capture's size cap and the splat's memory cap.

    >>> capped_size(3000, 2000, 1600), capped_size(1200, 1600, 1600), capped_size(12000, 9000, None)
    ((1600, 1067), (1200, 1600), (12000, 9000))
    """
    long_side = max(width, height)
    if not max_size or long_side <= max_size:
        return width, height
    scale = max_size / long_side
    return max(1, round(width * scale)), max(1, round(height * scale))


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


@dataclass(frozen=True, kw_only=True)
class Frame:
    """One input image: where its upright 8-bit copy lies and its size, not its pixels.

    The capture stage writes every frame to ``OUT/images/<name>`` and drops the pixels; stages that
    need them call :meth:`read_rgb`, so a run never holds all images at once.
    """

    name: str  # file name, kept through the pipeline (COLMAP image name)
    path: Path  # OUT/images/<name>: upright 8-bit copy (re-encoded if converted, else the original's bytes)
    size_wh: tuple[int, int]  # (width, height) of the upright image, pixels
    focal_prior_px: float | None = None  # focal length in pixels of this image (EXIF), if known

    def read_rgb(self) -> np.ndarray:
        """``[H, W, 3]`` uint8 RGB, upright, read from :attr:`path`; raises InputError if gone or resized."""
        import cv2

        from ffrecon.errors import InputError

        # The file is upright already: converted frames (EXIF orientation != 1 among them) were
        # written by OpenCV without EXIF, and byte-for-byte copies are only made of 8-bit
        # 3-channel files whose orientation is 1. A copy may still carry EXIF tags, so the
        # orientation is ignored here rather than applied a second time.
        bgr = cv2.imread(str(self.path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        fix = "the images folder changed during the run: start again into a fresh output folder"
        if bgr is None:
            raise InputError(f"cannot read frame {self.name} from {self.path} (missing or corrupt)", fix)
        if (bgr.shape[1], bgr.shape[0]) != tuple(self.size_wh):
            raise InputError(
                f"frame {self.name} at {self.path} is {bgr.shape[1]}x{bgr.shape[0]}, "
                f"expected {self.size_wh[0]}x{self.size_wh[1]}",
                fix,
            )
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


class ModelFamily(enum.Enum):
    """Model contracts ffrecon decodes (docs/models.md). The value is the ``ffrecon.contract`` metadata."""

    MULTIVIEW = "multiview"  # VGGT contract (docs/contracts.md, "Multi-view models")
    DA3 = "da3"  # Depth Anything 3: depth, depth_conf, extrinsics (cam_from_world), intrinsics
    PI3 = "pi3"  # Pi3: local_points, conf (logit), camera_poses (world_from_cam); no reference frame
    MAPANYTHING = "mapanything"  # MapAnything: per-view rays, depth along ray, cam_trans/cam_quats
    MONODEPTH = "monodepth"  # one image in, relative inverse depth or metric depth out
    PAIRWISE = "pairwise"  # DUSt3R / MASt3R contract (docs/contracts.md, "Pairwise models")

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

    def subset(self, indices: Sequence[int]) -> Prediction:
        """The frames at ``indices``, in that order (the same world frame)."""
        idx = [int(i) for i in indices]
        return replace(
            self,
            names=tuple(self.names[i] for i in idx),
            cam_from_world=self.cam_from_world[idx],
            cameras=tuple(self.cameras[i] for i in idx),
            depth=tuple(self.depth[i] for i in idx),
            depth_conf=tuple(self.depth_conf[i] for i in idx),
        )

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


# -- what every stage returns when it does not run, and the run's mode ---------------------------------


@dataclass(frozen=True)
class Skipped:
    """A stage that did not run, and why (shown in the report and the summary)."""

    stage: str
    reason: str


ONE_VIEW = "needs two or more views; this run has one photo (its depth, camera and point cloud are still produced)"


class RunMode(enum.Enum):
    """How a run makes its cameras (:attr:`ffrecon.pipeline.RunOptions.mode`)."""

    # The model's cameras (or COLMAP's, without a model), checked against an independent COLMAP
    # reconstruction of the same photos, then refined by bundle adjustment.
    FULL = "full"
    # ``--quick``: no COLMAP reconstruction. The model's cameras refined by bundle adjustment on SIFT
    # matches of the pairs they say overlap; nothing independent checks them. Needs a model.
    QUICK = "quick"


QUICK_STATEMENT = (
    "Quick mode: no independent COLMAP cross-check was run; the cameras are the feed-forward ones refined by "
    "bundle adjustment and are not verified against an independent reconstruction."
)
QUICK_NO_CROSSCHECK = (
    "quick mode (--quick): no independent COLMAP reconstruction; the refinement extracts and matches SIFT "
    "itself, on the pairs the model's cameras say overlap"
)
