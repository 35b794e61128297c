"""A frame nothing checks is contradicted where the model's own depth, placed with its camera, disagrees with the
other frames' depth (issue 39; ``geometry.overlap.view_agreement``, ``sfm.verify.signs._depth_misfits``).

On the repeated-tile object of held-out seeds 235-247 a frame 25 deg off had no verified match (the matches guided
by its camera found none), no dense evidence and no photometric verdict, and was exported unchecked. These scenes
are objects orbited 30-60 deg a step, as the sweep's object family, with seeds the rule was not tuned on."""

from __future__ import annotations

import numpy as np

from ffrecon.geometry.overlap import view_agreement
from ffrecon.sfm.verify.signs import _depth_misfits, _depth_shares
from ffrecon.sfm.verify.verdicts import CameraEvidence, CameraStatus, EvidenceOptions
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene
from ffrecon.synthetic.layouts import Layout
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate


def _object(seed: int, bad: tuple[int, ...]):
    options = SceneOptions(
        num_frames=8,
        width=160,
        height=120,
        seed=seed,
        path=CameraPath.WIDE,
        layout=Layout.OBJECT,
        texture=Texture.REPEATED,
        step_deg=(30.0, 60.0),
        fov_x_deg=65.0,
    )
    scene = make_scene(options)
    sim = SimulationOptions(seed=seed, bad_frames=bad, bad_rotation_deg=25.0, depth_scale_error=0.06)
    truth, _ = simulate(scene, sim)
    return scene, prediction_from_truth(scene, truth, sim)


def _unchecked(names) -> tuple[CameraEvidence, ...]:
    why = "0 verified matches (< 50); kept out of the refinement; no other evidence: the model's camera is kept"
    return tuple(CameraEvidence(n, CameraStatus.UNCHECKED, why) for n in names)


def test_frames_25_deg_off_are_often_contradicted_by_the_models_depth_and_good_frames_never():
    """Eight new seeds (11-18), one frame 25 deg off in each, every frame unchecked: the rule leaves out the bad frame
    in 3 of them (its depth agrees with the others' on 0-31 % as often as the median frame's) and no good frame (the
    lowest of 56: 48 %). A turn about the axis toward the object moves its points along the surface, where the depth
    still agrees: those are the photometric check's and the matches' to find."""
    caught, good_out = [], []
    for seed in range(11, 19):
        bad = [2, 5, 6, 1][seed % 4]
        scene, prediction = _object(seed, (bad,))
        per_image = _unchecked(scene.names)
        judged = _depth_misfits(per_image, _depth_shares(per_image, prediction, 10.0), EvidenceOptions())
        out = [k for k, e in enumerate(judged) if not e.status.kept]
        caught += [seed] if bad in out else []
        good_out += [(seed, k) for k in out if k != bad]
        assert all(judged[k].status is CameraStatus.DEPTH_MISFIT for k in out)
    assert good_out == []
    assert len(caught) >= 3, caught


def test_view_agreement_measures_the_share_of_points_the_others_see_alike():
    scene, prediction = _object(14, (6,))
    agreement = view_agreement(prediction, range(8))
    assert ((agreement[:, 1] <= agreement[:, 0]) & (agreement[:, 1] >= 0)).all()
    share = agreement[:, 1] / agreement[:, 0]
    assert share[6] < 0.1 * np.median(share) and np.delete(share, 6).min() > 0.5 * np.median(share), share


def test_frames_with_evidence_for_their_camera_are_not_judged():
    """A frame whose verified pairs agree with its camera (its correction within the limit), or that the refinement
    holds, keeps its verdict whatever the depth says."""
    scene, prediction = _object(11, (2,))
    per_image = list(_unchecked(scene.names))
    per_image[2] = CameraEvidence(scene.names[2], CameraStatus.UNCHECKED, "2 verified pairs agree", 3.0)
    per_image[5] = CameraEvidence(scene.names[5], CameraStatus.REFINED, "bundle-adjusted", 1.0)
    per_image = tuple(per_image)
    judged = _depth_misfits(per_image, _depth_shares(per_image, prediction, 10.0), EvidenceOptions())
    assert judged[2] == per_image[2] and judged[5] == per_image[5]
