"""The splat stage: seed, optimise briefly, clean, export, measure.

Two entries share one implementation. :func:`run_splat_from_prediction` (what the pipeline calls)
seeds from the feed-forward depth maps of the training views; :func:`run_splat` takes an explicit
seed cloud. Both write, under ``out_dir``: ``splat.ply`` (3DGS layout, see :mod:`ffrecon.formats.splat_ply`),
``renders/<view>_{truth,seed,splat}.png`` for a few held-out views and ``flythrough.mp4``.

The stage's modules: :mod:`~ffrecon.splat.options` (:class:`SplatOptions`), :mod:`~ffrecon.splat.result`
(:class:`SplatResult`), :mod:`~ffrecon.splat.stage_run` (the steps' shared state and the budget's split),
:mod:`~ffrecon.splat.evaluate` (render and score: held-out curve, cleaning judge, pose check, final scores) and
:mod:`~ffrecon.splat.outputs` (the files); this one chains them.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from ffrecon.capture import CaptureOptions
from ffrecon.checks import check_shape, require_finite
from ffrecon.errors import InputError
from ffrecon.gaussians import Gaussians
from ffrecon.splat.budget import StageBudget
from ffrecon.splat.clean import CleanReport, clean_gaussians
from ffrecon.splat.evaluate import (
    CURVE_SHARE,
    color_corrected,
    evaluate_heldout,
    heldout_curve_scorer,
    heldout_psnr_judge,
    image_metrics,
    known_scores,
    pose_changes,
    probe_costs,
    split_views,
    with_masks,
)
from ffrecon.splat.memory import splat_peak_bytes, training_side
from ffrecon.splat.optimize import cpu_threads, scene_scale, torch_threads
from ffrecon.splat.optimize_options import OptimizeResult
from ffrecon.splat.options import SplatDevice, SplatOptions, ViewPriors, resolve_device
from ffrecon.splat.outputs import MIN_VIDEO_FRAMES, OUTPUTS, write_outputs
from ffrecon.splat.render import warm_up
from ffrecon.splat.result import PoseChange, SplatResult, ViewMetrics
from ffrecon.splat.seed import initial_gaussians, reduce_points, seed_from_prediction
from ffrecon.splat.stage_run import StageRun, after_estimates, optimize_timed, plan_steps
from ffrecon.timing import StageTimer
from ffrecon.types import PinholeCamera, Prediction, capped_size

logger = logging.getLogger("ffrecon.splat")

__all__ = [  # the stage's names, and those of its modules that callers import from here
    "CURVE_SHARE",
    "MIN_VIDEO_FRAMES",
    "OUTPUTS",
    "PoseChange",
    "SplatDevice",
    "SplatOptions",
    "SplatResult",
    "ViewMetrics",
    "ViewPriors",
    "check_splat_fits",
    "check_splat_memory",
    "color_corrected",
    "image_metrics",
    "prediction_seed",
    "resolve_device",
    "run_splat",
    "run_splat_from_prediction",
    "split_views",
    "with_masks",
]
_Run = StageRun  # what tests call the steps' shared state
_write_outputs = write_outputs


def check_splat_fits(sizes_wh: Sequence[tuple[int, int]], options: SplatOptions) -> None:
    """Refuse, before any pose is made, a splat that cannot fit in memory at all (when the splat is on)."""
    if options.enabled:
        check_splat_memory(sizes_wh, options, when=" (planned)")


def check_splat_memory(sizes_wh: Sequence[tuple[int, int]], options: SplatOptions, *, when: str = "") -> int | None:
    """The long side (px) to which the CPU splat shrinks larger views of ``sizes_wh`` to fit the memory free
    now (None: full size; :mod:`ffrecon.splat.memory`), logged when it shrinks any. The pipeline asks before
    any work, so that a splat that cannot fit at all is a :class:`~ffrecon.errors.ResourceError` in seconds;
    the stage asks again when it starts, with the memory free then. On CUDA (gsplat): None."""
    if not sizes_wh or resolve_device(options.device) != "cpu":
        return None
    side = training_side(sizes_wh, options.optimize.max_gaussians)
    if side is not None:
        w, h = max(sizes_wh, key=lambda s: s[0] * s[1])
        full = splat_peak_bytes(sizes_wh, options.optimize.max_gaussians)
        shrunk = sum(max(s) > side for s in sizes_wh)
        logger.warning(
            "splat%s: training %d view(s) at %d px on the long side (%dx%d instead of %dx%d): full size needs "
            "about %.1f GB, more than memory allows; smaller frames (--max-image-size, default %s) avoid this",
            when,
            shrunk,
            side,
            *capped_size(w, h, side),
            w,
            h,
            full / 2**30,
            CaptureOptions.__dataclass_fields__["max_image_size"].default,
        )
    return side


def _capped(images, cameras, max_side: int | None) -> tuple[list[np.ndarray], list[PinholeCamera]]:
    """Views whose long side exceeds ``max_side`` shrunk to it (area average), their cameras scaled to the
    new pixel grid; the others as they are."""
    out_images, out_cameras = [], []
    for im, cam in zip(images, cameras):
        w, h = capped_size(im.shape[1], im.shape[0], max_side)
        if (w, h) != (im.shape[1], im.shape[0]):
            cam = cam.scaled(w / im.shape[1], h / im.shape[0])
            im = cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA)
        out_images.append(im)
        out_cameras.append(cam)
    return out_images, out_cameras


def run_splat(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    seed_xyz: np.ndarray,
    seed_rgb: np.ndarray,
    options: SplatOptions,
    out_dir: Path,
    *,
    masks: Sequence[np.ndarray] | None = None,
    timer: StageTimer | None = None,
) -> SplatResult:
    """Optimise, clean and export a Gaussian splat from an explicit seed; measure it on held-out views.

    Args:
        images: per frame ``[H, W, 3]`` uint8 RGB.
        names: per frame file names (held-out renders are named after their stem).
        cam_from_world: ``[N, 3, 4]`` OpenCV poses; cameras: per frame pinhole intrinsics.
        seed_xyz: ``[M, 3]`` world points; seed_rgb: ``[M, 3]`` float colours in [0, 1]. To keep the
            held-out PSNR honest, they should come from the training views of :func:`split_views` only.
        masks: per frame ``[H, W]`` bool (True: use the pixel; ``--masks``), or None: the loss and the held-out
            scores ignore the pixels they leave out.
        timer: the stage's timer when the caller's work (reading the photos) belongs to it: the stage's time
            budget (``optimize.max_seconds``) counts from when it was made. None: from now.
    """
    timer = timer or StageTimer()
    images = with_masks(images, masks)
    split = split_views(len(images), options.holdout_every)
    with torch_threads(cpu_threads(options.optimize.threads)):
        return _splat(images, names, cam_from_world, cameras, seed_xyz, seed_rgb, split, options, out_dir, timer)


def run_splat_from_prediction(
    prediction: Prediction,
    images: Sequence[np.ndarray],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    options: SplatOptions,
    out_dir: Path,
    *,
    unconfirmed: Sequence[int] = (),
    masks: Sequence[np.ndarray] | None = None,
    timer: StageTimer | None = None,
) -> SplatResult:
    """The splat stage seeded from feed-forward depth: split the views, seed from the training views, optimise.

    Args:
        prediction: the feed-forward output (depth maps, confidences, names) for the same frames.
        images: per frame ``[H, W, 3]`` uint8 RGB at the size of ``cameras``.
        cam_from_world: ``[N, 3, 4]`` OpenCV poses and cameras: per frame intrinsics, the final ones
            (e.g. after bundle adjustment), in the prediction's world frame and scale.
        unconfirmed: frames no independent evidence confirmed: with ``refine_unconfirmed_poses`` their
            training views' poses are optimised with the Gaussians (and reported, see :class:`PoseChange`).

    Each training view's depth map is unprojected with its final camera (see :func:`prediction_seed`),
    then :func:`run_splat`'s optimisation follows with the same split. With fewer than
    ``depth_prior_below`` frames and some frame unconfirmed, the depth maps are also a prior in the loss
    (``optimize.depth_weight``). ``timer``: as :func:`run_splat`'s.
    """
    timer = timer or StageTimer()
    images = with_masks(images, masks)  # the prediction's depth is already masked (no seed from there)
    split = split_views(len(images), options.holdout_every)
    _validate_views(images, prediction.names, cam_from_world, cameras)
    with torch_threads(cpu_threads(options.optimize.threads)):
        with timer.stage("fuse_depth"):
            xyz, rgb = prediction_seed(prediction, images, cam_from_world, cameras, split[0], options)
        names = prediction.names
        pose_views = tuple(unconfirmed) if options.refine_unconfirmed_poses else ()
        few = len(images) < options.depth_prior_below
        priors = ViewPriors(pose_views, _depth_priors(prediction) if few and unconfirmed else None)
        return _splat(images, names, cam_from_world, cameras, xyz, rgb, split, options, out_dir, timer, priors)


def _depth_priors(prediction: Prediction, min_conf: float = 1.0) -> tuple[np.ndarray, ...]:
    """Per frame the model's depth where it is known and confident (the seed's rule), 0 elsewhere."""
    return tuple(
        np.where(prediction.valid_mask(k, min_conf), d, 0).astype(np.float32) for k, d in enumerate(prediction.depth)
    )


def prediction_seed(
    prediction: Prediction,
    images: Sequence[np.ndarray],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    frames: Sequence[int],
    options: SplatOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Seed points from the depth maps of ``frames``, placed with the final cameras.

    Final (refined) cameras sit in the feed-forward world at its scale, so each depth map is
    unprojected with its frame's final pose and intrinsics: points from different frames then agree
    where the feed-forward poses did not. Images are resized (``INTER_AREA``) to their depth map's
    grid where the sizes differ. Returns ``(xyz [M, 3] float64, rgb [M, 3] float32 in [0, 1])``.
    """
    pred = dataclasses.replace(prediction, cam_from_world=cam_from_world, cameras=tuple(cameras))
    small = [
        im[..., :3] if im.shape[:2] == d.shape else cv2.resize(im[..., :3], d.shape[::-1], interpolation=cv2.INTER_AREA)
        for im, d in zip(images, pred.depth)
    ]
    return seed_from_prediction(
        pred, small, max_points=options.max_seed_points, frames=frames, seed=options.optimize.seed
    )


