"""Screening of the model's rotations against the verified pairs' own (sfm/refine/screen.py, issue 21): a frame
the model turned far off is found before the adjustment and starts it from its pairs' rotation."""

import dataclasses

import numpy as np
import pytest

from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import axis_angle_to_matrix, random_rotation, rotation_angle_deg
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions
from ffrecon.sfm.refine.run import run_refine
from ffrecon.sfm.refine.screen import PairGap, ScreenOptions, blame
from ffrecon.sfm.verify.evidence import judge_final_cameras
from ffrecon.sfm.verify.verdicts import CameraStatus, FrameVerdict
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate

TURN = axis_angle_to_matrix(np.array([0.0, np.radians(25.0), 0.0]))


def _poses(rotations: np.ndarray, centres: np.ndarray) -> np.ndarray:
    return np.concatenate([rotations, -np.einsum("nij,nj->ni", rotations, centres)[..., None]], axis=2)


def _gaps(true: np.ndarray, model: np.ndarray, pairs, wrong: dict | None = None) -> tuple[PairGap, ...]:
    """Pairs measured from the true ``[N, 3, 4]`` poses (``wrong`` replaces a pair's rotation), against the model."""
    out = []
    for i, j in pairs:
        measured = (wrong or {}).get((i, j), true[j, :, :3] @ true[i, :, :3].T)
        baseline = true[j, :, 3] - measured @ true[i, :, 3]  # camera i's centre in camera j
        gap = float(rotation_angle_deg(measured.T @ model[j, :, :3] @ model[i, :, :3].T))
        out.append(PairGap(i, j, 50, gap, measured, baseline / np.linalg.norm(baseline)))
    return tuple(out)


@pytest.fixture
def true():
    rng = np.random.default_rng(4)
    return _poses(random_rotation(rng, 6), rng.normal(size=(6, 3)))


def _off(true: np.ndarray, frame: int, move: float = 0.0) -> np.ndarray:
    """The true poses with ``frame`` turned 25 deg and its centre moved by ``move`` along x."""
    rotations, centres = true[:, :, :3].copy(), camera_centers(true)
    rotations[frame] = TURN @ rotations[frame]
    centres[frame, 0] += move
    return _poses(rotations, centres)


def test_the_frame_turned_off_is_blamed_and_its_pose_recovered(true):
    """A chain 0-1-...-5 plus 0-5; frame 2 turned 25 deg and moved: frame 2 alone is blamed, its rotation
    and its centre (where its two pairs' baselines meet) recovered."""
    model = _off(true, 2, move=0.4)
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 5)]
    found = blame(_gaps(true, model, pairs), model)
    assert [s.index for s in found] == [2] and found[0].num_agreeing == 2
    assert abs(found[0].gap_deg - 25.0) < 1e-6
    assert rotation_angle_deg(found[0].rotation @ true[2, :, :3].T) < 1e-6
    assert np.allclose(found[0].centre, camera_centers(true)[2])


def test_a_wrong_pair_measurement_blames_nobody(true):
    """One pair's own rotation wrong by 50 deg (flat walls, few inliers): the model is right, nobody is blamed,
    not the frame with that single pair, not its partner."""
    pairs = [(0, 1), (1, 2), (2, 3), (0, 3), (3, 4), (4, 5)]
    wrong = {(4, 5): axis_angle_to_matrix(np.array([np.radians(50.0), 0, 0])) @ true[5, :, :3] @ true[4, :, :3].T}
    assert blame(_gaps(true, true, pairs, wrong), true) == ()


def test_a_bad_frame_next_to_a_wrong_pair_is_still_the_one_blamed(true):
    """Seed 7's case: frame 1 turned 25 deg, its partner 0 also has a wrong pair with 5. Frame 0's implied
    rotations scatter (one from the bad frame, one from the wrong pair); frame 1's agree: frame 1 is blamed."""
    model = _off(true, 1)
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 5)]
    wrong = {(0, 5): axis_angle_to_matrix(np.array([0, 0, np.radians(50.0)])) @ true[5, :, :3] @ true[0, :, :3].T}
    assert [s.index for s in blame(_gaps(true, model, pairs, wrong), model)] == [1]


