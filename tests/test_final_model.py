"""``sparse/0`` holds every final camera: the source model's, plus the final frames it lacks (posed, no points)."""

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pycolmap

from ffrecon.colmap_io import (
    cam_from_world_by_name,
    reconstruction_from_cameras,
    write_reconstruction,
)
from ffrecon.final_cameras import (
    CameraSource,
    FinalCameras,
    _refined_final_cameras,
    select_final_cameras,
    write_final_model,
)
from ffrecon.models.stage import FeedForwardResult
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.verify.verdicts import CameraEvidence, CameraStatus, EvidenceResult
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate
from ffrecon.types import PinholeCamera, Skipped


def _poses(n: int, rng) -> np.ndarray:
    poses = []
    for _ in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        poses.append(np.hstack([q * np.sign(np.linalg.det(q)), rng.normal(size=(3, 1))]))
    return np.array(poses)


def test_frames_the_refinement_left_out_are_added_posed_without_points(tmp_path: Path):
    rng = np.random.default_rng(0)
    names = [f"frame_{i:03d}.png" for i in range(4)]
    poses = _poses(4, rng)
    cam = PinholeCamera(320, 240, 300.0, 301.0, 160.0, 120.0)
    refined = reconstruction_from_cameras(names[:3], poses[:3], [cam] * 3, rng.normal(size=(50, 3)))
    refine_dir = write_reconstruction(refined, tmp_path / "refine" / "model")
    lens = (0.01, -0.002, 0.0, 0.0)
    final = FinalCameras(
        tuple(range(4)),
        tuple(names),
        poses,
        (cam,) * 4,
        CameraSource.REFINED,
        ((0.0,) * 4,) * 3 + (lens,),
        unconfirmed=(3,),
    )
    target = write_final_model(final, refine_dir, tmp_path)
    assert target == tmp_path / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(target))
    got, registered = cam_from_world_by_name(rec, names)
    assert registered.all()
    np.testing.assert_allclose(got, poses, atol=1e-9)
    assert rec.num_points3D() == 50  # the refinement's points, none for the added frame
    copy = pycolmap.Reconstruction(str(tmp_path / "colmap" / "sparse" / "0"))  # where nerfstudio's parser looks
    np.testing.assert_array_equal(cam_from_world_by_name(copy, names)[0], got)
    added = rec.cameras[rec.find_image_with_name(names[3]).camera_id]
    assert added.model.name == "OPENCV" and np.allclose(added.params, [300, 301, 160, 120, *lens])
    assert pycolmap.Reconstruction(str(refine_dir)).num_images() == 3  # a resumed run reads this back unchanged
    # Rewritten on every run: a second call gives the same model, not a duplicate frame.
    rec2 = pycolmap.Reconstruction(str(write_final_model(final, refine_dir, tmp_path)))
    assert rec2.num_images() == 4


def test_frames_the_evidence_left_out_are_not_in_sparse_0(tmp_path: Path):
    """A frame the refinement registered but the evidence contradicted (e.g. held by one planar pair) is
    not a final camera: sparse/0 lacks it, as transforms.json and the splat do; the refinement's own model
    keeps it (a resumed run reads that back)."""
    rng = np.random.default_rng(1)
    names = [f"frame_{i:03d}.png" for i in range(4)]
    poses = _poses(4, rng)
    cam = PinholeCamera(320, 240, 300.0, 301.0, 160.0, 120.0)
    refined = reconstruction_from_cameras(names, poses, [cam] * 4, rng.normal(size=(50, 3)))
    refine_dir = write_reconstruction(refined, tmp_path / "refine" / "model")
    kept = [0, 1, 3]
    final = FinalCameras(tuple(kept), tuple(names[k] for k in kept), poses[kept], (cam,) * 3, CameraSource.REFINED)
    rec = pycolmap.Reconstruction(str(write_final_model(final, refine_dir, tmp_path)))
    assert sorted(im.name for im in rec.images.values()) == [names[k] for k in kept]
    got, registered = cam_from_world_by_name(rec, [names[k] for k in kept])
    assert registered.all()
    np.testing.assert_allclose(got, poses[kept], atol=1e-9)
    assert pycolmap.Reconstruction(str(refine_dir)).num_images() == 4


def test_no_final_cameras_no_model(tmp_path: Path):
    (tmp_path / "colmap" / "sparse" / "0").mkdir(parents=True)  # left by an earlier run: no final cameras now
    assert write_final_model(None, None, tmp_path) is None
    assert not (tmp_path / "sparse").exists() and not (tmp_path / "colmap").exists()