def _splat(
    images,
    names,
    cam_from_world,
    cameras,
    seed_xyz,
    seed_rgb,
    split,
    options: SplatOptions,
    out_dir,
    timer: StageTimer,
    priors: ViewPriors = ViewPriors(),
) -> SplatResult:
    """Both entries' implementation, from the seed cloud and the ``(train, heldout)`` split on.

    ``timer`` holds what the entry already measured and receives the rest of the steps; the stage's budget
    (``options.optimize.max_seconds``) counts from when it was made."""
    _validate_views(images, names, cam_from_world, cameras, seed=(seed_xyz, seed_rgb))
    train, heldout = split
    out_dir = Path(out_dir)
    options, max_side, images, cameras = _on_device(options, images, cameras, split)
    run = StageRun(timer, StageBudget(options.optimize.max_seconds, timer.started))
    seed, result, cleaned, clean_report = _fit_and_clean(
        images, cam_from_world, cameras, seed_xyz, seed_rgb, split, options, run, priors
    )
    poses = result.cam_from_world
    changes = _pose_check(timer, names, images, cam_from_world, cameras, result, split, options)
    splats = {"seed": seed, "optimized": result.gaussians, "cleaned": cleaned}
    known = (known_scores(run, heldout, result.iterations), run.seed_renders)  # scored by the held-out curve
    with timer.stage("evaluate"):
        metrics, renders = evaluate_heldout(
            heldout, names, images, poses, cameras, splats, options, out_dir, known=known
        )
    ply_path, video_path, web_paths = write_outputs(out_dir, cleaned, poses, cameras[0], options, run)
    timer.close()  # what no step holds (validation, the result itself): the steps sum to the stage
    res = SplatResult(
        out_dir=out_dir,
        ply_path=ply_path,
        renders_dir=out_dir / "renders",
        render_paths=renders,
        video_path=video_path,
        train=tuple(train),
        heldout=tuple(heldout),
        heldout_metrics=metrics,
        timings=timer.freeze(),
        iterations=result.iterations,
        iterations_per_second=result.iterations / max(result.seconds, 1e-9),
        count_seed=len(seed),
        count_optimized=len(result.gaussians),
        count_cleaned=len(cleaned),
        clean=clean_report,
        backend="gsplat" if options.optimize.device == "cuda" else "cpu",
        cam_from_world=poses,
        color_transforms=result.color_transforms,
        heldout_curve=tuple(run.curve),
        stop_reason=result.stop_reason,
        max_side=max_side,
        pose_changes=changes,
        depth_prior=priors.depths is not None and options.optimize.depth_weight > 0,
        budget_s=run.budget.seconds,
        skipped_steps=tuple(run.skipped.items()),
        **web_paths,
    )
    return _log_summary(res)


