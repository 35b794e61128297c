"""Brief splat optimisation: L1 + D-SSIM, Adam with the 3DGS per-parameter rates, densification,
optional joint refinement of the camera poses (as InstantSplat does), per-image exposure and
white-balance compensation (see :mod:`ffrecon.splat.appearance`), a budget in iterations and seconds,
and a progress bar.

Its parts: the settings and the result (:mod:`ffrecon.splat.optimize_options`), the views it trains on
(:mod:`ffrecon.splat.train_views`), the trainable tensors and their Adam (:mod:`ffrecon.splat.trainable`); the
loop and one training step are here.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import time
from collections.abc import Callable, Sequence

import numpy as np
import torch
from tqdm import tqdm

from ffrecon.gaussians import Gaussians
from ffrecon.geometry.poses import camera_centers
from ffrecon.splat.appearance import appearance_penalty, apply_color_transform
from ffrecon.splat.budget import StepClock
from ffrecon.splat.densify import Densifier
from ffrecon.splat.optimize_options import OptimizeOptions, OptimizeResult
from ffrecon.splat.poses import bound_poses, depth_loss
from ffrecon.splat.render import interrupts_deferred, warm_up
from ffrecon.splat.ssim import ssim_mean
from ffrecon.splat.train_views import _training_views, _TrainingViews, resolution_factor, unit_float
from ffrecon.splat.trainable import (
    _as_gaussians,
    _color_transform,
    _current_color_transforms,
    _current_poses,
    _densify,
    _set_lr,
    _trainable,
    _view_pose,
)

logger = logging.getLogger("ffrecon.splat")


def scene_scale(cam_from_world: np.ndarray, points: np.ndarray) -> float:
    """3DGS's "cameras extent": 1.1 x the largest camera distance from their mean centre.

    Falls back to the robust extent of ``points [M, 3]`` when the cameras barely move.
    """
    centers = camera_centers(np.asarray(cam_from_world, np.float64))
    radius = 1.1 * float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) if len(centers) else 0.0
    lo, hi = np.percentile(points, [5, 95], axis=0)
    extent = 0.5 * float(np.linalg.norm(hi - lo))
    return radius if radius > 0.05 * extent else max(extent, 1e-6)


def photometric_loss(rendered: torch.Tensor, target: torch.Tensor, ssim_weight: float) -> torch.Tensor:
    """``(1 - w) L1 + w (1 - SSIM)`` of ``[H, W, 3]`` images.

    A ``[H, W, 4]`` target carries a mask (``--masks``; 1 use, 0 ignore) in its 4th channel: the render
    takes the target's own colour where it is 0, so those pixels add no error and no gradient, to the L1
    term and to every SSIM window alike.
    """
    if target.shape[-1] == 4:
        weight, target = target[..., 3:], target[..., :3]
        rendered = weight * rendered + (1 - weight) * target
    l1 = (rendered - target).abs().mean()
    if ssim_weight == 0:
        return l1
    ssim = ssim_mean(rendered.permute(2, 0, 1), target.permute(2, 0, 1))
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim)


def cpu_threads(requested: int | None = None) -> int:
    """Torch threads for the CPU renderer: ``requested``, or all but one available core.

    Leaving a core free matters on shared machines: the renderer runs thousands of small
    parallel operations per iteration, and each one waits for its slowest OpenMP thread, so a
    single busy core can slow two threads down tenfold (measured on a shared 2-core machine).
    """
    if requested:
        return max(1, int(requested))
    available = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(torch.get_num_threads(), available - 1))


@contextlib.contextmanager
def torch_threads(num: int):
    """Set torch's intra-op thread count inside the block, restoring it afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(num)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _log_lerp(start: float, end: float, fraction: float) -> float:
    if start <= 0 or end <= 0:
        return start
    return math.exp((1 - fraction) * math.log(start) + fraction * math.log(end))


