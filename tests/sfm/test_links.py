"""Frames held to the rest only by weak links, or by links the model contradicts (sfm/refine/links.py, issue 21).

The case is a held-out seed of the wide-baseline scene (8 views 30-60 deg apart, plain walls) that the
bad-frame sweep over seeds 1-12 found: seed 6 with frame 4 25 deg off ends, with the link check off, with a
frame called confirmed 4.0 deg from the truth (0.4 with it). The test runs the quick refinement with and
without the check, so it fails if the check stops mattering as well as if it stops working.

Seed 46 with no bad frame (found by the sweep over held-out seeds 25-48, ``--no-bad``) splits into groups
of 5 and 3 frames joined by weak links; it is why the main group needs 1.5 times the frames of any other,
not twice.

Two earlier cases (seed 2, and seed 4 with frame 7 off: 5.7 and 10.4 deg without the check) no longer need
it: their weak links came from pairs SIFT's verification had failed, whose dense correspondences never
reached the adjustment (sfm/refine/dense_db.py, ``add_matches``); with those in, no link there is weak.
"""

import dataclasses

import numpy as np
import pycolmap
import pytest

from ffrecon.colmap_io import cam_from_world_by_name
from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.geometry.rotations import axis_angle_to_matrix, matrix_to_quat_xyzw, rotation_angle_deg
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.refine.components import hold_apart, parts, place_parts
from ffrecon.sfm.refine.links import LinkOptions, LinkVerdict, judge_links
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions
from ffrecon.sfm.refine.run import run_refine
from ffrecon.sfm.verify.evidence import judge_final_cameras
from ffrecon.sfm.verify.verdicts import EvidenceOptions, FrameVerdict
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate


def _run(tmp_path, seed: int, bad: tuple[int, ...], links: LinkOptions, evidence: EvidenceOptions = EvidenceOptions()):
    scene = make_scene(
        SceneOptions(num_frames=8, width=320, height=240, path=CameraPath.WIDE, texture=Texture.PLAIN_WALLS, seed=seed)
    )
    images = write_scene(scene, tmp_path / "scene")
    sim = SimulationOptions(seed=seed, bad_frames=bad, bad_rotation_deg=25.0)
    truth, _ = simulate(scene, sim)
    pred = prediction_from_truth(scene, truth, sim)
    # Without the prediction moved by the photos' consensus (sfm/refine/prealign.py): with it, seed 6's dense
    # tracks no longer leave a weak link (every frame within 0.35 deg without the check), and the check is not tested
    quick = RefineOptions.quick()
    options = dataclasses.replace(quick, links=links, dense=dataclasses.replace(quick.dense, prealign=False))
    result = run_refine(RefineInputs(images), pred, options, tmp_path / f"refine_{links.enabled}")
    ev = judge_final_cameras(scene.names, pred.cam_from_world, result, None, GatesResult((), False), evidence)
    errors = aligned_rotation_errors_deg(result.cam_from_world[:, :, :3], scene.cam_from_world[:, :, :3])
    confirmed = [k for k, e in enumerate(ev.per_image) if e.verdict is FrameVerdict.CONFIRMED]
    return result, errors, confirmed


@pytest.mark.parametrize(
    ("seed", "bad", "worst_without"),
    [
        (6, (4,), 3.0),
        # No frame off. Frames 0, 6 and 7 joined to 1-5 by 16 and 28 points only, a third of them 18-245 px
        # from the truth: the hinge 8.5 deg wrong, every frame 3-5.5 deg off, called confirmed. The groups
        # are 5 and 3 frames: taken out only since the main group needs 1.5 times the others (was 2).
        (46, (), 5.0),
    ],
)
def test_no_frame_beyond_a_weak_or_contradicted_link_is_called_confirmed(tmp_path, seed, bad, worst_without):
    """Without the check a frame called confirmed is over ``worst_without`` deg off; with it no confirmed
    frame is over 1 deg and the median of the other frames is within 0.5 deg (the model's: 2.5)."""
    # without the check, and without the rotation spread's rule (sfm/refine/rigidity.py), which since session 48
    # also keeps these frames from being called confirmed: here the links check alone is tested
    loose_ok = EvidenceOptions(max_rotation_spread_deg=1e9)
    _, errors_off, confirmed_off = _run(tmp_path, seed, bad, LinkOptions(enabled=False), loose_ok)
    assert errors_off[confirmed_off].max() > worst_without
    _, errors, confirmed = _run(tmp_path, seed, bad, LinkOptions())
    assert confirmed and errors[confirmed].max() < 1.0, errors
    kept = [k for k in range(8) if k not in bad]
    assert np.median(errors[kept]) < 0.5, errors


