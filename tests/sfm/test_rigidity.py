"""How firmly the matches fix each refined frame's rotation (:mod:`ffrecon.sfm.refine.rigidity`, issue 39): on the
object family (seed 238, drift) all 8 frames were refined and called confirmed 1.5-3.2 deg off, because a weak
hinge let three of them turn at almost no cost. Such frames are now unchecked, not confirmed."""

import dataclasses

import numpy as np
import pycolmap

from ffrecon.final_cameras import require_checked
from ffrecon.geometry.rotations import axis_angle_to_matrix
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.refine.rigidity import rotation_spread_deg
from ffrecon.sfm.verify.evidence import judge_final_cameras
from ffrecon.sfm.verify.verdicts import CameraStatus, EvidenceOptions, FrameVerdict
from ffrecon.types import Skipped


def _model(width: int, focal: float) -> tuple[pycolmap.Reconstruction, list[str]]:
    """Pycolmap's synthetic model: 6 frames, 300 points each seen by all, a pinhole ``width`` x 3/4 wide."""
    options = pycolmap.SyntheticDatasetOptions(
        num_rigs=1,
        num_frames_per_rig=6,
        num_points3D=300,
        camera_width=width,
        camera_height=width * 3 // 4,
        camera_params=[focal, width / 2, width * 3 / 8, 0.0],
    )
    pycolmap.set_random_seed(0)  # the same scene every run
    rec = pycolmap.synthesize_dataset(options)
    return rec, [rec.image(i).name for i in sorted(rec.reg_image_ids())]


def _keep_only(rec: pycolmap.Reconstruction, name: str, count: int) -> None:
    """Leave frame ``name`` ``count`` of its observations; the others see every point still."""
    image_id = rec.find_image_with_name(name).image_id
    kept = 0
    for point_id in list(rec.point3D_ids()):
        elements = [(e.image_id, e.point2D_idx) for e in rec.point3D(point_id).track.elements]
        mine = [e for e in elements if e[0] == image_id]
        if not mine:
            continue
        if kept < count:
            kept += 1
        elif len(elements) <= 2:
            rec.delete_point3D(point_id)
        else:
            rec.delete_observation(*mine[0])


def test_a_frame_held_by_a_few_points_spreads_more_than_the_others():
    rec, names = _model(160, 200.0)
    whole = np.array(rotation_spread_deg(rec, names))
    assert whole.shape == (6,) and whole.max() < 1.2 * whole.min() and whole.max() < 0.2
    _keep_only(rec, names[-1], 6)
    spread = np.array(rotation_spread_deg(rec, names))
    assert spread[-1] > 0.5 and spread[-1] > 3 * np.median(spread[:-1])  # the options' limit is 0.6
    assert np.allclose(spread[:-1], whole[:-1], rtol=0.3)  # the others are held about as before


def test_the_spread_is_in_pixels_so_it_shrinks_with_the_image():
    """The same model seen by a camera with 6.4 times the pixels (focal length and every observation scaled):
    one pixel is 6.4 times less angle, so every frame spreads 6.4 times less."""
    rec, names = _model(160, 200.0)
    _keep_only(rec, names[-1], 6)
    small = np.array(rotation_spread_deg(rec, names))
    camera = rec.cameras[rec.image(sorted(rec.reg_image_ids())[0]).camera_id]
    camera.width, camera.height = camera.width * 64 // 10, camera.height * 64 // 10
    camera.params = camera.params * np.array([6.4, 6.4, 6.4, 1.0])
    for image in rec.images.values():
        for point in image.points2D:
            point.xy = point.xy * 6.4
    ratio = small / np.array(rotation_spread_deg(rec, names))
    assert np.allclose(ratio, 6.4, rtol=0.01), ratio


def test_too_few_frames_say_nothing():
    rec, names = _model(160, 200.0)
    for image_id in sorted(rec.reg_image_ids())[2:]:
        rec.deregister_frame(rec.image(image_id).frame_id)
    assert rotation_spread_deg(rec, names) == ()


