"""A coloured surface mesh from the fused point cloud: open3d screened Poisson, trimesh GLB."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh

from ffrecon.checks import check_number, check_shape
from ffrecon.errors import InputError

logger = logging.getLogger("ffrecon.export")


@dataclass(frozen=True, kw_only=True)
class MeshOptions:
    depth: int = 8  # Poisson octree depth (2^depth cells across the cloud)
    density_quantile: float = 0.05  # drop vertices supported by the fewest points (Poisson's extrapolation)
    normal_neighbours: int = 30

    def __post_init__(self) -> None:
        check_number("MeshOptions.depth", self.depth, low=1, integer=True)
        check_number("MeshOptions.density_quantile", self.density_quantile, low=0, high=1)
        check_number("MeshOptions.normal_neighbours", self.normal_neighbours, low=1, integer=True)


def poisson_mesh(
    xyz: np.ndarray, rgb: np.ndarray, camera_centers: np.ndarray, options: MeshOptions = MeshOptions()
) -> o3d.geometry.TriangleMesh:
    """Screened Poisson surface of ``xyz [M, 3]`` (world) with colours ``rgb [M, 3]`` in [0, 1].

    Normals are estimated from neighbours and flipped to face the nearest of ``camera_centers
    [N, 3]`` (every point was seen from some camera, so its surface faces that way).
    """
    check_shape("xyz", xyz, (None, 3))
    check_shape("rgb", rgb, (len(xyz), 3))
    if len(xyz) < 100:
        raise InputError(f"only {len(xyz)} points: too few for a Poisson mesh", "mesh a denser point cloud")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz, np.float64)))
    pcd.colors = o3d.utility.Vector3dVector(np.clip(np.asarray(rgb, np.float64), 0, 1))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(options.normal_neighbours))
    normals = np.asarray(pcd.normals)
    pts = np.asarray(pcd.points)
    centers = np.asarray(camera_centers, np.float64).reshape(-1, 3)
    to_camera = centers[0] - pts
    best = np.sum(to_camera**2, axis=1)
    for c in centers[1:]:
        d = c - pts
        dist = np.sum(d**2, axis=1)
        closer = dist < best
        to_camera[closer], best[closer] = d[closer], dist[closer]
    flip = np.sum(normals * to_camera, axis=1) < 0
    normals[flip] *= -1
    pcd.normals = o3d.utility.Vector3dVector(normals)
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=options.depth)
    densities = np.asarray(densities)
    if options.density_quantile > 0 and len(densities):
        mesh.remove_vertices_by_mask(densities < np.quantile(densities, options.density_quantile))
    mesh.remove_unreferenced_vertices()
    logger.info("Poisson mesh: %d vertices, %d triangles", len(mesh.vertices), len(mesh.triangles))
    return mesh


def write_mesh(
    ply_path: Path,
    glb_path: Path | None,
    xyz: np.ndarray,
    rgb: np.ndarray,
    camera_centers: np.ndarray,
    options: MeshOptions = MeshOptions(),
) -> tuple[Path, Path | None]:
    """Write the Poisson mesh as PLY (open3d) and, when ``glb_path`` is given, as GLB (trimesh)."""
    mesh = poisson_mesh(xyz, rgb, camera_centers, options)
    ply_path = Path(ply_path)
    ply_path.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_triangle_mesh(str(ply_path), mesh, write_ascii=False):
        raise OSError(f"open3d could not write {ply_path}")
    if glb_path is not None:
        colours = (np.clip(np.asarray(mesh.vertex_colors), 0, 1) * 255).astype(np.uint8)
        tm = trimesh.Trimesh(
            vertices=np.asarray(mesh.vertices),
            faces=np.asarray(mesh.triangles),
            vertex_colors=np.concatenate([colours, np.full((len(colours), 1), 255, np.uint8)], axis=1),
            process=False,
        )
        Path(glb_path).write_bytes(tm.export(file_type="glb"))
    return ply_path, (Path(glb_path) if glb_path is not None else None)