def _two_groups_and_a_hinge(turn_deg: float, hinge_every: int = 8):
    """Pycolmap's synthetic model of 6 frames: points seen by frames 1-3 or 4-6 only, and a hinge of points seen
    by frames 3 and 4 only (every ``hinge_every``-th point: 50 of 400 at 8); frames 4-6 (and their points) then
    turned ``turn_deg`` as a whole, as a wrong hinge link leaves them. The model's cameras are the synthetic ones."""
    rec = pycolmap.synthesize_dataset(
        pycolmap.SyntheticDatasetOptions(num_rigs=1, num_frames_per_rig=6, num_points3D=400)
    )
    ids = sorted(rec.reg_image_ids())
    first, second = ids[:3], ids[3:]
    for n, point_id in enumerate(list(rec.point3D_ids())):
        keep = {ids[2], ids[3]} if n % hinge_every == 0 else set(first if n % 2 else second)
        elements = [(e.image_id, e.point2D_idx) for e in rec.point3D(point_id).track.elements]
        for image_id, point2D_idx in elements:
            if image_id not in keep:
                rec.delete_observation(image_id, point2D_idx)
    names = [rec.image(i).name for i in ids]
    model, _ = cam_from_world_by_name(rec, names)
    turn = axis_angle_to_matrix(np.radians(turn_deg) * np.array([0.0, 1.0, 0.0]))
    for image_id in second:  # cam_from_world R -> R turn^T: the frames turned about the world origin
        frame = rec.frame(rec.image(image_id).frame_id)
        old = frame.rig_from_world.matrix()
        rotation = old[:, :3] @ turn.T
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(matrix_to_quat_xyzw(rotation)), old[:, 3])
    return rec, names, model, first, second


def test_groups_joined_only_by_a_link_the_model_contradicts_are_placed_each_by_the_model():
    """Room seed 216 (photos, plain walls): frames 1-3 and 4-7 joined by one 30-point link 11 deg wrong, no group
    the largest by far; frames 4-7 ended 4.7-5 deg off, called confirmed (median 4.97, the model's 2.67). Held
    apart and each placed by the model: median 2.03."""
    rec, names, model, first, second = _two_groups_and_a_hinge(12.0)
    verdict = judge_links(rec, names, model)
    assert verdict.detached == ()
    assert verdict.split == (tuple(names[:3]), tuple(names[3:]))
    assert judge_links(rec, names, model, LinkOptions(split_groups=False)) == LinkVerdict()
    assert parts(rec) == [first + second]  # the hinge holds them together

    hinge = hold_apart(rec, verdict.split)
    place_parts(rec, names, model)

    assert hinge >= 40 and parts(rec) == [first, second]
    placed, _ = cam_from_world_by_name(rec, names)
    assert max(rotation_angle_deg(a[:, :3] @ b[:, :3].T) for a, b in zip(placed, model)) < 1e-3


def test_a_link_the_model_agrees_with_keeps_the_groups_together():
    rec, names, model, _, _ = _two_groups_and_a_hinge(2.0)  # under LinkOptions.min_disagreement_deg
    assert judge_links(rec, names, model) == LinkVerdict()


def test_a_link_the_model_trusts_depends_on_the_models_own_errors():
    """Room seed 223 (photos, plain walls): the link 4-5 (135 points) was 6 deg off the truth and 9.1 deg from
    the model's relative rotation, under the 10-deg limit; the other links disagreed 1.3-4.5 deg (median 3.0).
    Frames 5-7 ended 3.7-4.2 deg off, called confirmed. The limit is now 2.5 times the links' median
    disagreement (7.5 there), at least 3 deg: a 5-deg hinge is not trusted against an exact model, and is
    against one whose own relative errors are as large."""
    pycolmap.set_random_seed(0)  # the synthetic dataset, so that the model's errors below disagree as stated
    rec, names, model, _, _ = _two_groups_and_a_hinge(5.0, hinge_every=4)  # a hinge of 100 points
    assert judge_links(rec, names, model).split == (tuple(names[:3]), tuple(names[3:]))
    assert judge_links(rec, names, model, LinkOptions(min_disagreement_deg=10.0)) == LinkVerdict()  # as before
    # the six links within the groups disagree 3.2-5.0 deg (median 4.3): the limit is 10 deg, the hinge's 7.3 trusted
    assert judge_links(rec, names, _noisy(model)) == LinkVerdict()


def _noisy(model: np.ndarray) -> np.ndarray:
    """The model's cameras, each turned 2.5 deg about a random axis (a stand-in model's own errors)."""
    rng = np.random.default_rng(0)
    noisy = model.copy()
    for k in range(len(noisy)):
        axis = rng.normal(size=3)
        noisy[k, :, :3] = axis_angle_to_matrix(np.radians(2.5) * axis / np.linalg.norm(axis)) @ model[k, :, :3]
    return noisy


def test_a_weak_link_that_alone_joins_two_groups_must_agree_as_a_typical_link_does():
    """Held-out object seed 384 (scale errors): frames 0 and 5 joined the other six by one link of 34 points, 7.1
    deg from the model's relative rotation where the links' median was 4.1, under the 2.5-times limit; the pair
    ended 7.5 deg turned against the rest, both called confirmed 5.7 and 5.8 deg off. The same hinge as above, 7.3
    deg from a model whose links disagree by 4.3 at the median: trusted when 100 points hold it (the test above),
    not when 50 do (fewer than twice ``min_shared_points``)."""
    pycolmap.set_random_seed(0)
    weak, names, model, _, _ = _two_groups_and_a_hinge(5.0, hinge_every=8)
    assert judge_links(weak, names, _noisy(model)).split == (tuple(names[:3]), tuple(names[3:]))
    assert judge_links(weak, names, _noisy(model), LinkOptions(strong_bridge_ratio=0)) == LinkVerdict()  # as before