def optimize(
    gaussians: Gaussians,
    images: Sequence[torch.Tensor],
    cam_from_world: np.ndarray,
    Ks: np.ndarray,
    train: Sequence[int],
    options: OptimizeOptions,
    *,
    scale: float,
    callback: Callable[[int, float, Gaussians, np.ndarray], None] | None = None,
    callback_every: int = 0,
    pose_views: Sequence[int] | None = None,
    depths: Sequence[np.ndarray | None] | None = None,
    deadline: float | Callable[[], float] | None = None,
) -> OptimizeResult:
    """Optimise ``gaussians`` on the training views (torch threads set by ``options.threads``).

    Args:
        gaussians: the seed (not modified).
        images: per view ``[H_i, W_i, 3]`` RGB: uint8 (held as they are) or float in [0, 1] (see :func:`unit_float`).
        cam_from_world: ``[N, 3, 4]`` OpenCV poses; Ks: ``[N, 3, 3]`` (COLMAP pixel convention).
        train: indices of the views to fit.
        scale: scene scale (see :func:`scene_scale`) for the position and pose learning rates.
        callback: called as ``callback(iteration, seconds, gaussians, cam_from_world)`` every
            ``callback_every`` iterations (its time is not counted in the budget).
        pose_views: training views whose poses are optimised with the Gaussians (jointly, as InstantSplat and
            nerfstudio's camera optimiser do), each correction bounded by ``max_pose_rotation_deg`` and
            ``max_pose_translation``; when they are all the training views the first stays fixed (gauge).
            None: every training view but the first with ``options.refine_poses``, none without.
        depths: per view ``[h, w]`` z-depth priors in the poses' scale (0 where unknown; None: no prior for
            that view), resized to each training resolution; used when ``options.depth_weight > 0``.
        deadline: a ``time.perf_counter()`` by which the loop must end, its callbacks' time included (the
            splat stage's budget, :mod:`ffrecon.splat.budget`), or a function returning it (asked before each
            step: the stage moves it as it measures what its later steps cost): the loop then has
            ``min(max_seconds, deadline - its start)`` of wall clock, and the plan is compressed to that.
            None: ``max_seconds`` of optimisation alone, callbacks not counted.
    """
    threads = torch_threads(cpu_threads(options.threads)) if options.device == "cpu" else contextlib.nullcontext()
    with threads:
        return _optimize(
            gaussians,
            images,
            cam_from_world,
            Ks,
            train,
            options,
            scale=scale,
            callback=callback,
            callback_every=callback_every,
            priors=(pose_views, depths),
            deadline=deadline,
        )


def _train_step(
    params: dict[str, torch.Tensor],
    optimizer: torch.optim.Optimizer,
    views: _TrainingViews,
    view: int,
    sh_degree: int,
    options: OptimizeOptions,
    densifier: Densifier | None,
    factor: int = 1,
) -> torch.Tensor:
    """One iteration on one view at 1/``factor`` resolution: render, colour transform, loss, backward,
    densification statistics, Adam step.

    Returns the loss (detached).
    """
    images, k_mats = views.levels.get(factor, (views.images, views.k_mats))
    target = unit_float(images[view])
    height, width = target.shape[:2]
    prior = views.depth_levels[factor][view] if views.depth_levels else None
    g = _as_gaussians(params)
    out = views.render(
        g.means,
        g.quats_wxyz,
        g.log_scales,
        g.opacity_logits,
        g.sh,
        _view_pose(params, views, view),
        k_mats[view],
        width,
        height,
        background=views.background,
        sh_degree=sh_degree,
        with_depth=prior is not None,
        options=options.raster,
    )
    out.means2d.retain_grad()
    rgb = out.rgb
    if "color_deltas" in params:
        transform = _color_transform(params, views, view)
        rgb = apply_color_transform(rgb, transform)
    loss = photometric_loss(rgb, target, options.ssim_weight)
    if "color_deltas" in params:
        loss = loss + options.appearance_weight * appearance_penalty(transform)
    if prior is not None:
        loss = loss + options.depth_weight * depth_loss(out, prior)
    loss.backward()
    if densifier is not None and out.means2d.grad is not None:
        densifier.accumulate(out.means2d.grad, out.visible, width, height)
    optimizer.step()
    optimizer.zero_grad()
    bound_poses(params, options.max_pose_rotation_deg, options.max_pose_translation * views.scale)
    return loss.detach()


class _Plateau:
    """Detects a plateau of the training loss: the mean over the last ``plateau_window`` iterations
    (all at full resolution, past ``plateau_after`` of the plan) improved by less than
    ``plateau_tolerance`` (relative) on the mean of the window before. A window of about five rounds
    of the training views averages out how much harder one view is than another."""

    def __init__(self, options: OptimizeOptions) -> None:
        self.options = options
        self.losses: list[float] = []
        self.previous: float | None = None

    def reached(self, loss: float, fraction: float, factor: int) -> bool:
        o = self.options
        if o.plateau_window <= 0 or factor != 1 or fraction < o.plateau_after:
            return False
        self.losses.append(loss)
        if len(self.losses) < o.plateau_window:
            return False
        mean = float(np.mean(self.losses))
        self.losses.clear()
        done = self.previous is not None and (self.previous - mean) < o.plateau_tolerance * self.previous
        self.previous = mean
        return done


def _loop_budget(o: OptimizeOptions, deadline, loop_start: float, elapsed: float) -> tuple[float, float]:
    """``(the loop's seconds, seconds spent)``: ``max_seconds`` and the optimisation's own ``elapsed``, or with
    a ``deadline`` (see :func:`optimize`) what is left to it from the loop's start and the loop's wall clock
    (callbacks included)."""
    if deadline is None:
        return o.max_seconds, elapsed
    end = deadline() if callable(deadline) else deadline
    return max(1e-9, min(o.max_seconds, end - loop_start)), time.perf_counter() - loop_start


