"""The run's mesh: TSDF fusion of the final cameras' depth maps (default) or Poisson of the fused cloud.

TSDF (open3d ``ScalableTSDFVolume``): each frame's depth map, the pixels the point cloud fuses (known, not
masked out, above the frame's confidence quantile: :class:`~ffrecon.formats.pointcloud.FuseOptions`), is
integrated with its final camera, coloured from its photo; the zero level set is extracted by marching cubes.
The voxel is :attr:`MeshOptions.voxel_fraction` of the diagonal of the fused depth points' 2-98 % extent, the
truncation :attr:`MeshOptions.trunc_voxels` voxels; both are logged and returned (:class:`MeshResult`).
Small connected components are removed. An empty or broken surface is a result, not a failure: the mesh is
not written and :class:`~ffrecon.types.Skipped` says why.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from ffrecon.errors import InputError
from ffrecon.formats.mesh import MeshMethod, MeshOptions, poisson_mesh, remove_small_components, write_mesh_files
from ffrecon.formats.pointcloud import FuseOptions
from ffrecon.geometry.projection import flat_pixel_centers, unproject_pixels
from ffrecon.types import Prediction, Skipped

if TYPE_CHECKING:
    import open3d as o3d

log = logging.getLogger("ffrecon.export")
_EXTENT_SAMPLE = 20_000  # depth pixels per frame at most, for the extent that sets the voxel
_BLOCKS = 20_000  # the TSDF's first allocation of 8^3-voxel blocks (10 KB each); open3d grows it on demand


@dataclass(frozen=True)
class DepthMaps:
    """What a TSDF mesh is fused from: ``prediction`` with the final cameras (its frames, poses and
    intrinsics are the final ones, its depth the model's) and the photos of those frames, in that order."""

    prediction: Prediction
    images: Sequence[np.ndarray]  # [H_i, W_i, 3] uint8 RGB, read when indexed
    fuse: FuseOptions


@dataclass(frozen=True)
class MeshResult:
    ply: Path
    glb: Path
    method: MeshMethod
    num_vertices: int
    num_triangles: int
    voxel: float | None  # TSDF voxel edge, world units (None: Poisson)
    about: str  # one line for the log and the report


def fused_depth(prediction: Prediction, k: int, fuse: FuseOptions) -> np.ndarray:
    """``[h, w]`` float32 depth of frame ``k`` with 0 wherever the point cloud fuses nothing: unknown, masked
    out (the masks zero depth and confidence), below ``fuse.min_conf`` or the frame's ``fuse.conf_quantile``;
    all 0 when the frame's camera is not finite."""
    camera = prediction.depth_camera(k)
    if not (np.isfinite(prediction.cam_from_world[k]).all() and np.isfinite(camera.K).all()):
        return np.zeros(prediction.depth[k].shape, np.float32)
    valid = prediction.valid_mask(k, fuse.min_conf) & np.isfinite(prediction.depth[k])
    if valid.any():
        conf = prediction.depth_conf[k]
        valid &= conf >= np.quantile(conf[valid], fuse.conf_quantile)
    return np.where(valid, prediction.depth[k], 0).astype(np.float32)


def tsdf_grid(depth: DepthMaps, options: MeshOptions) -> tuple[float, float] | Skipped:
    """``(voxel, max depth)`` of the TSDF: the voxel from the extent of a sample of the fused depth points."""
    sample, far = [], 0.0
    pred = depth.prediction
    for k in range(len(pred)):
        d = fused_depth(pred, k, depth.fuse)
        idx = np.flatnonzero(d)
        if not len(idx):
            continue
        idx = idx[:: max(1, len(idx) // _EXTENT_SAMPLE)]
        uv = flat_pixel_centers(idx, d.shape[1])
        sample.append(unproject_pixels(uv, d.reshape(-1)[idx], pred.depth_camera(k).K, pred.cam_from_world[k]))
        far = max(far, float(d.max()))
    if not sample:
        return Skipped("mesh", "no depth pixel of the final frames is left to fuse (masked out, or the model unsure)")
    lo, hi = np.quantile(np.concatenate(sample), [0.02, 0.98], axis=0)
    voxel = float(np.linalg.norm(hi - lo)) * options.voxel_fraction
    if not np.isfinite(voxel) or voxel <= 0:
        return Skipped("mesh", "the fused depth points have no extent (every point in one place): no surface")
    return voxel, far


def tsdf_mesh(
    depth: DepthMaps, options: MeshOptions = MeshOptions()
) -> tuple[o3d.geometry.TriangleMesh, float] | Skipped:
    """The TSDF surface of ``depth`` and its voxel (world units), vertex-coloured from the photos.

    open3d's tensor ``VoxelBlockGrid`` (its legacy ``ScalableTSDFVolume`` extracts nothing in open3d 0.20),
    blocks of 8^3 voxels allocated where the depth maps reach. Pixel rule: ffrecon's intrinsics put the
    top-left pixel's centre at (0.5, 0.5), open3d's at (0, 0): the principal point moves by -0.5 px here.
    """
    import open3d as o3d  # 0.45 s: here, only the runs that make a mesh need it

    grid = tsdf_grid(depth, options)
    if isinstance(grid, Skipped):
        return grid
    voxel, far = grid
    o3c = o3d.core
    volume = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=(1, 1, 3),
        voxel_size=voxel,
        block_resolution=8,
        block_count=_BLOCKS,
        device=o3c.Device("CPU:0"),
    )
    pred, integrated = depth.prediction, 0
    for k in range(len(pred)):
        d = fused_depth(pred, k, depth.fuse)
        if not d.any():
            continue
        h, w = d.shape
        image = depth.images[k]
        colour = image if image.shape[:2] == (h, w) else cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
        cam = pred.depth_camera(k)
        K = o3c.Tensor(np.array([[cam.fx, 0, cam.cx - 0.5], [0, cam.fy, cam.cy - 0.5], [0, 0, 1]], np.float64))
        pose = o3c.Tensor(np.vstack([pred.cam_from_world[k], [0.0, 0.0, 0.0, 1.0]]))
        depth_image = o3d.t.geometry.Image(o3c.Tensor(d))
        colour_image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(colour, np.float32) / 255.0))
        ranges = {"depth_scale": 1.0, "depth_max": far * 1.01, "trunc_voxel_multiplier": float(options.trunc_voxels)}
        try:
            blocks = volume.compute_unique_block_coordinates(depth_image, K, pose, **ranges)
        except RuntimeError as err:  # a frame whose few pixels reach no block: nothing to integrate
            if "No block is touched" not in str(err):
                raise
            continue
        volume.integrate(blocks, depth_image, colour_image, K, pose, **ranges)
        integrated += 1
    if not integrated:
        return o3d.geometry.TriangleMesh(), voxel
    # open3d keeps voxels whose weight (frames integrated) is above the threshold, strictly
    mesh = volume.extract_triangle_mesh(weight_threshold=options.min_views - 0.5).to_legacy()
    return mesh, voxel


