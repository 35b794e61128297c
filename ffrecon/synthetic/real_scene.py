"""A scene of REAL photos for the simulated model: cameras and depth from a COLMAP reconstruction of them.

The simulated VGGT-contract model (:mod:`ffrecon.synthetic.simulated_model`) needs per-frame poses,
one shared camera and depth maps to add its errors to. For real photos these come from a reference
reconstruction, e.g. ``OUT/crosscheck/sparse/0`` (or ``OUT/sparse/0``) of a no-model ffrecon run:

- poses: COLMAP's ``cam_from_world`` (OpenCV) of every registered image, in name order;
- camera: the pinhole part of COLMAP's one shared camera (``SIMPLE_RADIAL``/``RADIAL`` and the like
  keep their focal length and principal point; the radial terms are ignored, which for a phone's small
  ``k`` moves points by about a pixel at the image corners);
- depth: per image, the z-depth of the sparse 3D points it observes, splatted on a coarse grid,
  filled by inpainting (OpenCV), upsampled bilinearly; grid cells farther than
  :attr:`DepthFillOptions.max_fill_cells` from any point (sky, the far ends of streets) stay 0 = unknown.

The result is a reference, not ground truth: the model built from it is SIMULATED, and its metadata
says so. Images the reference did not register are not in the scene (the model would not recognise them).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ffrecon.capture.images import load_image
from ffrecon.colmap_io import colmap_to_pinhole, pose_from_rigid
from ffrecon.types import PinholeCamera

logger = logging.getLogger("ffrecon.synthetic")


@dataclass(frozen=True, kw_only=True)
class DepthFillOptions:
    """How sparse point depths become a depth map."""

    grid_long_side: int = 80  # cells along the image's long side of the grid the points are splatted on
    max_fill_cells: float = 16.0  # cells farther than this from every splatted point stay unknown (0)
    inpaint_radius_cells: float = 3.0  # cv2.inpaint neighbourhood radius
    min_points: int = 10  # an image observing fewer points is refused


@dataclass(frozen=True, kw_only=True)
class RealSceneSource:
    """Where a :class:`RealScene` came from; its :meth:`to_dict` is the simulated model's ``ffrecon.scene``."""

    reconstruction: str  # the COLMAP model folder
    images: str  # the photos folder
    camera_model: str  # COLMAP's model of the shared camera, e.g. "SIMPLE_RADIAL"
    depth: DepthFillOptions = field(default_factory=DepthFillOptions)

    def to_dict(self) -> dict:
        return {
            "kind": "real photos",
            "description": "SIMULATED from a COLMAP reconstruction of real photos: poses and the pinhole part of the "
            f"shared {self.camera_model} camera (radial terms ignored) are the reconstruction's, depth is its sparse "
            "points densified; not ground truth",
            "reconstruction": self.reconstruction,
            "images": self.images,
            "camera_model": self.camera_model,
            "depth": asdict(self.depth),
        }


@dataclass(frozen=True)
class RealScene:
    """Real photos with reference cameras and depth, shaped like :class:`~ffrecon.synthetic.SyntheticScene`."""

    options: RealSceneSource
    names: tuple[str, ...]  # the photos' file names
    images: np.ndarray = field(repr=False)  # [N, H, W, 3] uint8 RGB, upright as ffrecon's capture reads them
    cam_from_world: np.ndarray = field(repr=False)  # [N, 3, 4] float64, OpenCV, the reference's world frame
    camera: PinholeCamera  # shared intrinsics, COLMAP pixel convention
    depth: np.ndarray = field(repr=False)  # [N, H, W] float32 z-depth, reference units; 0 = unknown

    def __len__(self) -> int:
        return len(self.names)

    @property
    def description(self) -> str:
        """What a model simulated from this scene is (its ONNX doc string)."""
        return (
            "SIMULATED VGGT-contract model built by ffrecon.synthetic.simulated_model from a COLMAP reconstruction "
            f"of {len(self)} real photos ({self.options.reconstruction}): it outputs the reconstruction's cameras and "
            "densified sparse depth plus injected error, and recognises only those photos. Not a trained network."
        )