def test_a_refinement_set_aside_keeps_the_models_cameras_without_the_frames_left_out(tmp_path: Path):
    """The refinement set aside as a whole (look-alike surfaces, a period off): the final cameras are the model's,
    but a frame the evidence then left out at the model's camera stays out (held-out street seed 269, frame 6 25 deg
    off, was contradicted and still exported)."""
    scene = make_scene(SceneOptions(num_frames=4, width=64, height=48, seed=2))
    truth, _ = simulate(scene, SimulationOptions(seed=2))
    prediction = prediction_from_truth(scene, truth, SimulationOptions(seed=2))
    ff = FeedForwardResult(prediction, np.zeros((0, 3)), np.zeros((0, 3)), tmp_path, ("CPUExecutionProvider",))
    per_image = [CameraEvidence(n, CameraStatus.UNCHECKED, "set aside") for n in scene.names]
    per_image[2] = CameraEvidence(scene.names[2], CameraStatus.PHOTO_MISFIT, "contradicted by the photos")
    evidence = EvidenceResult(GatesResult((), False), tuple(per_image), False, refinement_set_aside="a period off")
    final = select_final_cameras(
        tuple(scene.names), ff, Skipped("colmap", "off"), Skipped("refine", "set aside"), evidence
    )
    assert final.source is CameraSource.FEEDFORWARD and final.indices == (0, 1, 3)
    assert final.names == tuple(scene.names[k] for k in (0, 1, 3)) and final.unconfirmed == (0, 1, 2)
    np.testing.assert_array_equal(final.cam_from_world, prediction.cam_from_world[[0, 1, 3]])


def _seen_by_all(rec: pycolmap.Reconstruction, xyz: np.ndarray) -> None:
    """Give ``rec`` points that every image observes (a track through all of them)."""
    for image in rec.images.values():
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(np.array([10.0 + j, 20.0])) for j in range(len(xyz))])
    for j, point in enumerate(xyz):
        track = pycolmap.Track()
        for image_id in rec.images:
            track.add_element(image_id, j)
        rec.add_point3D(point, track)


def test_a_frame_kept_at_the_models_camera_is_written_there_without_points(tmp_path: Path):
    """A refined frame the evidence kept at the model's camera (``MODEL_FITS``: its matches moved it, the photos fit
    the model's camera better) is a final camera at the model's pose, not the refined one; ``sparse/0`` holds it
    there without observations (the points were triangulated with the pose set aside), and the other frames keep
    theirs."""
    rng = np.random.default_rng(4)
    names = tuple(f"frame_{i:03d}.png" for i in range(4))
    refined_poses = _poses(4, rng)
    model = refined_poses.copy()
    turn, _ = np.linalg.qr(np.eye(3) + 0.07 * rng.normal(size=(3, 3)))
    model[2, :, :3] = turn * np.sign(np.linalg.det(turn)) @ model[2, :, :3]
    cam = PinholeCamera(320, 240, 300.0, 301.0, 160.0, 120.0)
    rec = reconstruction_from_cameras(names, refined_poses, [cam] * 4)
    _seen_by_all(rec, rng.normal(size=(5, 3)))
    refine_dir = write_reconstruction(rec, tmp_path / "refine" / "model")
    refine = SimpleNamespace(
        cam_from_world=refined_poses, cameras=(cam,) * 4, distortion=None, registered=np.ones(4, bool)
    )
    per_image = [CameraEvidence(n, CameraStatus.REFINED, "refined") for n in names]
    per_image[2] = CameraEvidence(names[2], CameraStatus.MODEL_FITS, "the photos fit the model's camera")
    evidence = EvidenceResult(GatesResult((), False), tuple(per_image), False)
    final = _refined_final_cameras(names, Skipped("colmap", "off"), refine, evidence, model)
    assert final.indices == (0, 1, 2, 3) and final.unconfirmed == (2,)
    np.testing.assert_array_equal(final.cam_from_world[[0, 1, 3]], refined_poses[[0, 1, 3]])
    np.testing.assert_array_equal(final.cam_from_world[2], model[2])
    out = pycolmap.Reconstruction(str(write_final_model(final, refine_dir, tmp_path)))
    got, registered = cam_from_world_by_name(out, names)
    assert registered.all()
    np.testing.assert_allclose(got, final.cam_from_world, atol=1e-9)
    assert out.find_image_with_name(names[2]).num_points3D == 0
    assert [out.find_image_with_name(names[k]).num_points3D for k in (0, 1, 3)] == [5, 5, 5]
    assert out.num_points3D() == 5 and all(p.track.length() == 3 for p in out.points3D.values())
    assert pycolmap.Reconstruction(str(refine_dir)).find_image_with_name(names[2]).num_points3D == 5  # unchanged
