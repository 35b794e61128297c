"""Photos with a known lens made pinhole at capture: a photo whose given intrinsics (``--intrinsics``) carry
distortion (COLMAP's ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV`` or ``OPENCV_FISHEYE``) is undistorted with
OpenCV to the pinhole camera with the same fx, fy, cx, cy and size, and written in its place in
``images/``; so the network, COLMAP's cross-check, the splat and transforms.json all see pinhole frames.
What falls outside the photo (a fisheye's periphery beyond the pinhole's field of view is cropped: a 150
degree fisheye keeps about 93 x 76 degrees at 320 x 240) is black, and masked where a mask was given.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ffrecon.errors import InputError
from ffrecon.formats.intrinsics import Lens
from ffrecon.types import PinholeCamera


def undistortion_maps(camera: PinholeCamera, lens: Lens) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV remap tables ``[H, W]`` float32: where in the photo each pixel of the pinhole frame is (OpenCV's
    pixel centres are at integers, COLMAP's at half-integers: K is shifted by 0.5 for OpenCV and back)."""
    kind, coefficients = lens
    K = camera.K.copy()
    K[:2, 2] -= 0.5
    size, dist = (camera.width, camera.height), np.array(coefficients, np.float64)
    if kind == "fisheye":
        return cv2.fisheye.initUndistortRectifyMap(K, dist, np.eye(3), K, size, cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(K, dist, None, K, size, cv2.CV_32FC1)


def undistort_lens(image_path: Path, camera: PinholeCamera, lens: Lens, mask_path: Path | None = None) -> None:
    """Replace the frame at ``image_path`` (and its mask) by its pinhole view with ``camera``'s K."""
    image = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
    if image is None or (image.shape[1], image.shape[0]) != (camera.width, camera.height):
        raise InputError(f"{image_path.name}: cannot undistort it with its given lens", "check --intrinsics")
    map_x, map_y = undistortion_maps(camera, lens)
    if not cv2.imwrite(str(image_path), cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, cv2.BORDER_CONSTANT)):
        raise InputError(f"cannot write {image_path}", "check the output folder is writable")
    if mask_path is not None:  # outside the photo counts as masked (0)
        mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(mask_path), cv2.remap(mask, map_x, map_y, cv2.INTER_NEAREST, cv2.BORDER_CONSTANT))