def _pixels(views: _TrainingViews, view: int, factor: int) -> int:
    image = views.levels.get(factor, (views.images, views.k_mats))[0][view]
    return int(image.shape[0] * image.shape[1])


def _prepare(gaussians, images, cam_from_world, Ks, train, o: OptimizeOptions, scale, pose_views, depths):
    """``(views, params, adam, densifier)``: the optimisation's state before its first step."""
    views = _training_views(images, cam_from_world, Ks, train, o, pose_views, depths, scale)
    if o.device == "cpu" and (seconds := warm_up()) > 1.0:  # not counted in the budget
        logger.info("readied the CPU renderer in %.1f s (compiled on first use, then cached)", seconds)
    params, adam = _trainable(gaussians, o, scale, len(views.poses), bool(views.pose_views))
    densifier = None
    if o.densify is not None:
        densifier = Densifier(len(params["means"]), o.densify, scale, o.max_gaussians, o.seed, o.device)
    return views, params, adam, densifier


def _optimize(
    gaussians,
    images,
    cam_from_world,
    Ks,
    train,
    options: OptimizeOptions,
    *,
    scale,
    callback,
    callback_every,
    priors,
    deadline=None,
) -> OptimizeResult:
    """The loop: visit the training views in shuffled rounds until the plan's iterations, the time budget
    or a plateau of the training loss ends it; learning rate, resolution, SH degree and densification
    follow the fraction of the plan done (iterations or time, whichever is further on). ``priors``: the
    ``(pose_views, depths)`` of :func:`optimize`; ``deadline``: see there."""
    o = options
    train = list(train)
    if not train:
        raise ValueError("optimize: no training views")
    torch.manual_seed(o.seed)
    rng = np.random.default_rng(o.seed)
    views, params, adam, densifier = _prepare(gaussians, images, cam_from_world, Ks, train, o, scale, *priors)
    history: list[tuple[int, float, float]] = []
    plateau = _Plateau(o)
    order: list[int] = []
    elapsed, it, reason = 0.0, 0, "iterations"
    clock = StepClock()
    disable = None if o.progress else True  # None: off when not a terminal
    bar = tqdm(total=o.iterations, desc="splat", unit="it", disable=disable, leave=False)
    loop_start, fraction = time.perf_counter(), 0.0
    while it < o.iterations:
        budget, spent = _loop_budget(o, deadline, loop_start, elapsed)
        fraction = min(1.0, max(fraction, it / o.iterations, spent / budget))
        factor = resolution_factor(o, fraction)
        if not order:
            order = [train[j] for j in rng.permutation(len(train))]
        pixels = _pixels(views, order[-1], factor)
        # The budget is an upper bound, but for one step: a splat optimised for no step at all is only its seed.
        if it > 0 and spent + clock.predict(pixels) > budget:
            reason = "time budget"
            break
        start = time.perf_counter()
        _set_lr(adam, "means", _log_lerp(o.lr_means * scale, o.lr_means_final * scale, fraction))
        degree = min(o.sh_degree, it // max(o.sh_band_every, 1))
        with interrupts_deferred():  # a Ctrl-C is taken between steps, never inside a numba kernel
            loss = _train_step(params, adam, views, order.pop(), degree, o, densifier, factor).item()
        it += 1
        if densifier is not None and densifier.due(it, fraction):
            params = _densify(densifier, params, adam)
        elapsed += clock.record(pixels, time.perf_counter() - start)
        if it % 10 == 0:
            history.append((it, elapsed, loss))
            bar.set_postfix(loss=f"{loss:.4f}", n=len(params["means"]), res=f"1/{factor}")
        bar.update(1)
        if callback is not None and callback_every and it % callback_every == 0:
            callback(it, elapsed, _as_gaussians(params).detached().to("cpu"), _current_poses(params, views))
        if plateau.reached(loss, fraction, factor):
            reason = "plateau"
            break
    bar.close()
    return _result(params, views, it, elapsed, history, reason)


def _result(params, views: _TrainingViews, it: int, elapsed: float, history, reason: str) -> OptimizeResult:
    rate = it / max(elapsed, 1e-9)
    logger.info("splat: %d iterations in %.1f s (%.2f it/s), stopped by %s", it, elapsed, rate, reason)
    return OptimizeResult(
        gaussians=_as_gaussians(params).detached().to("cpu"),
        cam_from_world=_current_poses(params, views),
        color_transforms=_current_color_transforms(params, views),
        iterations=it,
        seconds=elapsed,
        history=tuple(history),
        stop_reason=reason,
        pose_views=views.pose_views,
    )
