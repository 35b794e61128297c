"""A refined frame its matches alone left out keeps the model's camera where the photos choose it (issue 39;
``sfm.verify.unmatched._model_camera_kept``, ``CameraStatus.MODEL_FITS``).

On look-alike surfaces dense tracks lock onto the period of a pattern nearest the model's prediction and move good
frames 5-12 deg; such a frame was left out though the model had it within 3 deg. Here the other frames are refined
exactly (the truth) and the frame's refined pose is its true pose turned 8 deg (a period off); the model's camera is
the stand-in's (about 2.5 deg off, or 25 deg off for a bad frame, whose refined pose is the model's turned 8 deg).
Scenes are the sweep's families, on seeds the rule (``PhotometricOptions.model_far_gain``, the depth doubt) was not
set on (it was set on 21-40)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ffrecon.geometry.rotations import axis_angle_to_matrix
from ffrecon.sfm.verify.photometric import PhotometricOptions, PhotometricScore
from ffrecon.sfm.verify.signs import _depth_doubted, _depth_shares
from ffrecon.sfm.verify.unmatched import _chooses_model, _guided_misfits, _model_camera_kept
from ffrecon.sfm.verify.verdicts import CameraEvidence, CameraStatus, EvidenceOptions
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene
from ffrecon.synthetic.layouts import Layout
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate

LUND = Path(__file__).resolve().parents[3] / "shared" / "data" / "lund"
GUIDED = "bundle-adjusted on matches the model's cameras chose: its refined pose is kept, not confirmed"
MOVED = "refined 8.0 deg from the model on dense correspondences: neither pose can be trusted, left out"


def _turned(pose: np.ndarray, deg: float, rng) -> np.ndarray:
    axis = rng.normal(size=3)
    out = pose.copy()
    out[:, :3] = axis_angle_to_matrix(np.radians(deg) * axis / np.linalg.norm(axis)) @ pose[:, :3]
    return out


def _judge(layout: Layout, texture: Texture, seed: int, frame: int) -> tuple[CameraStatus, CameraStatus]:
    """The frame's status when the model has it about 2.5 deg off, and when 25 deg off."""
    scene = make_scene(_options(layout, texture, seed))
    return tuple(_status(scene, seed, frame, bad) for bad in (False, True))


def _options(layout: Layout, texture: Texture, seed: int) -> SceneOptions:
    return SceneOptions(
        num_frames=8,
        width=320,
        height=240,
        seed=seed,
        path=CameraPath.WIDE,
        layout=layout,
        texture=texture,
        step_deg=(30.0, 50.0),
        fov_x_deg=70.0 if layout is Layout.ROOM else 65.0,
        photo_dir=str(LUND),
    )


def _scenes():
    """``(layout, seed, frame, scene)``: seeds 41-43 of each family, the texture and the judged frame drawn by seed."""
    for layout in (Layout.STREET, Layout.OBJECT, Layout.ROOM):
        for seed in range(41, 44):
            texture = [Texture.REPEATED, Texture.PHOTOS, Texture.PHOTOS_PLAIN_WALLS][seed % 3]
            yield layout, seed, [1, 6][seed % 2], make_scene(_options(layout, texture, seed))


def _prediction(scene, seed: int, frame: int, bad: bool):
    """The stand-in's prediction of ``scene``: about 2.5 deg off, and ``frame`` 25 deg off when ``bad``."""
    sim = SimulationOptions(seed=seed, bad_frames=(frame,) if bad else (), bad_rotation_deg=25.0)
    return prediction_from_truth(scene, simulate(scene, sim)[0], sim)


