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
reached the adjustment (sfm/refine/dense.py, ``_add_matches``); with those in, no link there is weak.
"""

import dataclasses

import numpy as np
import pytest

from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.refine.links import LinkOptions
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions
from ffrecon.sfm.refine.run import run_refine
from ffrecon.sfm.verify.evidence import judge_final_cameras
from ffrecon.sfm.verify.verdicts import FrameVerdict
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate


def _run(tmp_path, seed: int, bad: tuple[int, ...], links: LinkOptions):
    scene = make_scene(
        SceneOptions(num_frames=8, width=320, height=240, path=CameraPath.WIDE, texture=Texture.PLAIN_WALLS, seed=seed)
    )
    images = write_scene(scene, tmp_path / "scene")
    sim = SimulationOptions(seed=seed, bad_frames=bad, bad_rotation_deg=25.0)
    truth, _ = simulate(scene, sim)
    pred = prediction_from_truth(scene, truth, sim)
    options = dataclasses.replace(RefineOptions.quick(), links=links)
    result = run_refine(RefineInputs(images), pred, options, tmp_path / f"refine_{links.enabled}")
    ev = judge_final_cameras(scene.names, pred.cam_from_world, result, None, GatesResult((), False))
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
    _, errors_off, confirmed_off = _run(tmp_path, seed, bad, LinkOptions(enabled=False))
    assert errors_off[confirmed_off].max() > worst_without
    _, errors, confirmed = _run(tmp_path, seed, bad, LinkOptions())
    assert confirmed and errors[confirmed].max() < 1.0, errors
    kept = [k for k in range(8) if k not in bad]
    assert np.median(errors[kept]) < 0.5, errors