def _on_device(options: SplatOptions, images, cameras, split) -> tuple[SplatOptions, int | None, list, list]:
    """``(options, max_side, images, cameras)``: the options with the device the splat trains and renders on,
    and the views shrunk to what memory allows (see :func:`check_splat_memory`)."""
    device = resolve_device(options.device)  # training and every later render (scores, renders, video)
    options = dataclasses.replace(options, optimize=dataclasses.replace(options.optimize, device=device))
    logger.info("splat: %d training and %d held-out views, device %s", len(split[0]), len(split[1]), device)
    max_side = check_splat_memory([(im.shape[1], im.shape[0]) for im in images], options)
    return (options, max_side, *_capped(images, cameras, max_side))


def _fit_and_clean(
    images, cam_from_world, cameras, seed_xyz, seed_rgb, split, options: SplatOptions, run: StageRun, priors: ViewPriors
) -> tuple[Gaussians, OptimizeResult, Gaussians, CleanReport]:
    """Seed Gaussians, optimise them on the training views within what the stage's budget leaves after the
    steps to come, clean the result; adds the step times to ``run.timer`` and, with ``options.curve_every``,
    the held-out scores over the optimisation to ``run.curve``."""
    train, heldout = split
    opt, timer = options.optimize, run.timer
    cam_from_world = np.asarray(cam_from_world, np.float64)
    with timer.stage("seed"):
        seed, seed_points = _initial_splat(seed_xyz, seed_rgb, options)
        scale = scene_scale(cam_from_world[train], seed_points)
    targets = [torch.from_numpy(np.ascontiguousarray(im)) for im in images]  # uint8, as the photos (unit_float)
    if opt.device == "cpu":
        with timer.stage("compile"):  # numba's kernels: compiled on first use, then loaded from its cache
            warm_up()
    score = (
        heldout_curve_scorer(run, heldout, cameras, targets, options) if options.curve_every > 0 and heldout else None
    )
    run.curve_every = options.curve_every if score is not None else 0
    if score is not None:
        score(0, 0.0, seed, cam_from_world)  # also measures a view's render and score for the budget
    else:
        with timer.stage("budget_probe"):
            run.costs = probe_costs(seed, cam_from_world, cameras, (heldout or train)[0], targets, opt)
    plan_steps(run, len(seed), split, options, priors, curve=score is not None)
    result = optimize_timed(run, seed, targets, cam_from_world, cameras, split, opt, scale, score, priors)
    if score is not None and run.curve[-1][0] < result.iterations and run.after.allowed("heldout_curve"):
        score(result.iterations, result.seconds, result.gaussians, result.cam_from_world)  # ends where it did
    curve = run.curve_timer.freeze()
    timer.add("heldout_curve", curve.total_s, sum(c for c in curve.cpu if c is not None))
    run.after.update(after_estimates(run, len(result.gaussians), split, options, priors, curve=score is not None))
    logger.debug("splat: the steps after the optimiser, estimated: %s", {s.name: s.seconds for s in run.after.steps})
    poses = result.cam_from_world
    with timer.stage("clean"):
        optimized = [run.known.get((result.iterations, i), (None,))[0] for i in heldout]
        first = float(np.mean(optimized)) if heldout and None not in optimized else None
        judged = heldout and run.after.allowed("clean_judge")
        judge = heldout_psnr_judge(heldout, poses, cameras, targets, opt, first) if judged else None
        train_cameras = [cameras[i] for i in train]
        cleaned, report = clean_gaussians(result.gaussians, poses[train], train_cameras, options.clean, judge=judge)
    return seed, result, cleaned, report


