"""Given lenses (``--intrinsics`` with distortion) are undistorted at capture: each pixel of the pinhole frame
takes the photo's colour where the lens put that ray (OpenCV's projection, COLMAP's pixel-centre rule)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ffrecon.capture.lens import undistortion_maps
from ffrecon.formats.intrinsics import read_intrinsics
from ffrecon.types import PinholeCamera

CAMERA = PinholeCamera(320, 240, 250.0, 252.0, 161.0, 119.5)


@pytest.mark.parametrize(
    "lens", [("opencv", (-0.2, 0.05, 0.001, -0.002)), ("fisheye", (0.05, -0.01, 0.002, 0.0))], ids=lambda x: str(x)[:9]
)
def test_each_pinhole_pixel_reads_where_the_lens_projects_its_ray(lens):
    kind, coefficients = lens
    map_x, map_y = undistortion_maps(CAMERA, lens)
    v, u = np.mgrid[20:220:25, 20:300:25]
    pinhole = np.stack([u + 0.5, v + 0.5], -1).reshape(-1, 2)  # COLMAP pixel centres of the pinhole frame
    rays = np.column_stack([(pinhole - [CAMERA.cx, CAMERA.cy]) / [CAMERA.fx, CAMERA.fy], np.ones(len(pinhole))])
    K = CAMERA.K.copy()
    K[:2, 2] -= 0.5  # OpenCV's pixel centres
    dist = np.array(coefficients, np.float64)
    project = cv2.fisheye.projectPoints if kind == "fisheye" else cv2.projectPoints
    zero = np.zeros(3)
    photo = project(rays[:, None, :].astype(np.float64), zero, zero, K, dist)[0].reshape(-1, 2) + 0.5
    read = np.column_stack([map_x[v, u].ravel(), map_y[v, u].ravel()]) + 0.5
    np.testing.assert_allclose(read, photo, atol=0.05)


def test_colmap_lens_models_read_as_opencv_coefficients(tmp_path):
    path = tmp_path / "cameras.txt"
    path.write_text(
        "a.png SIMPLE_RADIAL 320 240 250 160 120 -0.1\nb.png PINHOLE 320 240 250 250 160 120\n"
        "c.png OPENCV_FISHEYE 320 240 150 150 160 120 0 0 0 0\n"
    )
    known = read_intrinsics(path)
    assert known.lens_of("a.png") == ("opencv", (-0.1, 0.0, 0.0, 0.0)) and known.lens_of("b.png") is None
    assert known.lens_of("c.png") == ("fisheye", (0.0, 0.0, 0.0, 0.0))  # equidistant: a fisheye all the same
