"""Benchmark: how close the mesh (TSDF, Poisson) and the fused point cloud come to a synthetic scene's exact surface.

For each synthetic scene (``ffrecon.synthetic``, exact depth and cameras), the depth maps are those of the
simulated model (``SimulationOptions.depth_error``: std of a smooth relative depth error per frame; 0: the true
depth) with, per row, the exact cameras or the model's own noisy ones (``rotation_noise_deg`` 2.5,
``translation_noise`` 0.03, ``focal_error`` 0.03: what the refinement starts from). From them, with the
export stage's own code and defaults:

- ``tsdf``: :func:`ffrecon.export.mesh.write_mesh` (TSDF, cleaned), 200,000 points sampled on it by area;
- ``poisson``: the same with ``MeshMethod.POISSON`` on the fused cloud, sampled the same way;
- ``cloud``: the fused point cloud itself (``ffrecon.formats.pointcloud.fuse_prediction``).

The truth is every frame's exact depth unprojected (the surface the cameras see), voxel-downsampled to 1/1000
of its extent, the extent being its bounding-box diagonal. Chamfer = mean of accuracy and completeness, F-score
at 1 % of the extent (:mod:`ffrecon.export.mesh_accuracy`). Prints a Markdown table.

With ``--run OUT --scene DIR`` it measures instead what a run wrote (``OUT/mesh.ply``, ``OUT/points.ply``, in the
frame of ``OUT/sparse/0``, the final cameras) against the scene it ran on (``DIR``: the demo's cache folder with
``ground_truth.json`` and ``depth.npz``), after the Sim(3) that best maps the final camera centres onto the true
ones (Umeyama): the mesh with the refined cameras, as ``ffrecon demo --mesh`` makes it.

Usage (from the repository root)::

    .venv/bin/python tools/bench_mesh.py [--frames 24] [--size 320x240] [--depth-errors 0 0.01 0.03]
    .venv/bin/python tools/bench_mesh.py --run OUT --scene ~/.cache/ffrecon/demo-KEY
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pycolmap

from ffrecon.colmap_io import cam_from_world_by_name
from ffrecon.export.mesh import DepthMaps, write_mesh
from ffrecon.export.mesh_accuracy import bounding_diagonal, sample_surface, surface_accuracy
from ffrecon.formats.mesh import MeshMethod, MeshOptions
from ffrecon.formats.pointcloud import FuseOptions, fuse_prediction
from ffrecon.geometry.alignment import umeyama
from ffrecon.geometry.poses import camera_centers
from ffrecon.synthetic import CameraPath, SceneOptions, SyntheticScene, load_scene, make_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate
from ffrecon.types import Prediction

SAMPLES = 200_000


def truth_points(scene: SyntheticScene) -> tuple[np.ndarray, float]:
    """The exact surface the scene's frames see, as points (1/1000 of the extent apart), and its extent."""
    points = np.concatenate([scene.frame_points(i).reshape(-1, 3) for i in range(len(scene))])
    extent = bounding_diagonal(points)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(extent / 1000)
    return np.asarray(cloud.points), extent


def model_prediction(scene: SyntheticScene, depth_error: float, exact_cameras: bool) -> Prediction:
    """The simulated model's depth maps (and confidences) with the exact cameras or the model's own."""
    options = SimulationOptions(depth_error=depth_error)
    truth, _ = simulate(scene, options)
    pred = prediction_from_truth(scene, truth, options)
    if depth_error == 0:  # no error: prediction_from_truth's confidence would be 1 + 9 exp(0) everywhere
        pred = dataclasses.replace(pred, depth_conf=tuple(np.full_like(d, 5.0) for d in pred.depth))
    if exact_cameras:
        pred = dataclasses.replace(pred, cam_from_world=scene.cam_from_world, cameras=(scene.camera,) * len(scene))
    return pred


