"""Whether a lens needs its radial term: the refinement's test (:func:`ffrecon.sfm.refine.passes.refine_tracks`).

On a forward walk, focal length and k trade off almost freely, and an unsupported k only bends the poses; so
the term is kept only where it clearly pays, and a clean lens is told apart cheaply first.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable

import numpy as np
import pycolmap

logger = logging.getLogger("ffrecon.sfm")

Adjust = Callable[[pycolmap.Reconstruction, pycolmap.LossFunctionType], bool]  # one adjustment, True: usable


class LensTrial(enum.Enum):
    """What became of the radial term (``BundleOptions.refine_distortion``)."""

    NONE = "none"  # nothing to try: a pinhole camera, or the term switched off
    PROBED = "probed"  # freeing it on the pinhole solution gained too little: no fine pass of its own
    REJECTED = "rejected"  # its own fine pass ran and did not pay
    KEPT = "kept"


def corner_distortion_px(camera: pycolmap.Camera) -> float:
    """How far (pixels) the camera's radial term moves an image corner: ``|k| r^3 f`` for SIMPLE_RADIAL.

    >>> camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=640, height=480, params=[500, 320, 240, 0.01])
    >>> corner_distortion_px(camera)  # corner at r = 400 / 500
    2.56
    """
    if camera.model.name != "SIMPLE_RADIAL":
        return 0.0
    focal, cx, cy, k = (float(x) for x in camera.params)
    r = np.hypot(max(cx, camera.width - cx), max(cy, camera.height - cy)) / focal
    return round(float(abs(k) * r**3 * focal), 6)


def distortion_may_pay(pinhole: pycolmap.Reconstruction, adjust_k: Adjust, min_px: float, min_gain: float) -> bool:
    """Whether the radial term is worth a fine pass of its own: one adjustment, with the term free, of a copy of
    the pinhole pass's converged model on its own tracks.

    The probe may understate what a pass of its own would gain (the pinhole pass has already filtered out the
    observations a lens bends most), so a pass follows from half of either threshold of
    :func:`distortion_pays`, which still decides. Measured on the 24-frame orbit through a 6 px barrel lens: the
    probe 15.9 %, the pass 15.5 %; undistorted, the probe 1.1 %. A clean lens (most captures) then costs one
    adjustment instead of a whole fine pass (112 s of the looped 500-frame bench scene's refinement).
    """
    probe = pycolmap.Reconstruction(pinhole)
    if not adjust_k(probe, pycolmap.LossFunctionType.TRIVIAL):
        return True  # the probe says nothing: let the pass decide
    probe.update_point_3d_errors()  # the adjustment leaves the points' stored errors as they were
    before, after = pinhole.compute_mean_reprojection_error(), probe.compute_mean_reprojection_error()
    corner = max(corner_distortion_px(camera) for camera in probe.cameras.values())
    may = corner >= min_px / 2 and after <= (1 - min_gain / 2) * before
    logger.info(
        "lens distortion %s: freed on the pinhole solution it moves the corners %.2f px and lowers the "
        "reprojection error %.1f%% (%.3f px to %.3f px)",
        "tried in a fine pass of its own" if may else "not tried",
        corner,
        100 * (1 - after / before) if before > 0 else 0.0,
        before,
        after,
    )
    return may


def distortion_pays(
    pinhole: pycolmap.Reconstruction, radial: pycolmap.Reconstruction, min_px: float, min_gain: float
) -> bool:
    """Whether the model with radial terms is clearly better: as many frames, corners moved by at least
    ``min_px``, mean reprojection error lower by at least the fraction ``min_gain``."""
    if radial.num_reg_images() < max(pinhole.num_reg_images(), 2):
        return False
    before, after = pinhole.compute_mean_reprojection_error(), radial.compute_mean_reprojection_error()
    corner = max(corner_distortion_px(camera) for camera in radial.cameras.values())
    k = next(float(c.params[3]) for c in radial.cameras.values() if c.model.name == "SIMPLE_RADIAL")
    pays = corner >= min_px and after <= (1 - min_gain) * before
    logger.info(
        "lens distortion %s: k = %.4g moves the corners %.1f px; reprojection error %.3f px without, %.3f px with",
        "kept" if pays else "not kept",
        k,
        corner,
        before,
        after,
    )
    return pays