def _pose_check(timer: StageTimer, *args) -> tuple[PoseChange, ...]:
    """:func:`pose_changes`, timed as the step ``pose_check``."""
    with timer.stage("pose_check"):
        return pose_changes(*args)


def _validate_views(images, names, cam_from_world, cameras, seed=None) -> None:
    """Raise :class:`InputError` unless there is one name, pose and camera per image (and, given ``seed``
    ``(xyz, rgb)``, a finite seed cloud with one colour per point)."""
    if seed is not None:
        _validate_seed(*seed)
    n = len(images)
    if not (len(names) == n == len(cameras) == len(cam_from_world)):
        raise InputError(
            f"run_splat: {n} images, {len(names)} names, {len(cameras)} cameras, {len(cam_from_world)} poses",
            "pass one of each per frame",
        )
    check_shape("cam_from_world", np.asarray(cam_from_world), (n, 3, 4))
    intrinsics = np.array([[c.fx, c.fy, c.cx, c.cy] for c in cameras])
    require_finite("splat", cam_from_world=cam_from_world, intrinsics=intrinsics, fix=CAMERAS_FIX)
    for name, image, cam in zip(names, images, cameras):
        check_shape(f"image {name}", image, (cam.height, cam.width, image.shape[-1] if image.ndim == 3 else 3))
        if image.shape[-1] not in (3, 4):
            raise InputError(f"image {name} has {image.shape[-1]} channels", "pass RGB images (and masks apart)")