def measure(pred: Prediction, scene: SyntheticScene, truth: np.ndarray, extent: float, out: Path) -> dict:
    """``{method: (SurfaceAccuracy, seconds, size)}`` for the TSDF mesh, the Poisson mesh and the fused cloud."""
    fuse = FuseOptions()
    start = time.perf_counter()
    cloud = fuse_prediction(pred, list(scene.images), fuse)
    rows = {"cloud": (surface_accuracy(cloud[0], truth, extent), time.perf_counter() - start, len(cloud[0]))}
    depth = DepthMaps(pred, list(scene.images), fuse)
    for method in (MeshMethod.TSDF, MeshMethod.POISSON):
        start = time.perf_counter()
        result = write_mesh(out, MeshOptions(method=method), cloud, camera_centers(pred.cam_from_world), depth)
        seconds = time.perf_counter() - start
        mesh = o3d.io.read_triangle_mesh(str(result.ply))
        points = sample_surface(mesh, SAMPLES)
        rows[method.value] = (surface_accuracy(points, truth, extent), seconds, len(mesh.vertices))
    return rows


def measure_run(run: Path, scene_dir: Path) -> None:
    """Print the rows of a run's mesh.ply and points.ply, aligned to the true cameras by their centres."""
    scene = load_scene(scene_dir)
    truth, extent = truth_points(scene)
    rec = pycolmap.Reconstruction(str(run / "sparse" / "0"))
    poses, registered = cam_from_world_by_name(rec, scene.names)
    true_from_run = umeyama(camera_centers(poses[registered]), camera_centers(scene.cam_from_world[registered]))
    print(
        f"| {scene_dir.name} ({extent:.2f}), {int(registered.sum())}/{len(scene)} final cameras | method | "
        "Chamfer % | acc % | comp % | F@1% | points |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name in ("mesh.ply", "points.ply"):
        if not (run / name).is_file():
            print(f"| {run.name} | {name} | not written | | | | |")
            continue
        if name == "mesh.ply":
            points = sample_surface(o3d.io.read_triangle_mesh(str(run / name)), SAMPLES)
        else:
            points = np.asarray(o3d.io.read_point_cloud(str(run / name)).points)
        acc = surface_accuracy(true_from_run.apply(points), truth, extent)
        print(
            f"| {run.name} | {name} | {acc.chamfer * 100:.3f} | {acc.accuracy * 100:.3f} "
            f"| {acc.completeness * 100:.3f} | {acc.fscore:.3f} | {len(points)} |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--size", default="320x240", help="WxH of the rendered frames")
    parser.add_argument("--depth-errors", type=float, nargs="+", default=[0.0, 0.01, 0.03])
    parser.add_argument(
        "--paths", nargs="+", default=["orbit", "arc", "forward"], choices=[p.value for p in CameraPath]
    )
    parser.add_argument("--run", type=Path, help="measure this run folder's mesh.ply and points.ply instead")
    parser.add_argument("--scene", type=Path, help="with --run: the synthetic scene folder the run was made from")
    args = parser.parse_args()
    if args.run is not None:
        measure_run(args.run, args.scene)
        return
    w, h = (int(v) for v in args.size.split("x"))
    print("| scene (extent) | cameras | depth error | method | Chamfer % | acc % | comp % | F@1% | size | s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.paths:
            scene = make_scene(SceneOptions(num_frames=args.frames, width=w, height=h, path=CameraPath(path)))
            truth, extent = truth_points(scene)
            for exact in (True, False):
                for depth_error in args.depth_errors:
                    if not exact and depth_error != max(args.depth_errors):
                        continue  # the model's cameras: one row, with the model's depth error
                    rows = measure(model_prediction(scene, depth_error, exact), scene, truth, extent, Path(tmp))
                    for method, (acc, seconds, size) in rows.items():
                        print(
                            f"| {path} ({extent:.2f}) | {'exact' if exact else 'model'} | {depth_error * 100:g} % "
                            f"| {method} | {acc.chamfer * 100:.3f} | {acc.accuracy * 100:.3f} "
                            f"| {acc.completeness * 100:.3f} | {acc.fscore:.3f} | {size} | {seconds:.1f} |"
                        )


if __name__ == "__main__":
    main()
