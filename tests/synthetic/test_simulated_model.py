"""The simulated VGGT-contract model: ground truth plus exactly the injected error, for any frame subset."""

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from ffrecon.errors import InputError
from ffrecon.geometry.metrics import pose_errors
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.projection import unproject_depth
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.models.vggt import decode_pose_enc, decode_vggt_outputs, preprocess_vggt
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt, injected_cam_from_first
from ffrecon.types import ModelFamily, ModelInfo

OPTIONS = SimulationOptions(bad_frames=(3,), seed=1)
SUBSET = [5, 2, 7, 0, 3]


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    scene = make_scene(SceneOptions(num_frames=8, width=224, height=168, seed=2))
    path = tmp_path_factory.mktemp("sim") / "sim.onnx"
    truth = build_simulated_vggt(scene, path, OPTIONS)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    batch, transforms = preprocess_vggt(list(scene.images))

    def run(frames):
        outputs = session.run(None, {"input_images": batch[frames]})
        return dict(zip([o.name for o in session.get_outputs()], outputs))

    return scene, truth, path, run, transforms


def test_metadata_says_simulated(sim):
    scene, _, path, _, _ = sim
    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["ffrecon.simulated"] == "true" and "SIMULATED" in model.doc_string
    assert json.loads(meta["ffrecon.scene"])["names"] == list(scene.names)
    assert json.loads(meta["ffrecon.simulation"])["bad_frames"] == [3]
    assert model.opset_import[0].version >= 17
    assert model.graph.input[0].name == "input_images"


@pytest.mark.parametrize("frames", [list(range(8)), SUBSET], ids=["all", "subset"])
def test_contract_and_pose_errors_equal_the_injected_ones(sim, frames):
    scene, truth, _, run, _ = sim
    out = run(frames)
    s, hn, wn = len(frames), 392, 518
    expected_shapes = {
        "pose_enc": (1, s, 9),
        "depth": (1, s, hn, wn, 1),
        "depth_conf": (1, s, hn, wn),
        "world_points": (1, s, hn, wn, 3),
        "world_points_conf": (1, s, hn, wn),
        "images": (1, s, 3, hn, wn),
    }
    assert {k: v.shape for k, v in out.items()} == expected_shapes
    assert all(v.dtype == np.float32 and np.isfinite(v).all() for v in out.values())
    assert out["depth"].min() > 0 and out["depth_conf"].min() >= 1 and out["world_points_conf"].min() >= 1
    np.testing.assert_array_equal(out["images"][0], preprocess_vggt([scene.images[k] for k in frames])[0])
    np.testing.assert_allclose(np.linalg.norm(out["pose_enc"][0, :, 3:7], axis=1), 1.0, atol=1e-6)

    cam_from_world, _ = decode_pose_enc(out["pose_enc"][0], (hn, wn))
    np.testing.assert_allclose(cam_from_world[0], np.eye(3, 4), atol=1e-6)  # the first input frame is the world
    measured = pose_errors(cam_from_world, scene.cam_from_world[frames]).per_image_rotation_deg
    injected = pose_errors(truth.cam_from_world[frames], scene.cam_from_world[frames]).per_image_rotation_deg
    np.testing.assert_allclose(measured, injected, atol=0.02)
    bad = frames.index(3)
    assert injected[bad] > 12 and np.delete(injected, bad).max() < 6 and np.delete(injected, bad).min() > 0.3
    # Relative poses equal the injected ones re-expressed in the first frame, up to one scale.
    expected = injected_cam_from_first(truth, frames)
    assert rotation_angle_deg(np.swapaxes(cam_from_world[:, :, :3], 1, 2) @ expected[:, :, :3]).max() < 1e-3
    scale = np.linalg.norm(expected[1:, :, 3], axis=1) / np.linalg.norm(cam_from_world[1:, :, 3], axis=1)
    np.testing.assert_allclose(cam_from_world[1:, :, 3] * scale[:, None], expected[1:, :, 3], atol=1e-5)
    assert np.ptp(scale) < 1e-5 * scale.mean()
    # VGGT-like normalisation: all the call's points lie at mean distance 1 from the first camera.
    assert np.linalg.norm(out["world_points"][0], axis=-1).mean() == pytest.approx(1.0, abs=1e-4)