CAMERAS_FIX = (
    "the cameras and seed points come from the earlier stages: see which made them in the run's report "
    "(a model: check it with `ffrecon inspect-model` and re-export it; COLMAP: pass --no-colmap or other photos)"
)


def _validate_seed(seed_xyz, seed_rgb) -> None:
    check_shape("seed_xyz", np.asarray(seed_xyz), (None, 3))
    check_shape("seed_rgb", np.asarray(seed_rgb), (len(seed_xyz), 3))
    require_finite("splat", seed_xyz=seed_xyz, seed_rgb=seed_rgb, fix=CAMERAS_FIX)


def _initial_splat(seed_xyz: np.ndarray, seed_rgb: np.ndarray, options: SplatOptions) -> tuple[Gaussians, np.ndarray]:
    """The seed cloud reduced to ``min(max_seed_points, optimize.max_gaussians)`` points, as 3DGS
    Gaussians, and those points (``[M, 3]`` float64)."""
    o = options.optimize
    xyz, rgb = reduce_points(
        np.asarray(seed_xyz, np.float64),
        np.asarray(seed_rgb, np.float32),
        voxel_size=None,
        max_points=min(options.max_seed_points, o.max_gaussians),
        seed=o.seed,
    )
    return initial_gaussians(xyz, rgb, sh_degree=o.sh_degree), xyz


def _log_summary(res: SplatResult) -> SplatResult:
    if res.heldout_metrics:
        logger.info(
            "splat: held-out PSNR %.2f -> %.2f dB (cleaned %.2f, colour-corrected %.2f), SSIM %.3f -> %.3f; "
            "%d iterations (%.2f it/s, stopped by %s)",
            res.mean("psnr_seed"),
            res.mean("psnr_optimized"),
            res.mean("psnr_cleaned"),
            res.mean("psnr_cleaned_color_corrected"),
            res.mean("ssim_seed"),
            res.mean("ssim_optimized"),
            res.iterations,
            res.iterations_per_second,
            res.stop_reason,
        )
    return res
