"""Pose comparison on exact inputs: invariance to Sim(3), disagreeing and missing images."""

from __future__ import annotations

import numpy as np
import pytest

from ffrecon.geometry.alignment import Sim3
from ffrecon.geometry.poses import look_at_cam_from_world
from ffrecon.geometry.rotations import axis_angle_to_matrix
from ffrecon.sfm.compare.poses import DisagreementOptions, compare_poses


@pytest.fixture()
def ring():
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    centers = np.stack([2 * np.cos(angles), 2 * np.sin(angles), np.full(12, 1.0)], 1)
    poses = np.stack([look_at_cam_from_world(c, np.zeros(3)) for c in centers])
    return poses, [f"im{i:02d}.png" for i in range(12)]


def _similar(poses: np.ndarray) -> np.ndarray:
    sim = Sim3(0.37, axis_angle_to_matrix(np.array([0.2, -0.5, 0.9])), np.array([3.0, -1.0, 0.5]))
    return sim.transform_cam_from_world(poses)


def test_identical_up_to_similarity_gives_zero_error(ring):
    ref, names = ring
    result = compare_poses(_similar(ref), ref, names, None, estimate="ff", reference="gt")
    assert result.errors.auc[5] == 1.0 and result.errors.rra[5] == 1.0 and result.errors.rta[5] == 1.0
    assert result.errors.ate < 1e-9
    np.testing.assert_allclose(result.per_image_rotation_deg, 0, atol=1e-6)
    np.testing.assert_allclose(result.aligned_centers, result.reference_centers, atol=1e-9)
    assert result.disagreeing == ()
    report = result.to_report()
    assert report["estimate"] == "ff" and report["metrics"]["AUC@30"] == 1.0
    assert set(report["per_image"]) == set(names)


def test_a_rotated_frame_and_an_unregistered_frame_disagree(ring):
    ref, names = ring
    est = _similar(ref)
    center = -est[3, :, :3].T @ est[3, :, 3]
    est[3, :, :3] = axis_angle_to_matrix(np.array([0.0, np.radians(12.0), 0.0])) @ est[3, :, :3]  # turn in place
    est[3, :, 3] = -est[3, :, :3] @ center
    registered = np.ones(12, bool)
    registered[7] = False
    result = compare_poses(est, ref, names, registered, options=DisagreementOptions(max_rotation_deg=5.0))
    assert result.disagreeing == ("im03.png", "im07.png")
    assert result.per_image_rotation_deg[3] == pytest.approx(12.0, abs=1e-6)
    assert "rotation" in result.disagreements[0].reason and "not registered" in result.disagreements[1].reason
    assert np.isnan(result.per_image_rotation_deg[7])
    # Frame 7 fails its 11 pairs, frame 3 its 11 rotations: 66 pairs, 45 clean.
    assert result.errors.rra[5] == pytest.approx(45 / 66)


def test_images_missing_from_the_reference_are_left_out(ring):
    ref, names = ring
    in_ref = np.ones(12, bool)
    in_ref[[0, 5]] = False
    result = compare_poses(_similar(ref), ref, names, None, ref_registered=in_ref)
    assert result.errors.num_images == 10 and result.errors.auc[5] == 1.0
    assert result.to_report()["not_in_reference"] == ["im00.png", "im05.png"]
    assert np.isnan(result.per_image_rotation_deg[0]) and np.isnan(result.reference_centers[5]).all()
    assert np.isfinite(result.aligned_centers[0]).all()  # the estimate still has it, aligned


def test_centre_error_threshold_is_relative_to_the_reference_extent(ring):
    ref, names = ring
    est = ref.copy()
    # Move camera 4 by 10% of the extent (about 4 units across) without turning it.
    shift = np.array([0.4, 0.0, 0.0])
    est[4, :, 3] -= est[4, :, :3] @ shift
    result = compare_poses(
        est, ref, names, None, options=DisagreementOptions(max_rotation_deg=90, max_center_error=0.05)
    )
    assert result.disagreeing == ("im04.png",)
    assert "centre" in result.disagreements[0].reason