def _status(scene, seed: int, frame: int, bad: bool, *, corrected: bool = False) -> CameraStatus:
    """The frame's status: moved 8 deg by its matches (from the truth; from the model's camera when ``bad``) and left
    out, or with ``corrected``, called corrected (to the truth when ``bad``; else the truth turned 20 deg)."""
    prediction = _prediction(scene, seed, frame, bad)
    rng = np.random.default_rng(seed)
    refined = np.array(scene.cam_from_world, np.float64)
    if corrected:
        refined[frame] = refined[frame] if bad else _turned(refined[frame], 20.0, rng)
    else:
        refined[frame] = _turned(prediction.cam_from_world[frame] if bad else refined[frame], 8.0, rng)
    refine = SimpleNamespace(registered=np.ones(8, bool), cam_from_world=refined, relocalized=())
    per_image = [CameraEvidence(n, CameraStatus.REFINED, "refined") for n in scene.names]
    per_image[frame] = (
        CameraEvidence(scene.names[frame], CameraStatus.CORRECTED, "refined far: the refined pose is used", 20.0)
        if corrected
        else CameraEvidence(scene.names[frame], CameraStatus.DENSE_MOVED, MOVED, 8.0, matches_only=True)
    )
    photos = [np.asarray(im) for im in scene.images]
    doubted = _depth_doubted(_depth_shares(tuple(per_image), prediction, 10.0), EvidenceOptions())
    read, options = photos.__getitem__, PhotometricOptions()
    out = _model_camera_kept(
        tuple(per_image), prediction.cam_from_world, refine, None, read, prediction, options, doubted
    )
    assert all(e.status is CameraStatus.REFINED for k, e in enumerate(out) if k != frame)
    return out[frame].status


def test_the_model_camera_is_kept_for_good_frames_and_never_for_a_frame_25_deg_off():
    """Three seeds per family (41-43), textures and the frame drawn by seed. Measured: the good frame kept at the
    model's camera in 8 of 9 scenes, the frame 25 deg off in none. On seeds 21-40 (two textures each, 120 scenes):
    108 of 120 good frames kept, no frame 25 deg off (two would have been without the depth doubt, both objects with
    photo textures)."""
    kept_good, kept_bad = [], []
    for layout in (Layout.STREET, Layout.OBJECT, Layout.ROOM):
        for seed in range(41, 44):
            frame = [1, 6][seed % 2]
            texture = [Texture.REPEATED, Texture.PHOTOS, Texture.PHOTOS_PLAIN_WALLS][seed % 3]
            good, bad = _judge(layout, texture, seed, frame)
            assert {good, bad} <= {CameraStatus.MODEL_FITS, CameraStatus.DENSE_MOVED}
            kept_good += [(layout.value, seed)] if good is CameraStatus.MODEL_FITS else []
            kept_bad += [(layout.value, seed)] if bad is CameraStatus.MODEL_FITS else []
    assert kept_bad == []
    assert len(kept_good) >= 7, kept_good


def test_a_correction_stands_where_the_photos_fit_it():
    """A frame called corrected keeps that pose only where the photos fit it better there than near the model's camera,
    and not poorly: a frame 25 deg off corrected to the truth stands; a good frame (the model 2.5 deg off) "corrected"
    20 deg away keeps the model's camera or is left out. Seeds 41-43 (held-out room seed 293 had two good frames
    corrected 90-96 deg off). Measured: 8 of 9 corrections to the truth stand (street 42, repeated tile: left out,
    its photo fitting 0.94 there against the references' 0.99), none of the 9 wrong ones. A frame 25 deg off never
    keeps the model's camera."""
    stands, wrong, at_model = [], [], []
    for layout, seed, frame, scene in _scenes():
        bad = _status(scene, seed, frame, True, corrected=True)
        stands += [(layout.value, seed)] if bad is CameraStatus.CORRECTED else []
        at_model += [(layout.value, seed)] if bad is CameraStatus.MODEL_FITS else []
        wrong += [seed] if _status(scene, seed, frame, False, corrected=True) is CameraStatus.CORRECTED else []
    assert at_model == [] and wrong == []
    assert len(stands) >= 7, stands


