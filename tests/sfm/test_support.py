"""A frame hanging on one planar pair is unchecked, not confirmed (sfm/verify/support.py, issue 21). The opposite
case, two real photos of a motorcycle (not planar) on one pair, stays confirmed:
tests/sfm/test_stereo_motorcycle.py."""

import dataclasses

from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions
from ffrecon.sfm.refine.run import run_refine
from ffrecon.sfm.verify.evidence import judge_final_cameras
from ffrecon.sfm.verify.support import planar_single_pair
from ffrecon.sfm.verify.verdicts import CameraStatus, FrameVerdict
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate

# Seed 5 of the wide-baseline scene: frame 6 hangs on frame 3 by all but 25 of its 74 observations, which a
# homography explains (86 % at 1 px; the rule runs at 2). Seed 7's frame 7 was the case until the dense
# correspondences of pairs SIFT could not verify reached the adjustment: it is now held by several pairs.
WIDE_5 = SceneOptions(num_frames=8, width=320, height=240, path=CameraPath.WIDE, texture=Texture.PLAIN_WALLS, seed=5)


def test_a_frame_on_one_planar_pair_is_not_confirmed(tmp_path):
    """Frame 6 is unchecked with the reason (its pose kept), whatever its error (here under 1.5 deg): one
    planar pair cannot tell its pose from the homography's other solution. Every frame called confirmed is
    within 1 deg of the truth; a frame seen with two partners is not a single pair."""
    scene = make_scene(WIDE_5)
    sim = SimulationOptions(seed=5)
    truth, _ = simulate(scene, sim)
    pred = prediction_from_truth(scene, truth, sim)
    # Without the prediction moved by the photos' consensus (sfm/refine/prealign.py): with it, dense tracks hold frame
    # 6 by 269 observations over several pairs (every frame within 0.3 deg), and the planar rule is not tested
    quick = RefineOptions.quick()
    options = dataclasses.replace(quick, dense=dataclasses.replace(quick.dense, prealign=False))
    result = run_refine(RefineInputs(write_scene(scene, tmp_path / "s")), pred, options, tmp_path / "r")
    ev = judge_final_cameras(scene.names, pred.cam_from_world, result, None, GatesResult((), False))
    errors = aligned_rotation_errors_deg(result.cam_from_world[:, :, :3], scene.cam_from_world[:, :, :3])
    assert ev.per_image[6].status is CameraStatus.PLANAR_PAIR and ev.per_image[6].status.kept
    assert "frame_003.png" in ev.per_image[6].why
    confirmed = [k for k, e in enumerate(ev.per_image) if e.verdict is FrameVerdict.CONFIRMED]
    assert confirmed == [0, 1, 2, 3, 4, 5, 7] and errors[confirmed].max() < 1.0 and errors[6] < 1.5
    rec = result.reconstruction
    ids = {im.name: im.image_id for im in rec.images.values()}
    support = planar_single_pair(rec, ids["frame_006.png"], 40)
    assert support.partner == "frame_003.png" and support.num_elsewhere < 40 and support.planar_ratio > 0.8
    assert planar_single_pair(rec, ids["frame_003.png"], 40) is None  # seen with frames 2 and 4
    assert not ev.gates.blocking
