"""A frame hanging on one planar pair is unchecked, not confirmed (sfm/support.py, issue 21). The opposite
case, two real photos of a motorcycle (not planar) on one pair, stays confirmed:
tests/sfm/test_stereo_motorcycle.py."""

from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.sfm.evidence import CameraStatus, FrameVerdict, judge_final_cameras
from ffrecon.sfm.gates import GatesResult
from ffrecon.sfm.refine import RefineOptions, run_refine
from ffrecon.sfm.support import planar_single_pair
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate

# Seed 7 of the wide-baseline scene: frame 7 hangs on frame 0 by 43 of its 50 observations, on a wall.
WIDE_7 = SceneOptions(num_frames=8, width=320, height=240, path=CameraPath.WIDE, texture=Texture.PLAIN_WALLS, seed=7)


def test_a_frame_on_one_planar_pair_is_not_confirmed(tmp_path):
    """Frame 7 ends 5.4 deg from the truth with a tight fit; before this it was called confirmed. Now it is
    unchecked with the reason, and every frame still called confirmed is within 1 deg of the truth."""
    scene = make_scene(WIDE_7)
    sim = SimulationOptions(seed=7)
    truth, _ = simulate(scene, sim)
    pred = prediction_from_truth(scene, truth, sim)
    result = run_refine(write_scene(scene, tmp_path / "s"), pred, RefineOptions.quick(), tmp_path / "r")
    ev = judge_final_cameras(scene.names, pred.cam_from_world, result, None, GatesResult((), False))
    errors = aligned_rotation_errors_deg(result.cam_from_world[:, :, :3], scene.cam_from_world[:, :, :3])
    assert ev.per_image[7].status is CameraStatus.PLANAR_PAIR and ev.per_image[7].status.kept
    assert "frame_000.png" in ev.per_image[7].why
    confirmed = [k for k, e in enumerate(ev.per_image) if e.verdict is FrameVerdict.CONFIRMED]
    assert confirmed == list(range(7)) and errors[confirmed].max() < 1.0
    rec = result.reconstruction
    ids = {im.name: im.image_id for im in rec.images.values()}
    support = planar_single_pair(rec, ids["frame_007.png"], 40)
    assert support.partner == "frame_000.png" and support.num_elsewhere < 40 and support.planar_ratio > 0.8
    assert planar_single_pair(rec, ids["frame_003.png"], 40) is None  # seen with frames 2 and 4
    assert not ev.gates.blocking