def test_two_frames_sharing_only_each_other_cannot_be_told_apart(true):
    model = _off(true[:2], 1)
    assert blame(_gaps(true[:2], model, [(0, 1)]), model) == ()
    assert blame(_gaps(true[:2], model, [(0, 1)]), model, ScreenOptions(min_agreeing=1)) == ()


def test_pairs_weigh_by_their_inliers(true):
    """Room seed 210 (repeated tile, frame 1 25 deg off): its two strongest pairs (73 and 126 inliers) agreed on a
    rotation within 4 deg of the truth, two weak ones (22 and 47) scattered. Counted one pair each, 2 of 4 is no
    majority and the frame was not blamed; weighed by inliers it is. The same pairs with the weights swapped blame
    nobody: two weak pairs do not outvote two strong ones."""
    model = _off(true, 1)
    pairs = [(0, 1), (1, 2), (1, 3), (1, 4), (2, 3), (3, 4), (4, 5), (0, 5)]
    scatter = {
        (1, 3): axis_angle_to_matrix(np.array([np.radians(40.0), 0, 0])) @ true[3, :, :3] @ true[1, :, :3].T,
        (1, 4): axis_angle_to_matrix(np.array([0, 0, np.radians(-60.0)])) @ true[4, :, :3] @ true[1, :, :3].T,
    }
    gaps = _gaps(true, model, pairs, scatter)
    inliers = {(0, 1): 73, (1, 2): 126, (1, 3): 22, (1, 4): 47}
    weighed = tuple(dataclasses.replace(g, num_inliers=inliers.get((g.index1, g.index2), 50)) for g in gaps)
    assert [s.index for s in blame(weighed, model)] == [1]
    swapped = {(0, 1): 22, (1, 2): 47, (1, 3): 73, (1, 4): 126}
    light = tuple(dataclasses.replace(g, num_inliers=swapped.get((g.index1, g.index2), 50)) for g in gaps)
    assert blame(light, model) == ()


# Seed 7 of the wide-baseline scene, frame 1 turned 25 deg: before the screen, the adjustment kept frame 1
# near its wrong pose and bent every other frame 5-11 deg (frame 1 confirmed at 10.6 deg, 7 others "corrected").
# Frame 7 used to hang on one pair whose matches lie on a wall and end 5.4 deg off, unchecked; since the
# dense correspondences of pairs SIFT could not verify reach the adjustment (sfm/refine/dense.py) it is held by
# several pairs and confirmed.
WIDE_7 = SceneOptions(num_frames=8, width=320, height=240, path=CameraPath.WIDE, texture=Texture.PLAIN_WALLS, seed=7)


def test_a_frame_25_deg_off_no_longer_bends_the_others(tmp_path):
    scene = make_scene(WIDE_7)
    sim = SimulationOptions(seed=7, bad_frames=(1,), bad_rotation_deg=25.0)
    truth, _ = simulate(scene, sim)
    pred = prediction_from_truth(scene, truth, sim)
    result = run_refine(RefineInputs(write_scene(scene, tmp_path / "s")), pred, RefineOptions.quick(), tmp_path / "r")
    ev = judge_final_cameras(scene.names, pred.cam_from_world, result, None, GatesResult((), False))
    assert [s.index for s in result.screened] == [1]
    assert ev.per_image[1].status is CameraStatus.CORRECTED
    errors = aligned_rotation_errors_deg(result.cam_from_world[:, :, :3], scene.cam_from_world[:, :, :3])
    confirmed = [k for k, e in enumerate(ev.per_image) if e.verdict is FrameVerdict.CONFIRMED]
    assert confirmed == [0, 2, 3, 4, 5, 6, 7] and errors[confirmed].max() < 1.0 and errors[1] < 1.0
    assert not ev.gates.blocking
