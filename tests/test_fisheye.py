"""Fisheye photos: a synthetic capture through a 150 degree (diagonal) equidistant fisheye, given as COLMAP's
OPENCV_FISHEYE (``--intrinsics``), is undistorted at capture to pinhole frames of the same K and reconstructs
at COLMAP's accuracy."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ffrecon.capture import CaptureOptions
from ffrecon.capture.lens import undistort_lens
from ffrecon.pipeline import RunOptions, run
from ffrecon.splat.stage import SplatOptions
from ffrecon.synthetic import SceneOptions, make_scene, write_scene

FISHEYE = SceneOptions(num_frames=24, fisheye=True, fov_x_deg=120.0, seed=3)  # 320x240: 150 deg diagonally


def test_the_undistorted_fisheye_frame_is_the_pinhole_view(tmp_path):
    fisheye = make_scene(SceneOptions(num_frames=1, fisheye=True, fov_x_deg=120.0, seed=3))
    diagonal = 2 * np.degrees(np.hypot(160, 120) / fisheye.camera.fx)
    assert diagonal == pytest.approx(150.0, abs=1.0)
    same_k = 2 * np.degrees(np.arctan(160 / fisheye.camera.fx))  # the pinhole's field of view with that focal
    pinhole = make_scene(SceneOptions(num_frames=1, fov_x_deg=same_k, seed=3))
    path = tmp_path / "frame.png"
    cv2.imwrite(str(path), cv2.cvtColor(fisheye.images[0], cv2.COLOR_RGB2BGR))
    undistort_lens(path, fisheye.camera, ("fisheye", (0.0, 0.0, 0.0, 0.0)))
    undistorted = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB).astype(float)
    before = np.abs(fisheye.images[0].astype(float) - pinhole.images[0]).mean()
    after = np.abs(undistorted - pinhole.images[0]).mean()
    assert after < 4.0 < 30.0 < before  # only resampling is left (measured: 2.98 and 41.7 grey levels)


def test_a_fisheye_capture_reconstructs_at_colmaps_accuracy(tmp_path):
    scene = make_scene(FISHEYE)
    write_scene(scene, tmp_path / "scene")
    c = scene.camera
    cameras = tmp_path / "cameras.txt"
    cameras.write_text(f"1 OPENCV_FISHEYE {c.width} {c.height} {c.fx} {c.fy} {c.cx} {c.cy} 0 0 0 0\n")
    options = RunOptions(
        capture=CaptureOptions(intrinsics=cameras),
        splat=SplatOptions(enabled=False),
        ground_truth=tmp_path / "scene",
    )
    result = run(tmp_path / "scene" / "images", tmp_path / "out", None, options)
    assert result.exit_code == 0 and result.colmap.num_registered == 24
    errors = result.comparisons.by_label("COLMAP", "ground truth").errors
    assert errors.auc[5] >= 0.98 and errors.median_rotation_deg < 0.2
