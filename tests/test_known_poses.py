"""Known poses in (``--poses``): the truth, in another similarity frame, given as a transforms.json.

They replace the model's (2.5 deg noisy) poses, moved into its frame; the refinement keeps the camera centres
near them; the report compares every estimate with them. The file formats are read alike.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from ffrecon.capture import CaptureOptions
from ffrecon.colmap_io import reconstruction_from_cameras, write_reconstruction
from ffrecon.errors import InputError
from ffrecon.formats.nerfstudio import write_transforms
from ffrecon.formats.poses import read_poses
from ffrecon.pipeline import RunOptions, run
from ffrecon.splat.stage import SplatOptions
from ffrecon.synthetic import load_scene

# The user's world: the truth rotated 30 deg about z, scaled 3x and moved.
_C, _S = np.cos(np.radians(30)), np.sin(np.radians(30))
USER_FROM_TRUTH = np.array([[_C, -_S, 0], [_S, _C, 0], [0, 0, 1.0]]), 3.0, np.array([1.0, -2.0, 0.5])


def _in_user_world(cam_from_world: np.ndarray) -> np.ndarray:
    """``cam_from_world`` poses of the truth's world expressed in the user's world."""
    rot, scale, shift = USER_FROM_TRUTH
    r = cam_from_world[:, :, :3] @ rot.T  # cam_from_user = cam_from_truth @ truth_from_user
    t = scale * cam_from_world[:, :, 3] - np.einsum("nij,j->ni", r, shift)
    return np.concatenate([r, t[:, :, None]], axis=2)


@pytest.mark.parametrize("prior", [False, True], ids=["fixed", "prior"])
def test_given_poses_replace_the_models_and_hold_the_refinement(demo12, tmp_path, prior):
    scene = load_scene(demo12.scene_dir)
    given = tmp_path / "transforms.json"
    poses = _in_user_world(scene.cam_from_world)
    write_transforms(given, [f"images/{n}" for n in scene.names], poses, [scene.camera] * len(scene.names))
    capture = CaptureOptions(poses=given, poses_prior=prior)
    options = RunOptions(capture=capture, splat=SplatOptions(enabled=False), ground_truth=demo12.scene_dir)
    result = run(demo12.images, tmp_path / "out", demo12.model, options)
    assert result.exit_code == 0
    model_vs_given = result.comparisons.by_label("feed-forward", "given poses").errors
    assert model_vs_given.median_rotation_deg > 1.0  # the model's own poses, as far off as it made them
    refined = result.comparisons.by_label("refined", "given poses").errors
    assert refined.median_rotation_deg < 0.1 and refined.auc[5] > 0.95
    truth = result.comparisons.by_label("refined", "ground truth").errors
    assert truth.median_rotation_deg < 0.1
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert "feedforward_vs_given_poses" in report["pose_errors"]
    if not prior:  # fixed: the refined cameras are the given ones (in the model's frame), to rounding
        assert result.refine.registered.all()
        np.testing.assert_allclose(
            result.refine.cam_from_world, result.feedforward.prediction.cam_from_world, atol=1e-6
        )
        assert np.nanmax(refined.per_image_rotation_deg) < 1e-4 and refined.ate_relative < 1e-6


def test_a_colmap_model_and_a_transforms_json_give_the_same_poses(demo12, tmp_path):
    scene = load_scene(demo12.scene_dir)
    rec = reconstruction_from_cameras(scene.names, scene.cam_from_world, [scene.camera] * len(scene.names))
    folder = write_reconstruction(rec, tmp_path / "model")
    json_path = write_transforms(tmp_path / "t.json", list(scene.names), scene.cam_from_world, [scene.camera] * 12)
    a, b = read_poses(folder), read_poses(json_path)
    for name, pose in zip(scene.names, scene.cam_from_world):
        np.testing.assert_allclose(a.get(name), pose, atol=1e-9)
        np.testing.assert_allclose(b.get(name), pose, atol=1e-9)


@pytest.mark.parametrize(
    ("content", "says"),
    [
        ('{"frames": [{"file_path": "a.png", "transform_matrix": [[1, 0, 0, 0]]}]}', "not finite 3x4"),
        ('{"frames": []}', "holds 0 poses"),
        ("not json", "cannot be read"),
    ],
)
def test_bad_pose_files_say_what_is_wrong(tmp_path, content, says):
    path = tmp_path / "transforms.json"
    path.write_text(content)
    with pytest.raises(InputError, match=says):
        read_poses(path)
    with pytest.raises(InputError, match="neither a COLMAP model"):
        read_poses(tmp_path / "missing")
