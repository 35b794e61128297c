"""Issue 2 end to end: photos -> feed-forward cameras, depth, point maps -> COLMAP / nerfstudio / PLY."""

import json
import shutil

import cv2
import numpy as np
import open3d as o3d
import pycolmap
import pytest
import trimesh

from ffrecon.capture import CaptureOptions
from ffrecon.cli import main
from ffrecon.geometry.metrics import pose_errors
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.models.global_alignment import AlignmentOptions
from ffrecon.models.multiview import MultiviewOptions, predict_multiview
from ffrecon.models.pairwise import PairwiseOptions
from ffrecon.models.runner import MULTIVIEW_INPUT, OnnxModel
from ffrecon.models.stage import FeedForwardOptions
from ffrecon.pipeline import RunOptions, run
from ffrecon.results import Skipped
from ffrecon.sfm.crosscheck.options import ColmapOptions
from ffrecon.sfm.refine.options import RefineOptions
from ffrecon.splat.stage import SplatOptions
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt
from tests.onnx_builders import vggt_like

FF_ONLY = dict(
    colmap=ColmapOptions(enabled=False), refine=RefineOptions(enabled=False), splat=SplatOptions(enabled=False)
)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A 12-frame scene, its simulated model and what the model injects."""
    folder = tmp_path_factory.mktemp("sim")
    scene = make_scene(SceneOptions(num_frames=12, width=224, height=168, seed=3))
    truth = build_simulated_vggt(scene, folder / "sim.onnx", SimulationOptions(seed=3, bad_frames=(5,)))
    return scene, truth, OnnxModel(folder / "sim.onnx")


def _predict(model, scene, **kw):
    infer = lambda batch: model.run({MULTIVIEW_INPUT: batch})  # noqa: E731
    return predict_multiview(list(scene.images), list(scene.names), infer, model.info(), MultiviewOptions(**kw))


def test_pose_error_through_onnx_equals_injected_error(simulated):
    scene, truth, model = simulated
    pred = _predict(model, scene)
    assert model.simulated and pred.model.simulated
    measured = pose_errors(pred.cam_from_world, scene.cam_from_world)
    injected = pose_errors(truth.cam_from_world, scene.cam_from_world)
    np.testing.assert_allclose(measured.per_image_rotation_deg, injected.per_image_rotation_deg, atol=0.02)
    assert measured.auc[5] == pytest.approx(injected.auc[5], abs=0.02)
    assert injected.per_image_rotation_deg.max() > 10, "the injected bad frame shows up"
    # Intrinsics come back in original pixels with the injected focal error.
    np.testing.assert_allclose([c.fx for c in pred.cameras], truth.K[:, 0, 0], rtol=1e-3)


def test_chunked_prediction_agrees_with_one_call(simulated):
    scene, _, model = simulated
    whole = _predict(model, scene, chunk_size=16)
    chunked = _predict(model, scene, chunk_size=4, chunk_overlap=2)
    # Both live in frame 0's camera frame; each call normalises its own scale (as VGGT does), so the
    # two agree up to one global scale, which the chunk Sim(3)s must otherwise keep exactly.
    rot_diff = rotation_angle_deg(np.swapaxes(whole.cam_from_world[:, :, :3], 1, 2) @ chunked.cam_from_world[:, :, :3])
    assert rot_diff.max() < 0.1
    c_whole, c_chunk = camera_centers(whole.cam_from_world), camera_centers(chunked.cam_from_world)
    scale = np.sum(c_whole * c_chunk) / np.sum(c_chunk * c_chunk)
    assert abs(scale - 1) > 1e-3, "per-call normalisation differs between a chunk and the whole set"
    assert np.abs(c_whole - scale * c_chunk).max() < 1e-3 * np.ptp(c_whole, axis=0).max()
    np.testing.assert_allclose(chunked.depth[7] * scale, whole.depth[7], rtol=1e-3, atol=1e-4)


def test_outputs_open_in_colmap_nerfstudio_open3d_trimesh(small_demo, tmp_path):
    out = tmp_path / "out"
    result = run(small_demo.images, out, small_demo.model, RunOptions(**FF_ONLY))
    rec = pycolmap.Reconstruction(str(out / "feedforward" / "sparse"))
    names = sorted(p.name for p in small_demo.images.iterdir())
    assert sorted(im.name for im in rec.images.values()) == names and rec.num_points3D() > 100
    # transforms.json: nerfstudio fields; OpenGL camera (looks down -z, y up).
    tf = json.loads((out / "transforms.json").read_text())
    assert {"fl_x", "fl_y", "cx", "cy", "w", "h", "camera_model", "frames"} <= tf.keys()
    assert len(tf["frames"]) == 8 and all((out / f["file_path"]).is_file() for f in tf["frames"])
    cloud = o3d.io.read_point_cloud(str(out / "points.ply"))
    pts = np.asarray(cloud.points)
    assert len(pts) > 500 and cloud.has_colors()
    for frame in tf["frames"]:
        world_from_cam = np.array(frame["transform_matrix"])
        cam = (pts - world_from_cam[:3, 3]) @ world_from_cam[:3, :3]  # points in the OpenGL camera
        k = {key: frame.get(key, tf[key]) for key in ("fl_x", "fl_y", "cx", "cy")}  # per-frame overrides
        in_front = cam[:, 2] < 0
        x = k["fl_x"] * cam[in_front, 0] / -cam[in_front, 2] + k["cx"]
        y = k["fl_y"] * -cam[in_front, 1] / -cam[in_front, 2] + k["cy"]
        visible = (x > 0) & (x < tf["w"]) & (y > 0) & (y < tf["h"])
        assert visible.sum() > 0.1 * len(pts), "the cloud must project into every view as nerfstudio projects it"
    mesh_cloud = trimesh.load(out / "points.ply")
    assert len(mesh_cloud.vertices) == len(pts)
    assert result.feedforward.prediction.model.simulated is True
    assert json.loads((out / "report.json").read_text())["feedforward"]["model"]["simulated"] is True
    assert "Simulated model" in (out / "report.html").read_text()
    assert result.exit_code == 0


def test_single_photo_gives_depth_camera_and_cloud(small_demo, tmp_path):
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(next(iter(sorted(small_demo.images.iterdir()))), one)
    out = tmp_path / "out"
    result = run(one, out, small_demo.model, RunOptions())
    rec = pycolmap.Reconstruction(str(out / "feedforward" / "sparse"))
    assert rec.num_images() == 1 and rec.num_points3D() > 100
    for stage in (result.colmap, result.gates, result.comparisons, result.refine, result.splat):
        assert isinstance(stage, Skipped) and "one photo" in stage.reason
    assert {"colmap cross-check", "refinement", "splat"} <= {s.stage for s in result.skipped}
    assert len(list((out / "feedforward" / "depth").glob("*.npz"))) == 1


def test_bad_models_and_existing_output_leave_results_intact(small_demo, tmp_path, capsys):
    out = tmp_path / "out"
    (out / ".ffrecon").mkdir(parents=True)  # an earlier ffrecon output (its marker)
    (out / "report.json").write_text('{"earlier": true}')
    # An existing OUT with results: refused, untouched.
    assert main(["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model)]) == 4
    assert "already holds the results of an earlier ffrecon run" in capsys.readouterr().err
    # A model whose outputs hold NaNs: refused even with --overwrite, OUT untouched.
    nan_model = vggt_like(tmp_path / "nan.onnx", fill=float("nan"))
    assert main(["run", str(small_demo.images), "-o", str(out), "--model", str(nan_model), "--overwrite"]) == 3
    assert "non-finite" in capsys.readouterr().err
    # A model with unknown inputs: the message names what was found and what was expected.
    odd = vggt_like(tmp_path / "odd.onnx", input_name="pixels")
    assert main(["run", str(small_demo.images), "-o", str(out), "--model", str(odd), "--overwrite"]) == 3
    err = capsys.readouterr().err
    assert "pixels" in err and "input_images" in err
    for family in ("VGGT", "Depth Anything 3", "Pi3", "MapAnything", "monocular depth", "DUSt3R / MASt3R"):
        assert family in err, family  # every supported family is named with the names it declares
    # A file that is not ONNX at all.
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    assert main(["run", str(small_demo.images), "-o", str(out), "--model", str(junk), "--overwrite"]) == 3
    assert json.loads((out / "report.json").read_text()) == {"earlier": True}
    assert sorted(p.name for p in out.iterdir()) == [".ffrecon", "report.json"]


def test_inspect_model_prints_contract(small_demo, capsys):
    assert main(["inspect-model", str(small_demo.model)]) == 0
    text = capsys.readouterr().out
    assert "multiview" in text and "SIMULATED" in text and "input_images" in text and "pose_enc" in text


@pytest.mark.parametrize("net", ["tiny_vggt.onnx", "tiny_dust3r.onnx"])
@pytest.mark.parametrize("num_images", [1, 3])
def test_tiny_nets_run_through_the_pipeline(net, num_images, tmp_path):
    """The shipped untrained nets exercise the real runner and both adapters end to end."""
    from tests.conftest import MODELS

    scene = make_scene(SceneOptions(num_frames=3, width=112, height=84, seed=5))
    src = tmp_path / "in"
    src.mkdir()
    for name, image in list(zip(scene.names, scene.images))[:num_images]:
        cv2.imwrite(str(src / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    out = tmp_path / "out"
    # Untrained nets give meaningless geometry: a short alignment is enough to exercise the path.
    quick = FeedForwardOptions(pairwise=PairwiseOptions(alignment=AlignmentOptions(iterations=30)))
    result = run(src, out, MODELS / net, RunOptions(feedforward=quick, **FF_ONLY))
    rec = pycolmap.Reconstruction(str(out / "feedforward" / "sparse"))
    assert rec.num_images() == num_images
    assert result.feedforward.prediction.model.family.value == ("multiview" if "vggt" in net else "pairwise")
    assert len(result.feedforward.prediction) == num_images and result.exit_code in (0, 5)


def test_video_input_keeps_the_sharpest_frames(small_demo, tmp_path):
    """A video of the scene, each frame shown three times with two blurred copies: the sharp ones are kept."""
    frames = [cv2.imread(str(p)) for p in sorted(small_demo.images.iterdir())]
    h, w = frames[0].shape[:2]
    clip = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    for image in frames:
        for k in range(3):
            writer.write(image if k == 1 else cv2.GaussianBlur(image, (0, 0), 2))
    writer.release()
    out = tmp_path / "out"
    options = RunOptions(capture=CaptureOptions(video_frames=len(frames)), **FF_ONLY)
    result = run(clip, out, small_demo.model, options)
    assert result.capture.is_video
    assert list(result.capture.names) == [f"clip_{3 * k + 1:06d}.png" for k in range(len(frames))]
    rec = pycolmap.Reconstruction(str(out / "feedforward" / "sparse"))
    assert rec.num_images() == len(frames) and rec.num_points3D() > 100
