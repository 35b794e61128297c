"""The export stage: the files other tools read, written with the final cameras.

``run_exports`` writes ``points.ply`` (the depth maps fused with the final cameras, or COLMAP's
sparse points when no model was given), the nerfstudio
``transforms.json`` and, on request, a mesh (``mesh.ply``, ``mesh.glb``: TSDF fusion of the depth maps with the
final cameras, or Poisson of the cloud; :mod:`ffrecon.export.mesh`). The COLMAP models
are written by the stages that make them; the report by :mod:`ffrecon.report.build`.

An empty cloud (every pixel masked out, or the model unsure of every pixel) is a result, not a failure:
the files made of points (``points.ply``, the mesh) are not written, and :attr:`ExportsResult.not_written`
says why, for the report; ``transforms.json`` is written all the same (it needs cameras only).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ffrecon.capture import Capture
from ffrecon.errors import InputError
from ffrecon.export.mesh import DepthMaps, MeshResult, write_mesh
from ffrecon.final_cameras import CameraSource, FinalCameras
from ffrecon.formats.mesh import MeshMethod, MeshOptions
from ffrecon.formats.nerfstudio import write_transforms
from ffrecon.formats.pointcloud import (
    FrameClouds,
    FuseOptions,
    fuse_prediction,
    fuse_prediction_frames,
    merge_frames,
    write_point_cloud,
)
from ffrecon.geometry.poses import camera_centers
from ffrecon.models.stage import FeedForwardResult
from ffrecon.sfm.crosscheck.run import ColmapResult
from ffrecon.splat.seed import seed_from_reconstruction
from ffrecon.types import Prediction, Skipped

log = logging.getLogger("ffrecon.export")
OUTPUTS = ("points.ply", "transforms.json", "mesh.ply", "mesh.glb")  # relative to the run folder


@dataclass(frozen=True, kw_only=True)
class ExportOptions:
    # mesh.ply and mesh.glb: None (no mesh), a method, or its name; True means TSDF. It sets mesh_options.method.
    mesh: MeshMethod | None = None
    mesh_options: MeshOptions = field(default_factory=MeshOptions)

    def __post_init__(self) -> None:
        mesh = self.mesh
        if mesh is True:
            mesh = MeshMethod.TSDF
        elif mesh is False or mesh is None:
            mesh = None
        elif mesh not in list(MeshMethod):  # a StrEnum member equals its value
            choices = ", ".join(m.value for m in MeshMethod)
            raise InputError(f"ExportOptions.mesh is {mesh!r}, not a mesh method", f"use one of {choices}, or None")
        else:
            mesh = MeshMethod(mesh)
        object.__setattr__(self, "mesh", mesh)
        if mesh is not None and self.mesh_options.method is not mesh:
            object.__setattr__(self, "mesh_options", dataclasses.replace(self.mesh_options, method=mesh))


@dataclass(frozen=True)
class ExportsResult:
    """Files written by the export stage (paths in the run folder)."""

    points_ply: Path | None  # None: not written (see ``not_written``)
    num_points: int
    points_from: str  # what the cloud is: fused depth maps, or COLMAP's sparse points
    transforms_json: Path
    mesh_ply: Path | None
    mesh_glb: Path | None
    cameras_from: CameraSource  # FinalCameras.source
    not_written: dict[str, str] = field(default_factory=dict)  # file name -> why it was not written
    mesh_about: str = ""  # the mesh's method, size, voxel and cleaning, in one line ("" without a mesh)


def empty_cloud_reason(points_from: str, masks: bool) -> str:
    """Why a cloud of ``points_from`` holds no point, and what to do (for the report).

    >>> empty_cloud_reason("COLMAP's sparse points", masks=False)
    "no point to write: COLMAP's sparse points hold none"
    """
    if "depth" not in points_from:
        return f"no point to write: {points_from} hold none"
    why = (
        "the masks (--masks) ignore every pixel, or the model is unsure of the rest: check the mask polarity, "
        "0 = ignore, 255 = use"
        if masks
        else "the model is unsure of every pixel: try another model"
    )
    return f"no depth pixel of the final frames is left to fuse; {why}"


def with_final_cameras(prediction: Prediction, final: FinalCameras) -> Prediction:
    """The depth maps of the final cameras' frames (frames left out, contradicted, stay out) with those
    cameras (poses and intrinsics) instead of the model's."""
    kept = prediction.subset(final.indices)
    return dataclasses.replace(kept, cam_from_world=final.cam_from_world, cameras=final.cameras)