def test_a_frame_refined_on_guided_matches_far_off_is_left_out():
    """A frame refined on guided matches (look-alike surfaces: not confirmed, but kept) that the photos contradict twice
    (a far turn fits clearly better, and poorly where it is) is left out: a frame 25 deg off refined 5 deg toward the
    truth, as on held-out streets 292 and 301; good frames refined within 1 deg of the truth (its two neighbours, also
    refined on guided matches) stay. Seeds 41-43 (the rule was measured on runs of seeds 279-301). Measured: the frame
    25 deg off left out in 5 of 9 scenes; 1 good frame of 18 (room 42, repeated tile: frame 0, whose only neighbour
    covering enough of it is the bad frame, fits -0.05 at its pose and 0.93 turned 25 deg; a known weakness: a frame
    is compared with its best-covering neighbours, and there the one far off)."""
    left_bad, left_good = [], []
    for layout, seed, frame, scene in _scenes():
        prediction = _prediction(scene, seed, frame, True)
        rng = np.random.default_rng(seed)
        refined = np.array([_turned(p, 0.5, rng) for p in np.asarray(scene.cam_from_world, np.float64)])
        toward = prediction.cam_from_world[frame]
        refined[frame] = _turned(toward, 5.0, rng)
        refine = SimpleNamespace(registered=np.ones(8, bool), cam_from_world=refined, relocalized=())
        guided = (frame - 1, frame, frame + 1)  # the others are confirmed, the references
        per_image = tuple(
            CameraEvidence(n, CameraStatus.GUIDED if k in guided else CameraStatus.REFINED, GUIDED, 1.0)
            for k, n in enumerate(scene.names)
        )
        photos = [np.asarray(im) for im in scene.images]
        out = _guided_misfits(
            per_image, prediction.cam_from_world, refine, photos.__getitem__, prediction, PhotometricOptions()
        )
        left = [k for k, e in enumerate(out) if e.status is CameraStatus.PHOTO_MISFIT]
        left_bad += [(layout.value, seed)] if frame in left else []
        left_good += [(layout.value, seed, k) for k in left if k != frame]
    assert len(left_good) <= 1, left_good
    assert len(left_bad) >= 5, left_bad


def _relocated_status(scene, seed: int, frame: int, bad: bool) -> CameraStatus:
    """The frame's status when its neighbours' renderings placed it far from the model's camera and the adjustment
    did not keep it (left out on that alone): a good frame placed 11.7 deg from the truth (as held-out object 335's
    frame 1), a frame 25 deg off placed within 1 deg of the truth."""
    prediction = _prediction(scene, seed, frame, bad)
    rng = np.random.default_rng(seed)
    refined = np.array(scene.cam_from_world, np.float64)
    placed = _turned(refined[frame], 1.0 if bad else 11.7, rng)
    registered = np.ones(8, bool)
    registered[frame] = False
    relocalized = (SimpleNamespace(index=frame, cam_from_world=placed),)
    refine = SimpleNamespace(registered=registered, cam_from_world=refined, relocalized=relocalized)
    per_image = [CameraEvidence(n, CameraStatus.REFINED, "refined") for n in scene.names]
    why = "not refined; its neighbours' renderings placed it far, but the adjustment did not keep it there: left out"
    per_image[frame] = CameraEvidence(scene.names[frame], CameraStatus.CONTRADICTED, why, 12.0, matches_only=True)
    photos = [np.asarray(im) for im in scene.images]
    out = _model_camera_kept(
        tuple(per_image),
        prediction.cam_from_world,
        refine,
        None,
        photos.__getitem__,
        prediction,
        PhotometricOptions(),
        frozenset(),
    )
    return out[frame].status


def test_a_relocalisation_the_adjustment_did_not_keep_yields_to_the_model_camera_the_photos_fit():
    """Seeds 41-43 of each family. Measured: the good frame keeps the model's camera in 8 of 9 scenes; the frame 25 deg
    off, placed near the truth by the renderings, never does (it stays left out)."""
    kept_good, kept_bad = [], []
    for layout, seed, frame, scene in _scenes():
        for bad, kept in ((False, kept_good), (True, kept_bad)):
            status = _relocated_status(scene, seed, frame, bad)
            assert status in (CameraStatus.MODEL_FITS, CameraStatus.CONTRADICTED)
            kept += [(layout.value, seed)] if status is CameraStatus.MODEL_FITS else []
    assert kept_bad == []
    assert len(kept_good) >= 6, kept_good


