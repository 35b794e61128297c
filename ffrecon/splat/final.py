"""The splat of a run's final cameras (:mod:`ffrecon.final_cameras`): which seed it grows from, and the
same splat grown from COLMAP's points for comparison (``--compare-seeds``).

The model's cameras (refined or not) grow from the model's depth maps; COLMAP's cameras from COLMAP's
sparse points. Photos with lens distortion are undistorted first: the rasteriser is a pinhole camera.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ffrecon.capture import Capture
from ffrecon.final_cameras import CameraSource, FinalCameras
from ffrecon.geometry.undistort import undistort_image
from ffrecon.models.stage import FeedForwardResult
from ffrecon.sfm.compare.poses import compare_poses
from ffrecon.sfm.crosscheck.run import ColmapResult
from ffrecon.splat.options import SplatOptions
from ffrecon.splat.result import SplatResult
from ffrecon.splat.seed import seed_from_reconstruction
from ffrecon.timing import StageTimer
from ffrecon.types import Skipped

CURVE_EVERY = 20  # iterations between held-out scores when the two seeds are compared


def run_splat(*args, **kwargs) -> SplatResult:
    """:func:`ffrecon.splat.stage.run_splat`, whose module (torch, the compiled kernels) loads when a splat runs."""
    from ffrecon.splat.stage import run_splat

    return run_splat(*args, **kwargs)


def run_splat_from_prediction(*args, **kwargs) -> SplatResult:
    """:func:`ffrecon.splat.stage.run_splat_from_prediction`, loaded as :func:`run_splat` is."""
    from ffrecon.splat.stage import run_splat_from_prediction

    return run_splat_from_prediction(*args, **kwargs)


def splat_final_cameras(
    final: FinalCameras,
    ff: FeedForwardResult | Skipped,
    colmap: ColmapResult | Skipped,
    capture: Capture,
    options: SplatOptions,
    work: Path,
) -> SplatResult:
    """The run's splat on the final cameras, in ``work``; reading the photos is the stage's first step (its
    time budget, ``options.optimize.max_seconds``, counts from the start)."""
    timer = StageTimer()
    with timer.stage("read_images"):
        images = capture.read_images(list(final.indices))
        masks = capture.read_masks(list(final.indices))
    cameras = final.cameras
    if final.distortion is not None:  # the rasteriser is a pinhole camera: train on undistorted photos
        with timer.stage("undistort"):
            images, cameras, masks = _undistorted(images, cameras, masks, final.distortion)
    if final.source is not CameraSource.COLMAP and isinstance(ff, FeedForwardResult):
        args = (ff.prediction.subset(final.indices), images, final.cam_from_world, cameras, options, work)
        return run_splat_from_prediction(*args, unconfirmed=final.unconfirmed, masks=masks, timer=timer)
    if not isinstance(colmap, ColmapResult):
        raise AssertionError(f"final cameras from {final.source} without the result they come from")
    with timer.stage("seed_points"):
        xyz, rgb = seed_from_reconstruction(colmap.reconstruction)  # COLMAP's cameras: its points
    args = (images, final.names, final.cam_from_world, cameras, xyz, rgb, options, work)
    return run_splat(*args, masks=masks, timer=timer)


def _undistorted(images, cameras, masks, distortion):
    """``(images, pinhole cameras, masks)`` undistorted (masks the same way, as the image's 4th channel)."""
    if masks is not None:
        images = [np.dstack([im, np.where(m, 255, 0).astype(np.uint8)]) for im, m in zip(images, masks)]
    pairs = [undistort_image(im, c, d) for im, c, d in zip(images, cameras, distortion)]
    images, cameras = [p[0] for p in pairs], tuple(p[1] for p in pairs)
    if masks is not None:
        masks, images = [im[..., 3] > 127 for im in images], [im[..., :3] for im in images]
    return images, cameras, masks


def with_curves(options: SplatOptions) -> SplatOptions:
    """With --compare-seeds both splats score their held-out views at least every ``CURVE_EVERY`` iterations
    as they train (for the plot that compares them; the default curve is sparser)."""
    if not options.compare_seeds or 0 < options.curve_every <= CURVE_EVERY:
        return options
    return dataclasses.replace(options, curve_every=CURVE_EVERY)


def seed_comparison_skip_reason(
    splat: SplatResult | Skipped, final: FinalCameras | Skipped, colmap: ColmapResult | Skipped
) -> str | None:
    """Why the seed comparison cannot run, or None."""
    if not isinstance(splat, SplatResult):
        return "the splat did not run"
    usable = isinstance(colmap, ColmapResult) and colmap.num_registered >= 3
    if not usable or not isinstance(final, FinalCameras) or final.source is CameraSource.COLMAP:
        return "needs a model's cameras and a COLMAP model of three images or more (seeds differ only then)"
    return None


def splat_from_colmap_points(
    final: FinalCameras, colmap: ColmapResult, capture: Capture, options: SplatOptions, work: Path
) -> SplatResult:
    """The same splat trained from COLMAP's points (moved into the final cameras' frame), same budget, in
    ``work/seed_comparison``."""
    names = capture.names
    full = np.stack([np.eye(3, 4)] * len(names))
    full[list(final.indices)] = final.cam_from_world
    timer = StageTimer()
    with timer.stage("read_images"):
        to_final = compare_poses(colmap.cam_from_world, full, names, colmap.registered).errors.est_to_ref
        xyz, rgb = seed_from_reconstruction(colmap.reconstruction)
        images, masks = capture.read_images(list(final.indices)), capture.read_masks(list(final.indices))
    args = (images, final.names, final.cam_from_world, final.cameras, to_final.apply(xyz), rgb)
    return run_splat(*args, options, work / "seed_comparison", masks=masks, timer=timer)