def fuse_with_final_cameras(
    prediction: Prediction,
    final: FinalCameras,
    read_images: Callable[[list[int]], Sequence[np.ndarray]],
    fuse: FuseOptions,
    clouds: FrameClouds | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The depth maps of the final cameras' frames fused with those cameras (:func:`with_final_cameras`), so
    points.ply agrees with sparse/0: the model's own fusion of ``prediction``'s frames, each reduced alone
    (``clouds``: :attr:`~ffrecon.models.stage.FeedForwardResult.frame_clouds`), moved to the final cameras
    (:func:`moved_frame_clouds`) and reduced together. Without ``clouds`` (a resumed run) that fusion is made
    again first, from ``read_images(indices)`` (the capture's photos, read one at a time as the fusion goes:
    :meth:`~ffrecon.capture.Capture.frames_on_demand`), so that a resumed run writes the same cloud."""
    if clouds is None:
        _, _, clouds = fuse_prediction_frames(prediction, read_images(list(range(len(prediction)))), fuse)
    kept = set(clouds.frames) if clouds is not None else set()
    if not kept & set(final.indices):  # no voxel grid (a flat cloud), or no final frame with a point
        return fuse_prediction(with_final_cameras(prediction, final), read_images(list(final.indices)), fuse)
    after = with_final_cameras(prediction, final)
    moved = [moved_frame_clouds(clouds, prediction, k, after, j) for j, k in enumerate(final.indices) if k in kept]
    return merge_frames([m[0] for m in moved], [m[1] for m in moved], clouds.voxel, fuse)


def moved_frame_clouds(
    clouds: FrameClouds, before: Prediction, k: int, after: Prediction, j: int
) -> tuple[np.ndarray, np.ndarray]:
    """The reduced points of frame ``k`` of ``clouds`` (made with ``before``'s camera ``k``) moved to camera ``j``
    of ``after`` (the same frame with other cameras, :func:`with_final_cameras`): ``(xyz [M, 3] world, rgb)``.

    A depth pixel's point in its camera is ``z K^-1 [u, v, 1]``, so with the final intrinsics ``K'`` it becomes
    ``K'^-1 K`` times the first one, and the whole move is affine: ``x' = R'^T (K'^-1 K (R x + t) - t')``. A
    mean moves with its points under an affine map, so each of the frame's voxel means is the mean of its
    pixels' points placed with the final camera, as a second fusion would make them; only the grouping into
    voxels is the model's world's (the voxel's size is the same, the world and its scale too)."""
    xyz, rgb = clouds.xyz[clouds.frames.index(k)], clouds.rgb[clouds.frames.index(k)]
    before_k, after_k = before.depth_camera(k).K, after.depth_camera(j).K
    rot, trans = before.cam_from_world[k][:3, :3], before.cam_from_world[k][:3, 3]
    rot2, trans2 = after.cam_from_world[j][:3, :3], after.cam_from_world[j][:3, 3]
    lens = np.linalg.solve(after_k, before_k)  # K'^-1 K
    a = rot2.T @ lens @ rot
    b = rot2.T @ (lens @ trans - trans2)
    return xyz @ a.T + b, rgb


def run_exports(
    final: FinalCameras,
    points: tuple[np.ndarray, np.ndarray],
    points_from: str,
    options: ExportOptions,
    out_dir: Path,
    *,
    masks: bool = False,
    depth: DepthMaps | None = None,
) -> ExportsResult:
    """Write the point cloud, transforms.json (the final cameras) and the optional mesh.

    Args:
        final: the cameras to write; transforms.json lists exactly these frames.
        points: ``(xyz [M, 3] world, rgb [M, 3] in [0, 1])`` in the frame of ``final``.
        points_from: what the points are, for the report.
        masks: the run has masks (``masks/<name>.png``), which transforms.json names per frame.
        depth: the depth maps with the final cameras, for a TSDF mesh (None: no model's depth agrees with
            these cameras; a TSDF mesh is then not written, and says why).
    """
    out_dir = Path(out_dir)
    xyz, rgb = points
    not_written: dict[str, str] = {}
    cloud = None
    if len(xyz):
        cloud = write_point_cloud(out_dir / "points.ply", xyz, rgb)
    else:
        reason = empty_cloud_reason(points_from, masks)
        not_written = {"points.ply": reason} | ({"mesh.ply": reason, "mesh.glb": reason} if options.mesh else {})
        log.warning("points.ply%s not written: %s", " and the mesh" if options.mesh else "", reason)
    files = [f"images/{n}" for n in final.names]
    transforms = write_transforms(
        out_dir / "transforms.json",
        files,
        final.cam_from_world,
        final.cameras,
        ply_file_path=None if cloud is None else "points.ply",
        distortion=final.distortion,
        mask_paths=[f"masks/{n}.png" for n in final.names] if masks else None,
    )
    mesh = None
    if options.mesh and cloud is not None:
        mesh = write_mesh(out_dir, options.mesh_options, points, camera_centers(final.cam_from_world), depth)
        if isinstance(mesh, Skipped):
            not_written |= {"mesh.ply": mesh.reason, "mesh.glb": mesh.reason}
    made = isinstance(mesh, MeshResult)
    return ExportsResult(
        cloud,
        int(len(xyz)),
        points_from,
        transforms,
        mesh.ply if made else None,
        mesh.glb if made else None,
        final.source,
        not_written=not_written,
        mesh_about=mesh.about if made else "",
    )


def export_final_cameras(
    final: FinalCameras,
    ff: FeedForwardResult | Skipped,
    colmap: ColmapResult | Skipped,
    capture: Capture,
    options: ExportOptions,
    fuse: FuseOptions,
    out_dir: Path,
) -> ExportsResult:
    """The exports of a run: the cloud that agrees with the final cameras (COLMAP's sparse points for its
    cameras; the depth maps fused again with the refined cameras; the model's own fused cloud for its
    cameras), then :func:`run_exports`."""
    depth = None
    if isinstance(ff, FeedForwardResult) and final.source is not CameraSource.COLMAP:
        depth = DepthMaps(with_final_cameras(ff.prediction, final), capture.frames_on_demand(final.indices), fuse)
    if final.source is CameraSource.COLMAP and isinstance(colmap, ColmapResult):
        rec = colmap.reconstruction
        points = seed_from_reconstruction(rec) if rec.num_points3D() else (np.zeros((0, 3)), np.zeros((0, 3)))
        what = "COLMAP's sparse points"
    elif isinstance(ff, FeedForwardResult) and final.source is CameraSource.REFINED:
        points = fuse_with_final_cameras(ff.prediction, final, capture.frames_on_demand, fuse, ff.frame_clouds)
        what = "depth maps fused with the refined cameras"
    elif isinstance(ff, FeedForwardResult):
        points, what = (ff.points_xyz, ff.points_rgb), "depth maps fused with the model's cameras"
    else:
        raise AssertionError(f"final cameras from {final.source} without the result they come from")
    return run_exports(final, points, what, options, out_dir, masks=capture.mask_dir is not None, depth=depth)