def test_a_covariance_finite_for_no_pair_holds_every_frame_loosely(monkeypatch):
    """A nearly singular adjustment as a whole (held-out room seed 315: NaN for every pair) says the frames are
    loosely held, not nothing (they had been called confirmed 2.4-3.9 deg off)."""
    import ffrecon.sfm.refine.rigidity as rigidity

    rec, names = _model(160, 200.0)

    class Singular:
        def get_cam2_cov_from_cam1(self, *args):
            return np.full((6, 6), np.nan)

    monkeypatch.setattr(rigidity, "_covariance", lambda rec, ids: Singular())
    assert rotation_spread_deg(rec, names) == (np.inf,) * len(names)
    monkeypatch.setattr(rigidity, "_covariance", lambda rec, ids: None)  # pycolmap refused it: nothing is said
    assert rotation_spread_deg(rec, names) == ()


def test_a_loosely_held_frame_is_unchecked_not_confirmed(orbit24, refined24):
    """On the orbit the refinement holds every frame firmly (a real run, spreads well under the limit): all are
    confirmed. A frame whose spread is over the limit is unchecked, kept, and the run does not stop."""
    result, _ = refined24
    names = orbit24.scene.names
    ff = orbit24.prediction.cam_from_world
    spread = np.array(result.rotation_spread_deg)
    limit = EvidenceOptions().max_rotation_spread_deg
    assert spread.shape == (len(names),) and np.nanmax(spread) < limit / 2

    def judge(spread):
        loose = dataclasses.replace(result, rotation_spread_deg=tuple(spread))
        return judge_final_cameras(names, ff, loose, None, GatesResult((), False))

    assert all(e.verdict is FrameVerdict.CONFIRMED for e in judge(spread).per_image)
    wide = spread.copy()
    wide[5] = 2 * limit
    judged = judge(wide)
    assert [k for k, e in enumerate(judged.per_image) if e.verdict is not FrameVerdict.CONFIRMED] == [5]
    frame = judged.per_image[5]
    assert frame.status is CameraStatus.LOOSE and frame.status.kept and frame.verdict is FrameVerdict.UNCHECKED
    assert f"only to {2 * limit:.1f} deg" in frame.why
    everywhere = judge(np.full(len(names), 2 * limit))
    assert all(e.status is CameraStatus.LOOSE for e in everywhere.per_image)
    assert require_checked(everywhere, Skipped("colmap", "off"), result) is everywhere  # the run goes on
    wide[5] = np.inf  # a covariance that was not finite: not held at all
    assert judge(wide).per_image[5].status is CameraStatus.LOOSE


def test_a_correction_the_matches_hold_loosely_is_not_called_corrected(orbit24, refined24):
    """The model's camera of frame 5 turned 20 deg: the refinement moves it back, on many pairs, and it is
    corrected where its matches hold it firmly, refined and loosely held (kept, unchecked) where they do not (held-out
    room seed 274: a correction fixing the rotation only to about 1 deg ended 3.6 deg from the truth)."""
    result, _ = refined24
    names = orbit24.scene.names
    ff = orbit24.prediction.cam_from_world.copy()
    ff[5, :, :3] = axis_angle_to_matrix(np.radians([0.0, 20.0, 0.0])) @ ff[5, :, :3]
    spread = np.array(result.rotation_spread_deg)

    def judge(spread):
        loose = dataclasses.replace(result, rotation_spread_deg=tuple(spread))
        return judge_final_cameras(names, ff, loose, None, GatesResult((), False)).per_image[5]

    assert judge(spread).status is CameraStatus.CORRECTED
    wide = spread.copy()
    wide[5] = 2 * EvidenceOptions().max_rotation_spread_deg
    frame = judge(wide)
    assert frame.status is CameraStatus.LOOSE and frame.status.kept and frame.verdict is FrameVerdict.UNCHECKED
    assert frame.correction_deg > 10 and "refined on its matches" in frame.why


def test_a_model_that_dropped_a_frame_is_still_measured():
    """The refinement drops frames it cannot hold; pycolmap keeps them in memory as frames without a pose, and its
    covariance estimation failed on every such model (nothing said: held-out room seed 333, frames 4-6 deg off called
    confirmed). The spreads are those of the model without the frame, and the same as the model read back."""
    rec, names = _model(160, 200.0)
    dropped = rec.find_image_with_name(names[0])
    for point_id in list(rec.point3D_ids()):
        for e in list(rec.point3D(point_id).track.elements):
            if e.image_id == dropped.image_id:
                rec.delete_observation(e.image_id, e.point2D_idx)
    rec.deregister_frame(dropped.frame_id)
    spread = rotation_spread_deg(rec, names)
    assert len(spread) == 6 and np.isnan(spread[0]) and np.all(np.isfinite(spread[1:])), spread
    assert max(spread[1:]) < 0.2