def test_depth_intrinsics_and_points_are_the_injected_ones(sim):
    scene, truth, _, run, transforms = sim
    out = run(SUBSET)
    info = ModelInfo(path="sim.onnx", family=ModelFamily.MULTIVIEW, simulated=True)
    pred = decode_vggt_outputs(out, [transforms[k] for k in SUBSET], [scene.names[k] for k in SUBSET], info)
    expected = injected_cam_from_first(truth, SUBSET)
    scale = np.linalg.norm(expected[1, :, 3]) / np.linalg.norm(pred.cam_from_world[1, :, 3])
    for local, k in enumerate(SUBSET):
        np.testing.assert_allclose(pred.cameras[local].K, truth.K[k], rtol=1e-5, atol=1e-4)
        rel = pred.depth[local] * scale / truth.depth[k] - 1
        # Bilinear resampling network -> original blurs depth edges only.
        assert np.median(np.abs(rel)) < 1e-4 and np.quantile(np.abs(rel), 0.9) < 2e-3
        # The point head agrees with the depth unprojected with the predicted camera.
        net_K = np.diag(
            [
                518 / 2 / np.tan(out["pose_enc"][0, local, 8] / 2),
                392 / 2 / np.tan(out["pose_enc"][0, local, 7] / 2),
                1.0,
            ]
        )
        net_K[:2, 2] = [518 / 2, 392 / 2]
        pts = unproject_depth(out["depth"][0, local, :, :, 0], net_K, pred.cam_from_world[local])
        np.testing.assert_allclose(out["world_points"][0, local], pts, atol=2e-5)
    # Injected depth error has the requested size; confidence drops where it is large.
    assert np.std(truth.depth_error) == pytest.approx(OPTIONS.depth_error, rel=0.5)
    conf = np.concatenate([c.ravel() for c in pred.depth_conf])
    err = np.concatenate([np.abs(truth.depth_error[k]).ravel() for k in SUBSET])
    assert conf.min() >= 1 and np.corrcoef(conf, err)[0, 1] < -0.9


def test_poses_and_focal_error_have_the_requested_size(sim):
    scene, truth, *_ = sim
    centre_err = np.linalg.norm(camera_centers(truth.cam_from_world) - camera_centers(scene.cam_from_world), axis=1)
    scene_distance = np.mean([np.median(d) for d in scene.depth])
    rms = np.sqrt(np.mean(np.delete(centre_err, 3) ** 2)) / scene_distance
    assert 0.4 * OPTIONS.translation_noise < rms < 2 * OPTIONS.translation_noise
    focal = truth.K[:, 0, 0] / scene.camera.fx - 1
    assert np.all(np.abs(np.abs(focal) - OPTIONS.focal_error) < 0.5 * OPTIONS.focal_error)
    rot = rotation_angle_deg(np.swapaxes(truth.cam_from_world[:, :, :3], 1, 2) @ scene.cam_from_world[:, :, :3])
    np.testing.assert_allclose(rot[3], OPTIONS.bad_rotation_deg, atol=1e-9)
    assert np.all(
        (np.delete(rot, 3) >= 0.5 * OPTIONS.rotation_noise_deg - 1e-9)
        & (np.delete(rot, 3) <= 1.5 * OPTIONS.rotation_noise_deg + 1e-9)
    )


def test_zero_error_model_returns_ground_truth(tmp_path):
    scene = make_scene(SceneOptions(num_frames=3, width=112, height=84, seed=0))
    zero = SimulationOptions(rotation_noise_deg=0, translation_noise=0, focal_error=0, depth_error=0)
    truth = build_simulated_vggt(scene, tmp_path / "zero.onnx", zero)
    np.testing.assert_allclose(truth.cam_from_world, scene.cam_from_world, atol=1e-12)
    session = ort.InferenceSession(str(tmp_path / "zero.onnx"), providers=["CPUExecutionProvider"])
    batch, _ = preprocess_vggt(list(scene.images))
    pose_enc = session.run(["pose_enc"], {"input_images": batch[[2, 0, 1]]})[0][0]
    cam_from_world, K = decode_pose_enc(pose_enc, batch.shape[2:])
    errors = pose_errors(cam_from_world, scene.cam_from_world[[2, 0, 1]])
    assert errors.per_image_rotation_deg.max() < 1e-4 and errors.ate_relative < 1e-5
    np.testing.assert_allclose(K[:, 0, 0] * scene.options.width / 518, scene.camera.fx, rtol=1e-5)
    with pytest.raises(ValueError, match="bad_frames"):
        build_simulated_vggt(scene, tmp_path / "bad.onnx", SimulationOptions(bad_frames=(3,)))