def test_the_model_camera_fitting_as_well_as_the_references_is_chosen_whatever_fits_further():
    """Held-out street 338 (repeated tile), frame 5, 1.2 deg off in the model, moved 17.6 deg by guided matches: 0.06
    where the matches put it, 0.87 near the model's camera, 0.93 turned 24 deg (a period of the tile), the references
    0.82 at theirs. It was left out; the model's camera fits at least as well as the references fit theirs, so it is
    kept. Where this rule fired on the held-out sweeps of session 55: 3 good frames (1.2-3.3 deg off in the model)
    fitting 0.64-0.90 near the model's camera against references of 0.32-0.82, and room 353's frame 25 deg off, 0.95
    against 0.96 (with a margin of fit_factor it had been kept there)."""
    from ffrecon.sfm.verify.photometric import PhotometricOptions, PhotometricScore
    from ffrecon.sfm.verify.unmatched import _chooses_model

    options = PhotometricOptions()
    score = PhotometricScore(0.683, 0.866, 0.933, 24.0)
    assert not _chooses_model(score, 0.059, options)  # without the references: a far turn fits clearly better
    assert _chooses_model(score, 0.059, options, 0.821)
    assert not _chooses_model(score, 0.059, options, 0.95)  # references fitting far better than it: not chosen
    assert not _chooses_model(score, 0.9, options, 0.821)  # it fits better where the matches put it
    # held-out room 353 (repeated tile): a frame 25 deg off, moved 17.9 deg by dense tracks, 0.85 there, 0.95 near
    # the model's camera (a period of the tile), 0.99 turned 29 deg, the references 0.96: not chosen
    assert not _chooses_model(PhotometricScore(0.93, 0.95, 0.99, 29.0), 0.85, options, 0.96)


def _unseen_status(scene, seed: int, frame: int, bad: bool) -> tuple[CameraStatus, str]:
    """The frame's status when its matches moved it where no reference sees it (its centre 10,000 units below the
    scene, which every camera looks across), and left it out on that alone."""
    prediction = _prediction(scene, seed, frame, bad)
    refined = np.array(scene.cam_from_world, np.float64)
    refined[frame, :, 3] -= [0.0, 1e4, 0.0]  # its centre 1e4 along its own image-down axis (the cameras are upright)
    refine = SimpleNamespace(registered=np.ones(8, bool), cam_from_world=refined, relocalized=())
    per_image = [CameraEvidence(n, CameraStatus.REFINED, "refined") for n in scene.names]
    why = "refined on its matches far from the model, but on one planar pair: left out"
    per_image[frame] = CameraEvidence(scene.names[frame], CameraStatus.CONTRADICTED, why, 30.0, matches_only=True)
    photos = [np.asarray(im) for im in scene.images]
    out = _model_camera_kept(
        tuple(per_image), prediction.cam_from_world, refine, None, photos.__getitem__, prediction,
        PhotometricOptions(), frozenset(),
    )  # fmt: skip
    return out[frame].status, out[frame].why


def test_where_nothing_sees_the_pose_the_matches_gave_the_model_camera_must_fit_as_the_references_do():
    """Held-out room 397 (plain walls, session 58): frame 1, 24.4 deg off in the model, moved 23.6 deg by one planar
    pair to where no reference saw it, fitted 0.77 near the model's camera against the references' 0.91, and no
    camera turned further fitted 1.5 times better: the model's camera was kept and exported unchecked. Nothing
    compares the two poses there, so the model's camera must fit within ``unseen_margin`` (0.1) of the references.
    Seeds 41-43 of each family. Measured: the good frame keeps the model's camera in 8 of 9 scenes (object 42, 0.67
    against 0.87, is left out; with the fit the model's camera needs where the matched pose is seen, 3 of 9); the
    frame 25 deg off in none (the photos fit it better turned far in each)."""
    kept_good, kept_bad = [], []
    for layout, seed, frame, scene in _scenes():
        for bad, kept in ((False, kept_good), (True, kept_bad)):
            status, why = _unseen_status(scene, seed, frame, bad)
            assert status in (CameraStatus.MODEL_FITS, CameraStatus.CONTRADICTED)
            kept += [(layout.value, seed)] if status is CameraStatus.MODEL_FITS else []
    assert kept_bad == []
    assert len(kept_good) >= 7, kept_good
    # room 397's numbers: nothing seen there, 0.77 near the model's camera against the references' 0.91
    score = PhotometricScore(0.77, 0.77, 0.82, 31.0)  # as its log gave them, two decimals
    assert _chooses_model(score, float("nan"), PhotometricOptions(), 0.91)  # what kept it until session 58
    assert score.near < 0.91 - PhotometricOptions().unseen_margin  # what leaves it out now