def build_mesh(
    options: MeshOptions,
    points: tuple[np.ndarray, np.ndarray],
    camera_centers: np.ndarray,
    depth: DepthMaps | None,
) -> tuple[o3d.geometry.TriangleMesh, float | None] | Skipped:
    """The mesh ``options.method`` asks for (TSDF of ``depth``; Poisson of ``points``, seen from
    ``camera_centers``) and its voxel, before cleaning; Skipped (with the reason) when it cannot be made."""
    if options.method is MeshMethod.TSDF:
        if depth is None:
            return Skipped(
                "mesh",
                "a TSDF mesh needs the model's depth maps and the final cameras are COLMAP's "
                "(no model, or the model was found unsuited): use --mesh poisson for a mesh of COLMAP's points",
            )
        return tsdf_mesh(depth, options)
    try:
        return poisson_mesh(*points, camera_centers, options), None
    except InputError as err:
        return Skipped("mesh", f"{err.args[0] if err.args else err}")


def write_mesh(
    out_dir: Path,
    options: MeshOptions,
    points: tuple[np.ndarray, np.ndarray],
    camera_centers: np.ndarray,
    depth: DepthMaps | None = None,
) -> MeshResult | Skipped:
    """Make, clean, check and write ``out_dir/mesh.ply`` and ``out_dir/mesh.glb``; Skipped when there is
    no surface to write (nothing fused, every triangle a small component, non-finite vertices)."""
    made = build_mesh(options, points, camera_centers, depth)
    if isinstance(made, Skipped):
        log.warning("mesh not written: %s", made.reason)
        return made
    mesh, voxel = made
    total = len(mesh.triangles)
    mesh, removed = remove_small_components(mesh, options.min_component_fraction)
    vertices = np.asarray(mesh.vertices)
    reason = ""
    if len(mesh.triangles) == 0:
        reason = f"the {options.method.value} surface has no triangle" + (
            f" ({total} before cleaning)" if total else ""
        )
    elif not np.isfinite(vertices).all():
        reason = f"the {options.method.value} surface has non-finite vertices: the depth maps or cameras are broken"
    if reason:
        log.warning("mesh not written: %s", reason)
        return Skipped("mesh", reason)
    ply, glb = write_mesh_files(mesh, Path(out_dir) / "mesh.ply", Path(out_dir) / "mesh.glb")
    grid = "" if voxel is None else f", voxel {voxel:.4g} ({options.voxel_fraction:.4g} of the depth points' extent)"
    about = (
        f"{options.method.value} mesh: {len(vertices)} vertices, {len(mesh.triangles)} triangles{grid}; "
        f"{removed} small components removed ({total - len(mesh.triangles)} triangles)"
    )
    log.info("%s", about)
    return MeshResult(ply, glb, options.method, len(vertices), len(mesh.triangles), voxel, about)
