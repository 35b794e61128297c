"""The run's mesh (ffrecon.export.mesh): TSDF fusion measured against a synthetic scene's exact surface, the
GLB beside the PLY, and inputs with no surface skipped with the reason."""

from __future__ import annotations

import dataclasses
import functools
import json

import numpy as np
import open3d as o3d
import pytest
import trimesh

from ffrecon import cli
from ffrecon.errors import InputError
from ffrecon.export.mesh import DepthMaps, MeshResult, write_mesh
from ffrecon.export.mesh_accuracy import bounding_diagonal, sample_surface, surface_accuracy
from ffrecon.export.stage import ExportOptions, run_exports
from ffrecon.final_cameras import CameraSource, FinalCameras
from ffrecon.formats.mesh import MeshMethod, MeshOptions
from ffrecon.formats.pointcloud import FuseOptions, fuse_prediction
from ffrecon.geometry.poses import camera_centers
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.types import ModelFamily, ModelInfo, Prediction, Skipped

NO_POINTS = (np.zeros((0, 3)), np.zeros((0, 3)))


@functools.cache
def _scene():
    """12 orbit frames of 128x96 (0.3 s to render), their true depth as the model's, and the exact surface."""
    scene = make_scene(SceneOptions(num_frames=12, width=128, height=96))
    n = len(scene)
    conf = tuple(np.full_like(d, 5.0) for d in scene.depth)
    pred = Prediction(
        scene.names,
        scene.cam_from_world,
        (scene.camera,) * n,
        tuple(scene.depth),
        conf,
        ModelInfo("truth", ModelFamily.MULTIVIEW),
    )
    truth = np.concatenate([scene.frame_points(i).reshape(-1, 3) for i in range(n)])
    extent = bounding_diagonal(truth)
    truth = np.asarray(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(truth)).voxel_down_sample(extent / 1000).points
    )
    return scene, pred, truth, extent


def _depth(pred: Prediction, images) -> DepthMaps:
    return DepthMaps(pred, list(images), FuseOptions())


@pytest.fixture(scope="module")
def true_depth_mesh(tmp_path_factory) -> MeshResult:
    """The TSDF mesh of :func:`_scene`'s true depth with the exact cameras, written once for this module."""
    scene, pred, _, _ = _scene()
    out = tmp_path_factory.mktemp("tsdf")
    return write_mesh(out, MeshOptions(), NO_POINTS, camera_centers(pred.cam_from_world), _depth(pred, scene.images))


def test_the_tsdf_mesh_of_true_depth_lies_on_the_true_surface(true_depth_mesh):
    """Issue 42's bar: Chamfer <= 1 % of the extent (the true points' bounding-box diagonal, 8.6 here) and
    F-score at 1 % >= 0.9. Measured: Chamfer 0.22 %, F 0.998; the tighter 0.4 % bar fails a mesh fused with the
    principal point 2 px off (0.43 %), which the issue's bar lets through."""
    _, _, truth, extent = _scene()
    result = true_depth_mesh
    assert isinstance(result, MeshResult), result
    assert result.method is MeshMethod.TSDF and 0 < result.voxel < extent / 100
    mesh = o3d.io.read_triangle_mesh(str(result.ply))
    score = surface_accuracy(sample_surface(mesh, 100_000), truth, extent, threshold=0.01)
    assert score.chamfer <= 0.01 and score.fscore >= 0.9, score
    assert score.chamfer <= 0.004 and score.fscore >= 0.98, score
    colours = np.asarray(mesh.vertex_colors)
    assert len(colours) == len(mesh.vertices) and colours.std() > 0.05  # coloured from the photos, not flat


def test_a_mesh_shifted_by_two_percent_fails_the_bar():
    """The measure itself: the true points moved by 2 % of the extent are not within 1 %."""
    _, _, truth, extent = _scene()
    score = surface_accuracy(truth + [0.02 * extent, 0, 0], truth, extent, threshold=0.01)
    assert score.fscore < 0.9 and score.chamfer > 0.005


def test_the_glb_holds_the_ply_vertices_in_trimesh(true_depth_mesh):
    result = true_depth_mesh
    ply = trimesh.load(result.ply, process=False)
    glb = trimesh.load(result.glb, force="mesh", process=False)
    assert len(glb.vertices) == len(ply.vertices) == result.num_vertices > 1000
    assert len(glb.faces) == len(ply.faces) == result.num_triangles
    np.testing.assert_allclose(glb.vertices, ply.vertices, atol=1e-5)
    assert glb.visual.vertex_colors.shape == (result.num_vertices, 4)


def _final(pred: Prediction, source: CameraSource = CameraSource.FEEDFORWARD) -> FinalCameras:
    return FinalCameras(tuple(range(len(pred))), pred.names, pred.cam_from_world, pred.cameras, source)


