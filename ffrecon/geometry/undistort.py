"""Lens distortion: COLMAP's camera models as OpenCV coefficients, and undistorted images for the splat.

The splat's rasteriser is a pinhole camera, so it trains on undistorted photos. OpenCV does the
remapping; its pixel centres are at integer coordinates, ffrecon's (COLMAP's) at +0.5, so the
calibration is shifted by half a pixel on the way in and back on the way out (the one boundary).
"""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap

from ffrecon.types import PinholeCamera

NO_DISTORTION = (0.0, 0.0, 0.0, 0.0)


def opencv_coefficients(camera: pycolmap.Camera) -> tuple[float, float, float, float]:
    """``(k1, k2, p1, p2)`` of a COLMAP camera (zeros for pinhole models).

    >>> opencv_coefficients(pycolmap.Camera(model="SIMPLE_RADIAL", width=4, height=3, params=[2.0, 2.0, 1.5, -0.1]))
    (-0.1, 0.0, 0.0, 0.0)
    """
    name = camera.model.name
    p = [float(x) for x in camera.params]
    if name == "SIMPLE_RADIAL":
        return (p[3], 0.0, 0.0, 0.0)
    if name == "RADIAL":
        return (p[3], p[4], 0.0, 0.0)
    if name in ("OPENCV", "FULL_OPENCV"):
        return (p[4], p[5], p[6], p[7])
    if name in ("SIMPLE_PINHOLE", "PINHOLE"):
        return NO_DISTORTION
    raise ValueError(f"camera model {name} has no OpenCV (k1, k2, p1, p2) equivalent")


def _opencv_K(camera: PinholeCamera) -> np.ndarray:
    K = camera.K.copy()
    K[:2, 2] -= 0.5  # COLMAP's pixel centres -> OpenCV's
    return K


def undistort_image(
    rgb: np.ndarray, camera: PinholeCamera, coefficients: tuple[float, float, float, float]
) -> tuple[np.ndarray, PinholeCamera]:
    """The image as a pinhole camera of the same size would see it, cropped to valid pixels.

    Args:
        rgb: ``[H, W, 3]`` uint8, taken with ``camera`` (COLMAP pixel convention) and the OpenCV
            ``coefficients`` ``(k1, k2, p1, p2)``.
    Returns:
        ``(undistorted [H, W, 3] uint8, its pinhole camera)``; unchanged when there is no distortion.
    """
    if not any(coefficients):
        return rgb, camera
    K = _opencv_K(camera)
    dist = np.array(coefficients, np.float64)
    size = (camera.width, camera.height)
    new_K, _ = cv2.getOptimalNewCameraMatrix(K, dist, size, 0.0, size)  # alpha 0: only valid pixels
    out = cv2.undistort(rgb, K, dist, None, new_K)
    new_K[:2, 2] += 0.5  # back to COLMAP's convention
    return out, PinholeCamera.from_K(new_K, camera.width, camera.height)