def test_depth_stored_at_a_stride_is_upsampled_in_the_graph(tmp_path):
    """``depth_stride`` 4: a model about 16 times smaller whose depth and confidence are the full-resolution
    ones away from depth edges (bilinear upsampling of area averages), for the long-capture benchmarks."""
    scene = make_scene(SceneOptions(num_frames=4, width=320, height=240, seed=2))
    outs = {}
    for stride in (1, 4):
        path = tmp_path / f"s{stride}.onnx"
        build_simulated_vggt(scene, path, SimulationOptions(seed=1, depth_stride=stride))
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        batch, _ = preprocess_vggt(list(scene.images))
        values = session.run(None, {"input_images": batch})
        stored = {t.name: len(t.raw_data) for t in onnx.load(str(path)).graph.initializer}
        per_frame = sum(size for name, size in stored.items() if name.split("_")[0] in ("depth", "conf"))
        outs[stride] = (dict(zip([o.name for o in session.get_outputs()], values)), per_frame)
    (full, full_bytes), (strided, strided_bytes) = outs[1], outs[4]
    assert 0 < strided_bytes < full_bytes / 14  # what grows with the frames: depth and confidence
    assert strided["depth"].shape == full["depth"].shape
    np.testing.assert_allclose(strided["pose_enc"][..., 7:], full["pose_enc"][..., 7:], rtol=1e-6)  # same focal
    relative = np.abs(strided["depth"] / full["depth"] - 1)
    assert np.median(relative) < 0.005 and np.quantile(relative, 0.9) < 0.05
    with pytest.raises(InputError, match="depth_stride"):
        SimulationOptions(depth_stride=0)


def test_drift_turns_each_slot_of_a_call_about_the_vertical(tmp_path):
    """``drift_deg_per_slot``: the k-th input frame's camera is the drift-free one in a world turned k times the
    drift about world z through the first frame's centre; its depth and focal are unchanged. So the same
    frames called in another order drift differently, which is what chained chunks accumulate."""
    scene = make_scene(SceneOptions(num_frames=6, width=224, height=168, seed=2))
    sessions = {}
    for drift in (0.0, 0.5):
        path = tmp_path / f"d{drift}.onnx"
        truth = build_simulated_vggt(scene, path, SimulationOptions(seed=1, drift_deg_per_slot=drift))
        sessions[drift] = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    batch, _ = preprocess_vggt(list(scene.images))
    frames = [1, 2, 3, 4, 5]
    plain, drifted = (
        dict(zip(["pose_enc", "depth"], s.run(["pose_enc", "depth"], {"input_images": batch[frames]})))
        for s in sessions.values()
    )
    np.testing.assert_allclose(drifted["depth"], plain["depth"], rtol=1e-5)
    np.testing.assert_allclose(drifted["pose_enc"][0, :, 7:], plain["pose_enc"][0, :, 7:], rtol=1e-6)
    cam_plain, _ = decode_pose_enc(plain["pose_enc"][0], batch.shape[2:])
    cam_drift, _ = decode_pose_enc(drifted["pose_enc"][0], batch.shape[2:])
    # cam_from_first of slot k: [R D_k^T | t] in the world of the first camera, D_k a turn about world z.
    world_z_in_first = truth.cam_from_world[frames[0], :, :3] @ np.array([0.0, 0.0, 1.0])  # the model's first camera
    for k in range(len(frames)):
        turn = cam_plain[k, :, :3].T @ cam_drift[k, :, :3]  # D_k^T, expressed in the first camera's frame
        assert rotation_angle_deg(turn[None])[0] == pytest.approx(0.5 * k, abs=1e-3)
        if k:
            axis = np.array([turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0], turn[1, 0] - turn[0, 1]])
            assert abs(axis @ world_z_in_first) / np.linalg.norm(axis) > 0.999
    # The first frame's centre is the pivot; the others move sideways about it (their distance from it is kept).
    centres_plain, centres_drift = camera_centers(cam_plain), camera_centers(cam_drift)
    np.testing.assert_allclose(np.linalg.norm(centres_drift, axis=1), np.linalg.norm(centres_plain, axis=1), rtol=1e-4)
    assert np.linalg.norm(centres_drift[-1] - centres_plain[-1]) > 1e-3 * np.linalg.norm(centres_plain[-1])
    with pytest.raises(InputError, match="drift_deg_per_slot"):
        SimulationOptions(drift_deg_per_slot=-0.1)