def densify_depth(uv: np.ndarray, z: np.ndarray, size_hw: tuple[int, int], options: DepthFillOptions) -> np.ndarray:
    """A full depth map from sparse samples.

    ``uv`` ``[P, 2]`` pixel positions (COLMAP rule: top-left pixel centre at (0.5, 0.5)), ``z`` ``[P]``
    positive z-depth; returns ``[H, W]`` float32, 0 where no sample is near (see :class:`DepthFillOptions`).
    The nearest sample wins within a grid cell.

    >>> d = densify_depth(np.array([[10.0, 10.0], [30.0, 20.0]]), np.array([2.0, 4.0]), (30, 40), DepthFillOptions())
    >>> d.shape, d.dtype, float(d[10, 10]) > 0, float(d.min()) >= 0
    ((30, 40), dtype('float32'), True, True)
    """
    h, w = size_hw
    scale = options.grid_long_side / max(h, w)
    gh, gw = max(2, round(h * scale)), max(2, round(w * scale))
    cols = np.clip((uv[:, 0] * gw / w).astype(int), 0, gw - 1)
    rows = np.clip((uv[:, 1] * gh / h).astype(int), 0, gh - 1)
    grid = np.full((gh, gw), np.inf, np.float32)
    np.minimum.at(grid, (rows, cols), z.astype(np.float32))
    empty = ~np.isfinite(grid)
    grid[empty] = 0
    filled = cv2.inpaint(grid, empty.astype(np.uint8), options.inpaint_radius_cells, cv2.INPAINT_TELEA)
    distance = cv2.distanceTransform(empty.astype(np.uint8), cv2.DIST_L2, 5)
    known = (distance <= options.max_fill_cells).astype(np.uint8)
    depth = cv2.resize(filled, (w, h), interpolation=cv2.INTER_LINEAR)
    known_full = cv2.resize(known, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    return np.where(known_full & (depth > 0), depth, 0).astype(np.float32)


def _observed_depth(
    recon: pycolmap.Reconstruction, image: pycolmap.Image, cam_from_world: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(uv [P, 2], z [P])``: the image's observed 3D points projected with the pinhole ``K`` (in front only)."""
    ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
    xyz = np.array([recon.points3D[i].xyz for i in ids], np.float64).reshape(-1, 3)
    cam = xyz @ cam_from_world[:, :3].T + cam_from_world[:, 3]
    cam = cam[cam[:, 2] > 0]
    uv = cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    return uv, cam[:, 2]


def real_scene_from_colmap(
    reconstruction: Path, images_dir: Path, options: DepthFillOptions = DepthFillOptions()
) -> RealScene:
    """The registered photos of ``reconstruction`` (a COLMAP model folder) read from ``images_dir``.

    The reconstruction must have ONE shared camera (as ffrecon's cross-check makes for one-phone
    captures) whose size matches the photos. Raises ValueError otherwise, or when an image observes
    fewer than ``options.min_points`` points.
    """
    recon = pycolmap.Reconstruction(str(reconstruction))
    if len(recon.cameras) != 1:
        raise ValueError(f"need one shared camera in {reconstruction}, found {len(recon.cameras)}")
    colmap_camera = next(iter(recon.cameras.values()))
    camera = colmap_to_pinhole(colmap_camera)  # radial terms ignored
    by_name = sorted((im.name, im) for im in recon.images.values() if im.has_pose)
    names, images, poses, depths = [], [], [], []
    for name, image in by_name:
        rgb = load_image(Path(images_dir) / name)[0]
        if rgb.shape[:2] != (camera.height, camera.width):
            raise ValueError(f"{name} is {rgb.shape[1]}x{rgb.shape[0]}, the camera {camera.width}x{camera.height}")
        pose = pose_from_rigid(image.cam_from_world())
        uv, z = _observed_depth(recon, image, pose, camera.K)
        if len(z) < options.min_points:
            raise ValueError(f"{name} observes {len(z)} points, fewer than {options.min_points}")
        names.append(name)
        images.append(rgb)
        poses.append(pose)
        depths.append(densify_depth(uv, z, (camera.height, camera.width), options))
    depth = np.stack(depths)
    logger.info(
        "real scene from %s: %d images, %.0f%% of pixels with depth",
        reconstruction,
        len(names),
        100 * float((depth > 0).mean()),
    )
    source = RealSceneSource(
        reconstruction=str(reconstruction),
        images=str(images_dir),
        camera_model=str(colmap_camera.model.name),
        depth=options,
    )
    return RealScene(
        options=source,
        names=tuple(names),
        images=np.stack(images),
        cam_from_world=np.stack(poses),
        camera=camera,
        depth=depth,
    )
