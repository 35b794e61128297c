"""Look-alike surfaces on a scene family the refinement was not designed on (issue 39), and the photometric
check of frames no match checks.

The street of :mod:`ffrecon.synthetic.layouts` with one tile repeated on every surface, 8 views 30-50 deg
apart, a simulated model 2.5 deg / 3 % off per frame (seed 201, one of issue 39's held-out seeds). Its
verified pairs between the even and the odd frames mostly sit one period of the tile off, and agree with
each other: adjusted on them, one group of frames turned 16 deg against the other (median 8.5 deg from
the truth at 0.70 px) before :func:`ffrecon.sfm.refine.screen.drop_contradicting_pairs`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.geometry.rotations import axis_angle_to_matrix
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.refine.guided import MatchGuidance
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions
from ffrecon.sfm.refine.run import run_refine
from ffrecon.sfm.verify.evidence import judge_final_cameras
from ffrecon.sfm.verify.photometric import PhotometricOptions, photometric_check
from ffrecon.sfm.verify.unmatched import _photometric
from ffrecon.sfm.verify.verdicts import CameraEvidence, CameraStatus, FrameVerdict
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.layouts import Layout
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate

from .conftest import Capture

LUND = Path(__file__).resolve().parents[3] / "shared" / "data" / "lund"  # photos the textures are cut from


def _street(tmp_path_factory, texture: Texture, seed: int) -> Capture:
    options = SceneOptions(
        num_frames=8,
        width=320,
        height=240,
        seed=seed,
        path=CameraPath.WIDE,
        layout=Layout.STREET,
        texture=texture,
        step_deg=(30.0, 50.0),
        fov_x_deg=85.0,
        photo_dir=str(LUND) if texture is not Texture.REPEATED else "",
    )
    scene = make_scene(options)
    image_dir = write_scene(scene, tmp_path_factory.mktemp("street"))
    sim = SimulationOptions(seed=seed)
    truth, _ = simulate(scene, sim)
    return Capture(scene, image_dir, prediction_from_truth(scene, truth, sim))


@pytest.fixture(scope="module")
def street201(tmp_path_factory) -> Capture:
    return _street(tmp_path_factory, Texture.REPEATED, 201)


def _median_error(cam_from_world: np.ndarray, capture: Capture, registered: np.ndarray) -> float:
    truth = capture.scene.cam_from_world[registered, :, :3]
    return float(np.median(aligned_rotation_errors_deg(cam_from_world[registered, :, :3], truth)))


def test_pairs_a_period_off_are_dropped_and_the_refinement_beats_the_model(street201, tmp_path):
    capture = street201
    everyone = np.ones(len(capture.scene), bool)
    model = _median_error(capture.prediction.cam_from_world, capture, everyone)
    result = run_refine(RefineInputs(capture.image_dir), capture.prediction, RefineOptions(), tmp_path / "drop")
    assert result.guidance is not None and result.guidance.mode is MatchGuidance.GUIDED
    assert result.guidance.dropped_pairs >= 1
    assert result.registered.all()
    # issue 39's bar: at most half the model's error (measured 0.79 deg against 2.35 through the ONNX path)
    assert _median_error(result.cam_from_world, capture, result.registered) <= 0.5 * model

    # The same refinement keeping every verified pair ends worse than the model (measured 8.5 deg): the
    # test above fails without the rule.
    keep_all = RefineOptions(guidance=dataclasses.replace(RefineOptions().guidance, max_pair_gap_deg=180.0))
    kept = run_refine(RefineInputs(capture.image_dir), capture.prediction, keep_all, tmp_path / "keep")
    assert kept.guidance.dropped_pairs == 0
    assert _median_error(kept.cam_from_world, capture, kept.registered) > model


def _turned(cam_from_world: np.ndarray, frame: int, degrees: float) -> np.ndarray:
    """The cameras with ``frame`` turned by ``degrees`` about its own vertical axis (its centre kept)."""
    out = cam_from_world.copy()
    turn = axis_angle_to_matrix(np.radians(degrees) * np.array([0.0, 1.0, 0.0]))
    rotation, centre = out[frame, :, :3], -out[frame, :, :3].T @ out[frame, :, 3]
    out[frame, :, :3] = turn @ rotation
    out[frame, :, 3] = -(turn @ rotation) @ centre
    return out


@pytest.mark.parametrize("texture", [Texture.PHOTOS, Texture.REPEATED])
def test_the_photometric_check_tells_a_25_deg_camera_from_a_few_degrees(tmp_path_factory, texture):
    if texture is Texture.PHOTOS and not LUND.is_dir():
        pytest.skip(f"{LUND} (../shared/data/lund) is not there")
    """Truth cameras for the confirmed frames, the model's depth (3 % off): frame 3 turned 2.5 deg is not
    contradicted, turned 25 deg it is, on photo and repeated-tile textures alike."""
    capture = _street(tmp_path_factory, texture, 202)
    photos = [np.asarray(im) for im in capture.scene.images]
    confirmed = [0, 1, 2, 4, 5, 6, 7]
    options = PhotometricOptions()
    scores = {}
    for degrees in (0.0, 2.5, 25.0):
        poses = _turned(capture.scene.cam_from_world, 3, degrees)
        check = photometric_check(photos.__getitem__, capture.prediction, poses, confirmed, [3], options)
        assert check is not None
        scores[degrees] = check.scores["frame_003.png"].score
        assert check.contradicts("frame_003.png") is (degrees > 10), (degrees, scores, check.reference)
    assert scores[0.0] > scores[25.0]


def test_two_view_tracks_hold_frames_a_pair_a_period_off_would_turn(tmp_path_factory, tmp_path):
    """The repeated-tile room of seed 204 (``tools/sweep_families.py``: 30-50 deg turns, 85 deg field of view),
    quick mode. Two of its guided pairs hold matches a period off (one all, one two thirds of them) within the
    8 deg rule. Adjusted on tracks over three frames only (COLMAP's default), 459 points were left and frames 0
    and 1 ended 4-5 deg off (median 1.8, the model's 2.1) although all their own matches were right; with the
    two-view tracks and a robust fine pass, every frame within 0.3 deg (measured)."""
    options = SceneOptions(
        num_frames=8,
        width=320,
        height=240,
        seed=204,
        path=CameraPath.WIDE,
        layout=Layout.ROOM,
        texture=Texture.REPEATED,
        step_deg=(30.0, 50.0),
        fov_x_deg=85.0,
    )
    scene = make_scene(options)
    image_dir = write_scene(scene, tmp_path_factory.mktemp("room"))
    sim = SimulationOptions(seed=204)
    truth, _ = simulate(scene, sim)
    capture = Capture(scene, image_dir, prediction_from_truth(scene, truth, sim))
    model = aligned_rotation_errors_deg(capture.prediction.cam_from_world[:, :, :3], scene.cam_from_world[:, :, :3])

    def errors(two_view: bool, folder: str) -> np.ndarray:
        guidance = dataclasses.replace(RefineOptions().guidance, two_view_tracks=two_view)
        result = run_refine(
            RefineInputs(capture.image_dir),
            capture.prediction,
            RefineOptions.quick(guidance=guidance),
            tmp_path / folder,
        )
        assert result.guidance is not None and result.guidance.mode is MatchGuidance.GUIDED and result.registered.all()
        return aligned_rotation_errors_deg(result.cam_from_world[:, :, :3], scene.cam_from_world[:, :, :3])

    refined = errors(True, "two_view")
    assert np.median(refined) <= 0.5 * np.median(model) and refined.max() < 1.0
    assert errors(False, "three_view").max() > 2.0  # the same without them: frames degrees off


def test_a_frame_dense_tracks_move_far_on_lookalikes_is_left_out(street201, tmp_path):
    """The repeated-tile street with frame 6 25 deg off, quick mode. SIFT leaves frame 6 short; dense
    correspondences tracked from the model's prediction lock onto the pattern's nearest period, some 8 deg from
    the model's rotation, and verify: such a pair is not written on look-alike surfaces (as a guided pair that far
    is dropped: held-out room 351, where one left out a frame the model had within 2.7 deg), so the refinement
    leaves frame 6 out and the photos judge it: left out, not kept. The other seven are refined within 2 deg, on
    matches the model chose (kept, not called confirmed: look-alike surfaces), and the refinement is kept (one
    point ending a round at 1e154 px once had the whole model thrown away as diverged)."""
    scene = street201.scene
    sim = SimulationOptions(seed=201, bad_frames=(6,), bad_rotation_deg=25.0)
    truth, _ = simulate(scene, sim)
    prediction = prediction_from_truth(scene, truth, sim)
    result = run_refine(RefineInputs(street201.image_dir), prediction, RefineOptions.quick(), tmp_path)
    assert result.dense is not None and result.dense.per_frame["frame_006.png"] == 0
    assert result.registered.sum() == 7 and not result.registered[6]
    photos = [np.asarray(im) for im in scene.images]
    evidence = judge_final_cameras(
        scene.names,
        prediction.cam_from_world,
        result,
        None,
        GatesResult((), False),
        photos=photos.__getitem__,
        depth=prediction,
    )
    assert evidence.per_image[6].verdict is FrameVerdict.CONTRADICTED and not evidence.per_image[6].status.kept
    errors = aligned_rotation_errors_deg(result.cam_from_world[:, :, :3], scene.cam_from_world[:, :, :3])
    guided = [k for k, e in enumerate(evidence.per_image) if e.status is CameraStatus.GUIDED]
    assert guided == [0, 1, 2, 3, 4, 5, 7] and errors[guided].max() < 2.0
    assert evidence.count(FrameVerdict.CONFIRMED) == 0  # nothing independent of the model checked them


@pytest.mark.parametrize("degrees", [2.5, 25.0])
def test_a_frame_held_by_one_planar_pair_is_checked_against_the_photos(tmp_path_factory, degrees):
    """Held-out room seed 214, frame 6 25 deg off: one planar pair moved it 5 deg, and it was exported 30.8 deg off,
    unchecked. Frames refined on one planar pair are judged by the photos too, and judge others: here the other
    frames are all held by one planar pair or by guided matches, none confirmed."""
    capture = _street(tmp_path_factory, Texture.REPEATED, 202)
    photos = [np.asarray(im) for im in capture.scene.images]
    poses = _turned(capture.scene.cam_from_world, 3, degrees)
    statuses = [CameraStatus.PLANAR_PAIR if k % 2 else CameraStatus.GUIDED for k in range(8)]
    per_image = tuple(
        CameraEvidence(n, s, "its refined pose is kept, unconfirmed", 1.0)
        for n, s in zip(capture.scene.names, statuses)
    )
    guided = SimpleNamespace(lookalike=True)
    refine = SimpleNamespace(registered=np.ones(8, bool), cam_from_world=poses, guidance=guided)
    judged = _photometric(per_image, poses, refine, photos.__getitem__, capture.prediction, PhotometricOptions(), 10.0)
    expected = CameraStatus.PHOTO_MISFIT if degrees > 10 else CameraStatus.PLANAR_PAIR
    assert judged[3].status is expected, judged[3].why
    assert all(e.status is s for k, (e, s) in enumerate(zip(judged, statuses)) if k != 3)


@pytest.mark.parametrize("degrees", [1.5, 15.0])
def test_a_frame_dense_tracks_moved_a_few_degrees_is_kept_only_where_the_photos_fit_it(tmp_path_factory, degrees):
    """On look-alike surfaces a frame SIFT left short that dense tracks moved 5-10 deg from the model was left out
    whatever its refined pose: on held-out street seed 249 (scale) frames 0 and 4, refined 2.7 and 1.5 deg from the
    truth (the model's 2.9 and 4.0), left `sparse/0` incomplete. Now the photos judge it at its refined pose: kept
    (refined on guided matches, not confirmed) where they fit it at least as well as the references fit at theirs;
    left out where they fit it worse (the street 201 frame 6 of the test above, moved 7.6 deg to 15.9 from the
    truth: 0.85 against 0.99)."""
    capture = _street(tmp_path_factory, Texture.REPEATED, 202)
    photos = [np.asarray(im) for im in capture.scene.images]
    poses = _turned(capture.scene.cam_from_world, 3, degrees)
    per_image = tuple(
        CameraEvidence(n, CameraStatus.DENSE_MOVED if k == 3 else CameraStatus.GUIDED, "left out", 7.0)
        for k, n in enumerate(capture.scene.names)
    )
    assert not per_image[3].status.kept  # without the photos (--no-photometric, no depth) it stays left out
    guided = SimpleNamespace(lookalike=True)
    refine = SimpleNamespace(registered=np.ones(8, bool), cam_from_world=poses, guidance=guided)
    judged = _photometric(per_image, poses, refine, photos.__getitem__, capture.prediction, PhotometricOptions(), 10.0)
    expected = CameraStatus.GUIDED if degrees < 5 else CameraStatus.DENSE_MOVED
    assert judged[3].status is expected, judged[3].why
    assert judged[3].status.kept == (degrees < 5)
    assert all(e.status is CameraStatus.GUIDED for k, e in enumerate(judged) if k != 3)


@pytest.mark.parametrize("degrees", [2.5, 25.0])
def test_a_frame_whose_dense_pair_turned_is_judged_by_its_fit_against_the_references(tmp_path_factory, degrees):
    """Held-out room 353 (repeated tile, frame 1 25 deg off, no verified match): its dense pair verified a period
    off, turned beyond what the model's error explains, and is not written (sfm/refine/dense.py); the frame was
    exported unchecked. Such a frame is left out where the photos fit it worse near its camera than the references
    fit theirs, and kept where they fit it as well: here frame 3, in a turned pair, at 2.5 and at 25 deg."""
    capture = _street(tmp_path_factory, Texture.REPEATED, 202)
    photos = [np.asarray(im) for im in capture.scene.images]
    poses = capture.prediction.cam_from_world.copy()  # the references as the model has them, 2.5 deg off
    poses[3] = _turned(capture.scene.cam_from_world, 3, degrees)[3]
    statuses = [CameraStatus.UNCHECKED if k == 3 else CameraStatus.GUIDED for k in range(8)]
    per_image = tuple(
        CameraEvidence(n, s, "no other evidence: the model's camera is kept")
        for n, s in zip(capture.scene.names, statuses)
    )
    refine = SimpleNamespace(
        registered=np.arange(8) != 3, cam_from_world=poses, guidance=SimpleNamespace(lookalike=True)
    )
    names = capture.scene.names
    judged = [
        _photometric(per_image, poses, refine, photos.__getitem__, capture.prediction, PhotometricOptions(), 10.0, **k)
        for k in ({}, {"turned": frozenset({names[3]})})
    ]
    assert judged[0][3].status is CameraStatus.UNCHECKED, judged[0][3].why  # the turned pair alone decides
    expected = CameraStatus.PHOTO_MISFIT if degrees > 10 else CameraStatus.UNCHECKED
    assert judged[1][3].status is expected, judged[1][3].why