@pytest.mark.parametrize(
    ("change", "why"),
    [
        (lambda d, c: (np.zeros_like(d), c), "no depth pixel"),  # every pixel unknown (or masked out)
        (lambda d, c: (d, np.full_like(c, 0.5)), "no depth pixel"),  # the model unsure of every pixel
        (lambda d, c: (np.where(np.arange(d.size).reshape(d.shape) == 7, d, 0), c), "no triangle"),  # a pixel a frame
    ],
)
def test_depth_with_no_surface_skips_the_mesh_with_the_reason(tmp_path, caplog, change, why):
    scene, pred, _, _ = _scene()
    depth, conf = zip(*(change(d, c) for d, c in zip(pred.depth, pred.depth_conf)))
    bad = dataclasses.replace(pred, depth=tuple(depth), depth_conf=tuple(conf))
    cloud = fuse_prediction(pred, list(scene.images))  # a cloud, so that only the mesh is in question
    result = run_exports(
        _final(bad), cloud, "test", ExportOptions(mesh=True), tmp_path, depth=_depth(bad, scene.images)
    )
    assert result.mesh_ply is None and result.mesh_glb is None and not (tmp_path / "mesh.ply").exists()
    assert why in result.not_written["mesh.ply"] and result.not_written["mesh.glb"] == result.not_written["mesh.ply"]
    assert result.points_ply is not None and json.loads(result.transforms_json.read_text())["frames"]
    assert "mesh not written" in caplog.text


def test_frames_with_broken_cameras_are_left_out_of_the_tsdf(tmp_path):
    scene, pred, _, _ = _scene()
    poses = pred.cam_from_world.copy()
    poses[1:] = np.nan
    broken = dataclasses.replace(pred, cam_from_world=poses)
    result = write_mesh(tmp_path, MeshOptions(), NO_POINTS, camera_centers(poses[:1]), _depth(broken, scene.images))
    assert isinstance(result, MeshResult) and np.isfinite(trimesh.load(result.ply, process=False).vertices).all()
    none = dataclasses.replace(pred, cam_from_world=np.full_like(poses, np.nan))
    result = write_mesh(tmp_path / "none", MeshOptions(), NO_POINTS, camera_centers(poses), _depth(none, scene.images))
    assert isinstance(result, Skipped) and "no depth pixel" in result.reason


def test_tsdf_without_the_models_depth_says_to_use_poisson(tmp_path):
    _, pred, _, _ = _scene()
    cloud = (np.random.default_rng(0).normal(size=(500, 3)), np.full((500, 3), 0.5))
    result = run_exports(
        _final(pred, CameraSource.COLMAP), cloud, "COLMAP's sparse points", ExportOptions(mesh="tsdf"), tmp_path
    )
    assert result.mesh_ply is None and "--mesh poisson" in result.not_written["mesh.ply"]


def test_poisson_of_too_few_points_is_skipped_not_raised(tmp_path):
    _, pred, _, _ = _scene()
    few = (np.random.default_rng(0).normal(size=(20, 3)), np.full((20, 3), 0.5))
    result = run_exports(_final(pred), few, "test", ExportOptions(mesh="poisson"), tmp_path)
    assert result.mesh_ply is None and "too few for a Poisson mesh" in result.not_written["mesh.ply"]


def test_poisson_stays_an_option(tmp_path):
    scene, pred, truth, extent = _scene()
    cloud = fuse_prediction(pred, list(scene.images))
    options = ExportOptions(mesh=MeshMethod.POISSON, mesh_options=MeshOptions(depth=6))
    result = run_exports(_final(pred), cloud, "test", options, tmp_path)
    assert result.mesh_ply is not None and result.mesh_about.startswith("poisson mesh")
    glb = trimesh.load(result.mesh_glb, force="mesh", process=False)
    assert len(glb.vertices) == len(trimesh.load(result.mesh_ply, process=False).vertices)


@pytest.mark.parametrize(
    ("argv", "method"), [([], None), (["--mesh"], MeshMethod.TSDF), (["--mesh", "poisson"], MeshMethod.POISSON)]
)
def test_the_mesh_flag_picks_the_method(argv, method):
    args = cli.parse_args(["run", "photos", "-o", "out", *argv])
    options = ExportOptions(mesh=args.mesh)
    assert options.mesh is method
    assert options.mesh_options.method is (method or MeshMethod.TSDF)


def test_an_unknown_mesh_method_in_python_is_an_input_error():
    with pytest.raises(InputError, match="not a mesh method"):
        ExportOptions(mesh="marching")


def test_an_unknown_mesh_method_is_one_line_and_exit_2(tmp_path, capsys):
    assert cli.main(["run", str(tmp_path / "photos"), "-o", str(tmp_path / "out"), "--mesh", "marching"]) == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'marching'" in err and "Traceback" not in err
    assert len([line for line in err.splitlines() if line.strip() and "fix:" not in line]) == 1, err


def test_a_run_with_mesh_writes_the_tsdf_mesh_of_the_models_depth(small_demo, tmp_path, capsys):
    out = tmp_path / "out"
    run = ["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model)]
    assert cli.main([*run, "--no-colmap", "--no-refine", "--no-splat", "-q", "--mesh", "--force"]) == 0
    assert "Traceback" not in capsys.readouterr().err
    exports = json.loads((out / "report.json").read_text())["exports"]
    assert exports["mesh"]["about"].startswith("tsdf mesh") and "voxel" in exports["mesh"]["about"]
    assert "mesh.ply" not in exports["not_written"]
    ply = trimesh.load(out / "mesh.ply", process=False)
    assert len(ply.faces) > 1000 and len(trimesh.load(out / "mesh.glb", force="mesh", process=False).vertices) == len(
        ply.vertices
    )
    points = trimesh.load(out / "points.ply")  # the mesh lies where the cloud is (the same depth, the same cameras)
    lo, hi = np.percentile(points.vertices, [1, 99], axis=0)
    inside = np.all((ply.vertices >= lo - 0.05 * (hi - lo)) & (ply.vertices <= hi + 0.05 * (hi - lo)), axis=1)
    assert inside.mean() > 0.95
