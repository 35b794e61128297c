"""Verification gates: verdicts, causes named for bad captures, and the stop before expensive stages."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pycolmap
import pytest

from ffrecon.capture import CaptureOptions, run_capture
from ffrecon.capture.quality import assess_capture, measure_frame
from ffrecon.sfm.crosscheck.gate_types import FailureCause, GateOptions, GatesResult, GateStatus
from ffrecon.sfm.crosscheck.gates import evaluate_gates, run_gates, sparse_cloud_gate
from ffrecon.sfm.crosscheck.options import ColmapOptions
from ffrecon.sfm.crosscheck.registration import diagnose_registration
from ffrecon.sfm.crosscheck.run import run_colmap
from ffrecon.synthetic import SceneOptions, Texture, make_scene, write_scene


def test_good_capture_passes_every_gate(orbit24, colmap24):
    quality = assess_capture(orbit24.scene.names, [measure_frame(img) for img in orbit24.scene.images])
    assert quality.flags == ()  # the demo's scene: no capture flag either
    verdicts = evaluate_gates(colmap=colmap24[0], prediction=orbit24.prediction, quality=quality)
    assert [v.name for v in verdicts] == ["registration", "sparse_cloud", "depth_coverage"]
    assert all(v.status is GateStatus.PASS for v in verdicts), [v.reason for v in verdicts]
    assert verdicts[0].value == 1.0 and verdicts[0].threshold == 0.85
    assert not GatesResult(tuple(verdicts), forced=False).blocking
    assert verdicts[1].to_report()["status"] == "pass"


@pytest.mark.parametrize(
    ("scene_options", "cause", "word"),
    [
        (SceneOptions(num_frames=12, blur_sigma_px=3.0), FailureCause.BLUR, "blur"),
        (SceneOptions(num_frames=12, texture=Texture.TEXTURELESS), FailureCause.TEXTURE, "texture"),
    ],
    ids=["blurred", "textureless"],
)
def test_bad_capture_fails_registration_fast_and_names_the_cause(scene_options, cause, word, tmp_path):
    scene = make_scene(scene_options)
    image_dir = write_scene(scene, tmp_path / "scene")
    start = time.perf_counter()
    capture = run_capture(image_dir, CaptureOptions(), tmp_path / "out")
    assert set(capture.quality.flagged(cause.value)) == set(scene.names)  # flagged at capture already
    colmap = run_colmap(image_dir, scene.names, ColmapOptions(), tmp_path / "colmap", focal_prior_px=scene.camera.fx)
    gates = run_gates(colmap=colmap, prediction=None, quality=capture.quality)
    verdicts = gates.verdicts
    elapsed = time.perf_counter() - start
    registration = verdicts[0]
    assert registration.status is GateStatus.FAIL
    assert registration.causes[0] is cause
    assert word in registration.reason and word in registration.fix
    assert elapsed < 120  # "within minutes", measured on 2 shared cores: a few seconds
    assert gates.blocking and gates.failed == (registration,)
    assert not run_gates(colmap=colmap, prediction=None, quality=capture.quality, force=True).blocking


def test_diagnosis_uses_capture_flags_of_the_images_colmap_saw():
    scene = make_scene(SceneOptions(num_frames=6, width=160, height=120, textureless_frames=(0, 1)))
    quality = assess_capture(scene.names, [measure_frame(img) for img in scene.images])
    assert quality.flagged("texture") == list(scene.names[:2]) and not quality.flagged("blur")
    options = GateOptions()
    assert diagnose_registration(quality, scene.names, 1000, options) == (FailureCause.TEXTURE,)  # 2 of 6 >= 30%
    assert diagnose_registration(quality, scene.names[2:], 1000, options) == (FailureCause.OVERLAP,)
    assert diagnose_registration(None, scene.names, 1000, options) == (FailureCause.OVERLAP,)
    assert diagnose_registration(None, scene.names, 10, options) == (FailureCause.BLUR, FailureCause.TEXTURE)
    # Photos that look fine: the verified matches decide between overlap and parallax.
    fine = scene.names[2:]
    assert diagnose_registration(quality, fine, 1000, options, median_verified_matches=99) == (FailureCause.OVERLAP,)
    many = diagnose_registration(quality, fine, 1000, options, median_verified_matches=1528)
    assert many == (FailureCause.SMALL_PARALLAX,)  # a stereo pair's 1,528 matches: never "too little overlap"
    split = diagnose_registration(quality, fine, 1000, options, median_verified_matches=50, num_models=2)
    assert split == (FailureCause.DISCONNECTED,)

    # Two cameras: the left-out photos are the phone's, the registered ones the other camera's.
    groups = np.array([0, 0, 1, 1])
    mixed = diagnose_registration(
        quality, fine, 1000, options, camera_groups=groups, registered=np.array([False, False, True, True])
    )
    assert mixed == (FailureCause.MIXED_CAMERAS,)
    # ... but left-out photos spread over both cameras are not blamed on the mix.
    spread = diagnose_registration(
        quality, fine, 1000, options, camera_groups=groups, registered=np.array([False, True, False, True])
    )
    assert FailureCause.MIXED_CAMERAS not in spread


def _copy(rec: pycolmap.Reconstruction) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(rec)


def test_sparse_cloud_gate_catches_points_behind_cameras_and_explosions(colmap24):
    rec = colmap24[0].reconstruction
    assert sparse_cloud_gate(rec, GateOptions()).status is GateStatus.PASS
    # Mirror every point through its first camera: observations now see them from behind.
    behind = _copy(rec)
    for point_id in list(behind.point3D_ids())[::2]:
        point = behind.points3D[point_id]
        image = behind.image(point.track.elements[0].image_id)
        center = image.projection_center()
        point.xyz = 2 * center - point.xyz
    verdict = sparse_cloud_gate(behind, GateOptions())
    assert verdict.status is GateStatus.FAIL and "behind the camera" in verdict.reason
    # Throw 5% of the points a million units away.
    exploded = _copy(rec)
    for point_id in list(exploded.point3D_ids())[::20]:
        exploded.points3D[point_id].xyz = exploded.points3D[point_id].xyz * 1e6
    verdict = sparse_cloud_gate(exploded, GateOptions())
    assert verdict.status is GateStatus.FAIL and "explodes" in verdict.reason
    assert sparse_cloud_gate(None, GateOptions()).status is GateStatus.SKIPPED
    # A sound model with few points (two small photos): too thin to trust, not "wrong".
    thin = sparse_cloud_gate(rec, GateOptions(min_points=rec.num_points3D() + 1))
    assert thin.status is GateStatus.FAIL and "too thin" in thin.reason and "full resolution" in thin.fix
    assert "looks wrong" not in thin.reason and "moving objects" not in thin.fix


def test_depth_coverage_gate(orbit24):
    prediction = orbit24.prediction
    assert evaluate_gates(colmap=None, prediction=prediction)[2].status is GateStatus.PASS
    unsure = dataclasses.replace(
        prediction, depth_conf=tuple(np.where(c > 0, 1.0, 0.0).astype(np.float32) for c in prediction.depth_conf)
    )
    verdicts = evaluate_gates(colmap=None, prediction=unsure)
    assert verdicts[0].status is GateStatus.SKIPPED and verdicts[1].status is GateStatus.SKIPPED
    assert verdicts[2].status is GateStatus.FAIL and verdicts[2].value == 0.0
