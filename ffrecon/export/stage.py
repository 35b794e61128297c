"""The export stage: the files other tools read, written with the final cameras.

``run_exports`` writes ``points.ply`` (the depth maps fused with the final cameras), the nerfstudio
``transforms.json`` and, on request, a Poisson mesh (``mesh.ply``, ``mesh.glb``). The COLMAP models
are written by the stages that make them; the report by :mod:`ffrecon.export.report`.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ffrecon.export.mesh import MeshOptions, write_mesh
from ffrecon.export.nerfstudio import write_transforms
from ffrecon.export.pointcloud import FuseOptions, fuse_prediction, write_point_cloud
from ffrecon.geometry.poses import camera_centers
from ffrecon.types import PinholeCamera, Prediction

log = logging.getLogger("ffrecon.export")
OUTPUTS = ("points.ply", "transforms.json", "mesh.ply", "mesh.glb")  # relative to the run folder


@dataclass(frozen=True, kw_only=True)
class ExportOptions:
    mesh: bool = False  # Poisson mesh of the fused cloud: mesh.ply and mesh.glb
    mesh_options: MeshOptions = field(default_factory=MeshOptions)


@dataclass(frozen=True)
class ExportsResult:
    """Files written by the export stage (paths in the run folder)."""

    points_ply: Path
    num_points: int
    transforms_json: Path
    mesh_ply: Path | None
    mesh_glb: Path | None
    cameras_from: str  # "refined" or "feed-forward": the cameras the files use


def run_exports(
    prediction: Prediction,
    read_images: Callable[[], list[np.ndarray]],
    final: tuple[np.ndarray, Sequence[PinholeCamera]] | None,
    fused: tuple[np.ndarray, np.ndarray],
    fuse: FuseOptions,
    options: ExportOptions,
    out_dir: Path,
) -> ExportsResult:
    """Write the point cloud, transforms.json and the optional mesh.

    Args:
        prediction: the feed-forward prediction (depth maps, feed-forward cameras).
        read_images: returns the frames as ``[H, W, 3]`` uint8 RGB (read only when re-fusing).
        final: refined ``(cam_from_world [N, 3, 4], cameras)`` in the prediction's world frame, or
            None to keep the feed-forward cameras.
        fused: the feed-forward stage's fused cloud ``(xyz [M, 3], rgb [M, 3] in [0, 1])``, used as
            it is when the cameras are the feed-forward ones.
    """
    out_dir = Path(out_dir)
    xyz, rgb = fused
    cam_from_world, cameras = prediction.cam_from_world, prediction.cameras
    if final is not None:
        # Re-fuse the depth maps with the refined cameras so points.ply agrees with sparse/0.
        cam_from_world, cameras = final[0], tuple(final[1])
        moved = dataclasses.replace(prediction, cam_from_world=cam_from_world, cameras=cameras)
        xyz, rgb = fuse_prediction(moved, read_images(), fuse)
    points = write_point_cloud(out_dir / "points.ply", xyz, rgb)
    files = [f"images/{n}" for n in prediction.names]
    transforms = write_transforms(
        out_dir / "transforms.json", files, cam_from_world, cameras, ply_file_path="points.ply"
    )
    mesh_ply = mesh_glb = None
    if options.mesh:
        mesh_ply, mesh_glb = write_mesh(
            out_dir / "mesh.ply", out_dir / "mesh.glb", xyz, rgb, camera_centers(cam_from_world), options.mesh_options
        )
    cameras_from = "refined" if final is not None else "feed-forward"
    return ExportsResult(points, int(len(xyz)), transforms, mesh_ply, mesh_glb, cameras_from)
