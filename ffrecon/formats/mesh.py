"""Coloured surface meshes: open3d screened Poisson of a point cloud, small-component cleaning, PLY and GLB files.

The TSDF fusion of depth maps (the default mesh) lives with the export stage (:mod:`ffrecon.export.mesh`); this
module holds what a mesh is once made: its options, the Poisson alternative, the cleaning and the writers
(``mesh.ply`` by open3d, ``mesh.glb`` by trimesh, with the same vertices in the same order).
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ffrecon.checks import check_number, check_shape
from ffrecon.errors import InputError

if TYPE_CHECKING:
    import open3d as o3d

logger = logging.getLogger("ffrecon.export")


class MeshMethod(enum.StrEnum):
    TSDF = "tsdf"  # TSDF fusion of the final cameras' depth maps (open3d ScalableTSDFVolume)
    POISSON = "poisson"  # screened Poisson surface of the fused point cloud


@dataclass(frozen=True, kw_only=True)
class MeshOptions:
    method: MeshMethod = MeshMethod.TSDF
    # TSDF: the voxel is this fraction of the diagonal of the fused depth points' 2-98 % extent (1/400: about
    # 2 cm in the synthetic 6 x 6 x 2.6 m room); the signed distance is truncated at trunc_voxels voxels (8: a
    # 3 % depth error at 3 m, 9 cm, stays inside; 4 gave F@1% 0.88 instead of 0.90 there, tools/bench_mesh.py).
    voxel_fraction: float = 1 / 400
    trunc_voxels: float = 8.0
    min_views: int = 1  # TSDF voxels that fewer frames' depth reaches make no surface
    depth: int = 8  # Poisson octree depth (2^depth cells across the cloud)
    density_quantile: float = 0.05  # drop vertices supported by the fewest points (Poisson's extrapolation)
    normal_neighbours: int = 30
    # Connected components with fewer triangles than this fraction of the mesh's are removed (floaters).
    min_component_fraction: float = 0.002

    def __post_init__(self) -> None:
        check_number("MeshOptions.voxel_fraction", self.voxel_fraction, low=0, high=0.1, low_open=True)
        check_number("MeshOptions.trunc_voxels", self.trunc_voxels, low=1)
        check_number("MeshOptions.min_views", self.min_views, low=1, integer=True)
        check_number("MeshOptions.depth", self.depth, low=1, integer=True)
        check_number("MeshOptions.density_quantile", self.density_quantile, low=0, high=1)
        check_number("MeshOptions.normal_neighbours", self.normal_neighbours, low=1, integer=True)
        check_number("MeshOptions.min_component_fraction", self.min_component_fraction, low=0, high=1)


def poisson_mesh(
    xyz: np.ndarray, rgb: np.ndarray, camera_centers: np.ndarray, options: MeshOptions = MeshOptions()
) -> o3d.geometry.TriangleMesh:
    """Screened Poisson surface of ``xyz [M, 3]`` (world) with colours ``rgb [M, 3]`` in [0, 1].

    Normals are estimated from neighbours and flipped to face the nearest of ``camera_centers
    [N, 3]`` (every point was seen from some camera, so its surface faces that way).
    """
    import open3d as o3d  # 0.45 s: here, only the runs that make a mesh need it

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


def remove_small_components(
    mesh: o3d.geometry.TriangleMesh, min_fraction: float
) -> tuple[o3d.geometry.TriangleMesh, int]:
    """``mesh`` without the connected components (edge-connected triangles) holding fewer than ``min_fraction``
    of its triangles, and how many components went. Changes ``mesh`` in place.

    >>> import open3d as o3d
    >>> box = o3d.geometry.TriangleMesh.create_box()
    >>> speck = o3d.geometry.TriangleMesh.create_tetrahedron(radius=0.01).translate((5.0, 0.0, 0.0))
    >>> mesh, removed = remove_small_components(box + speck, 0.3)
    >>> len(mesh.triangles), removed
    (12, 1)
    """
    if len(mesh.triangles) == 0:
        return mesh, 0
    clusters, sizes, _ = mesh.cluster_connected_triangles()
    clusters, sizes = np.asarray(clusters), np.asarray(sizes)
    small = sizes < min_fraction * len(clusters)
    if small.any():
        mesh.remove_triangles_by_mask(small[clusters])
        mesh.remove_unreferenced_vertices()
    return mesh, int(small.sum())


def write_mesh_files(
    mesh: o3d.geometry.TriangleMesh, ply_path: Path, glb_path: Path | None
) -> tuple[Path, Path | None]:
    """Write ``mesh`` as binary PLY (open3d) and, when ``glb_path`` is given, as GLB (trimesh) with the same
    vertices in the same order, vertex colours as RGBA8 and vertex normals."""
    import open3d as o3d  # 0.45 s: here, only the runs that make a mesh need it

    ply_path = Path(ply_path)
    ply_path.parent.mkdir(parents=True, exist_ok=True)
    if not mesh.has_vertex_normals():
        mesh.compute_vertex_normals()
    if not o3d.io.write_triangle_mesh(str(ply_path), mesh, write_ascii=False):
        raise OSError(f"open3d could not write {ply_path}")
    if glb_path is None:
        return ply_path, None
    vertices = np.asarray(mesh.vertices)
    if mesh.has_vertex_colors():
        rgb = np.round(np.clip(np.asarray(mesh.vertex_colors), 0, 1) * 255).astype(np.uint8)
    else:
        rgb = np.full((len(vertices), 3), 200, np.uint8)
    import trimesh  # here, not at the top: 0.3 s of every run's start for the runs that write a mesh

    tm = trimesh.Trimesh(
        vertices=vertices,
        faces=np.asarray(mesh.triangles),
        vertex_normals=np.asarray(mesh.vertex_normals),
        vertex_colors=np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1),
        process=False,
    )
    Path(glb_path).write_bytes(tm.export(file_type="glb"))
    return ply_path, Path(glb_path)
