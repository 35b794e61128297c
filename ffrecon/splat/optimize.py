"""Brief splat optimisation: L1 + D-SSIM, Adam with the 3DGS per-parameter rates, densification,
optional joint refinement of the camera poses (as InstantSplat does), per-image exposure and
white-balance compensation (see :mod:`ffrecon.splat.appearance`), a budget in iterations and seconds,
and a progress bar.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ffrecon.checks import check_number
from ffrecon.errors import InputError
from ffrecon.gaussians import Gaussians
from ffrecon.geometry.poses import camera_centers
from ffrecon.splat.appearance import appearance_penalty, apply_color_transform, identity_transforms
from ffrecon.splat.budget import StepClock
from ffrecon.splat.densify import Densifier, DensifyOptions, replace_rows
from ffrecon.splat.poses import bound_poses, depth_levels, depth_loss, pose_views_of, refined_pose
from ffrecon.splat.render import RasterOptions, interrupts_deferred, render, warm_up
from ffrecon.splat.ssim import ssim_mean

logger = logging.getLogger("ffrecon.splat")


@dataclass(frozen=True, kw_only=True)
class OptimizeOptions:
    """Optimiser settings. The learning rates default to the ones of the 3DGS paper (Kerbl et al. 2023),
    tuned for ~30k iterations; :meth:`brief` scales them for the few hundred a CPU does in minutes.

    Adam (``torch.optim.Adam``, betas 0.9 and 0.999, eps 1e-15) has one learning rate per tensor:
    positions (times the scene scale), SH DC, SH rest, opacity, scales, rotations, with
    ``refine_poses`` the camera corrections and with ``appearance`` the per-image colour transforms.

    ``appearance``: each training image gets an affine colour transform ``[A | b]`` (``[3, 4]``)
    applied to its render before the loss, so that exposure and white-balance changes between photos
    are not baked into the Gaussians as floaters. The transforms average ``[I | 0]`` over the training
    images (the gauge: the Gaussians keep the mean exposure, and renders need no transform), and the
    loss adds ``appearance_weight * ||[A | b] - [I | 0]||^2`` of the image trained on. Measured on the
    demo scene (brief rates, 300 iterations, 1 thread, ``tools/bench_splat.py``): at its constant
    exposure, held-out PSNR 26.74 dB off and 26.71 dB on (26.62 and 26.64 with seed 1); with
    per-photo channel gains in [0.7, 1.3], colour-corrected held-out PSNR 24.62 dB off, 25.81 dB on.
    ``lr_appearance`` 2e-3 adds 0.14 dB to the latter but costs 0.14 dB at constant exposure."""

    iterations: int = 3000  # the plan: learning rates, resolution, SH and densification follow it
    # The splat stage's time budget (--splat-seconds): the optimisation's plan is compressed to fit what the
    # stage's other steps leave of it. The one default of the budget (brief() keeps it).
    max_seconds: float = 60.0
    # Coarse to fine: (fraction of the plan, downscale factor) from which that resolution is used.
    resolution_schedule: tuple[tuple[float, int], ...] = ((0.0, 1),)
    # Stop on a plateau of the training loss: once the plan is past ``plateau_after`` (full resolution,
    # densification over), stop when the mean loss of the last ``plateau_window`` iterations fell by
    # less than ``plateau_tolerance`` (relative) against the window before. 0 windows: never.
    plateau_window: int = 0
    plateau_tolerance: float = 0.002
    plateau_after: float = 0.6
    ssim_weight: float = 0.2  # loss = (1 - w) L1 + w (1 - SSIM), as 3DGS
    lr_means: float = 1.6e-4  # times the scene scale, decaying log-linearly to lr_means_final
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 5e-2
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    sh_degree: int = 3
    sh_band_every: int = 250  # switch on one more SH band every this many iterations
    densify: DensifyOptions | None = field(default_factory=DensifyOptions)
    max_gaussians: int = 100_000
    refine_poses: bool = False  # every training view's pose but the first's (``optimize(pose_views=...)``: some)
    lr_pose_rotation: float = 1e-4  # radians per step (the first training view stays fixed: gauge)
    lr_pose_translation: float = 1e-4  # times the scene scale
    # Bounds on each view's total correction: a camera further off than a few degrees is the evidence's
    # job (sfm.evidence), not the photometric loss's, which a wrong start drags into a wrong minimum.
    max_pose_rotation_deg: float = 5.0
    max_pose_translation: float = 0.05  # times the scene scale
    # The model's depth as a prior: loss += depth_weight * mean |rendered depth / prior depth - 1| over the
    # pixels where both are known (``optimize(depths=...)``; the splat stage passes them for few views).
    depth_weight: float = 0.2
    appearance: bool = True  # per-training-image affine colour transform (exposure, white balance)
    lr_appearance: float = 1e-3  # Adam rate of the colour transforms' entries (brief keeps it)
    appearance_weight: float = 1e-3  # pull of each transform towards [I | 0]
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    raster: RasterOptions = field(default_factory=RasterOptions)
    device: str = "cpu"  # "cuda" renders with gsplat (ffrecon.splat.render_gsplat)
    threads: int | None = None  # torch CPU threads while optimising; None: see cpu_threads()
    seed: int = 0
    progress: bool = True

    def __post_init__(self) -> None:
        check_number("OptimizeOptions.max_seconds", self.max_seconds, low=0, low_open=True, flag="--splat-seconds")
        check_number("OptimizeOptions.iterations", self.iterations, low=1, integer=True)
        for name in ("plateau_window", "sh_band_every"):
            check_number(f"OptimizeOptions.{name}", getattr(self, name), low=0, integer=True)
        check_number("OptimizeOptions.sh_degree", self.sh_degree, low=0, high=3, integer=True)
        check_number("OptimizeOptions.max_gaussians", self.max_gaussians, low=1, integer=True)
        check_number("OptimizeOptions.threads", self.threads, low=1, integer=True, allow_none=True)
        rates = [f.name for f in fields(self) if f.name.startswith("lr_")]  # 0 keeps that tensor as it is
        bounds = ("max_pose_rotation_deg", "max_pose_translation", "depth_weight")
        for name in (*rates, *bounds, "plateau_tolerance", "appearance_weight"):
            check_number(f"OptimizeOptions.{name}", getattr(self, name), low=0)
        for name in ("plateau_after", "ssim_weight"):
            check_number(f"OptimizeOptions.{name}", getattr(self, name), low=0, high=1)
        for start, factor in self.resolution_schedule:
            check_number("OptimizeOptions.resolution_schedule start", start, low=0, high=1)
            check_number("OptimizeOptions.resolution_schedule factor", factor, low=1, integer=True)
        if len(self.background) != 3:
            raise InputError(
                f"OptimizeOptions.background {self.background} is not an RGB triple",
                "set OptimizeOptions.background to (r, g, b), each in [0, 1]",
            )
        for value in self.background:
            check_number("OptimizeOptions.background", value, low=0, high=1)

    @staticmethod
    def brief(**overrides) -> OptimizeOptions:
        """Rates and schedule for runs of a few hundred to a thousand iterations: the 3DGS rates with
        positions and scales x10, SH x3, rotations x3 and opacity x2 (the final position rate stays
        3DGS's); a plan of 1500 iterations compressed into ``max_seconds``, trained at 1/4 resolution for
        the first 10 % of it, 1/2 until 30 %, full resolution after; one more SH band every 150
        iterations; stop early on a plateau of the training loss.

        Measured on a 24-view 640x480 scene like the demo's (``tools/bench_splat.py --optimize-only
        --width 640 --height 480 --seconds S``, 2 cores shared with other work): held-out PSNR 23.8 dB
        at S = 20, 25.3 at 30, 27.9-28.4 at 60, 32.3 at 150.

        Measured on the demo scene (60k Gaussians, 300 iterations, no densification): held-out
        PSNR 22.6 dB with only positions x10, 26.2 dB with this preset (26.7 dB with densification).

        Pose corrections at 5e-3 (rotation in radians, translation times the scene scale) per step, 50x
        3DGS-era rates: a few hundred steps must move a camera by the model's 2-3 deg. On the wide-baseline
        scene (tools/bench_sparse_splat.py, 20 s, 8 views) 3e-3 moved the cameras 0.3-1.0 deg and 1e-2 up
        to 3.8 deg (overshooting); the bounds (max_pose_*) cap the total either way.
        """
        base = OptimizeOptions()
        schedule = {
            "iterations": 1500,
            "resolution_schedule": ((0.0, 4), (0.1, 2), (0.3, 1)),
            "sh_band_every": 150,
            "plateau_window": 100,
        }
        rates = {
            "lr_means": base.lr_means * 10,
            "lr_scales": base.lr_scales * 10,
            "lr_sh_dc": base.lr_sh_dc * 3,
            "lr_sh_rest": base.lr_sh_rest * 3,
            "lr_quats": base.lr_quats * 3,
            "lr_opacity": base.lr_opacity * 2,
            "lr_pose_rotation": 5e-3,
            "lr_pose_translation": 5e-3,
        }
        return replace(base, **{**schedule, **rates, **overrides})


@dataclass(frozen=True)
class OptimizeResult:
    gaussians: Gaussians  # detached
    cam_from_world: np.ndarray  # [N, 3, 4] float64, refined where refine_poses (else the input)
    color_transforms: np.ndarray  # [N, 3, 4] float64 [A | b] per view: learnt where appearance, else [I | 0]
    iterations: int
    seconds: float  # optimisation time, callbacks excluded
    history: tuple[tuple[int, float, float], ...]  # (iteration, seconds, loss) every 10 iterations
    stop_reason: str = ""  # "plateau", "iterations" or "time budget"
    pose_views: tuple[int, ...] = ()  # the views whose poses were optimised


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


@dataclass(frozen=True)
class _TrainingViews:
    """What every iteration reads and never changes: the views on the optimisation device."""

    images: list[torch.Tensor]  # per view [H_i, W_i, 3] RGB as given: uint8, or float in [0, 1] (see unit_float)
    poses: torch.Tensor  # [N, 3, 4] float32 cam_from_world, as given
    k_mats: torch.Tensor  # [N, 3, 3] float32
    background: torch.Tensor  # [3] float32
    cam_from_world: np.ndarray  # [N, 3, 4] float64, as given
    train: list[int]
    render: Callable  # ffrecon's CPU renderer, or gsplat's on CUDA (same signature)
    # Per downscale factor of the resolution schedule (1 included): the images and their intrinsics.
    levels: dict[int, tuple[list[torch.Tensor], torch.Tensor]] = field(default_factory=dict)
    scale: float = 1.0  # the scene scale (pose translation bounds)
    pose_views: tuple[int, ...] = ()  # views whose poses carry a correction
    # Per downscale factor: per view the depth prior at that level's image size (None: no prior).
    depth_levels: dict[int, list[torch.Tensor | None]] = field(default_factory=dict)


def _training_views(
    images, cam_from_world, Ks, train: list[int], options: OptimizeOptions, pose_views=None, depths=None, scale=1.0
) -> _TrainingViews:
    dev = torch.device(options.device)
    render_fn = render
    if dev.type == "cuda":
        from ffrecon.splat.render_gsplat import render_gsplat as render_fn
    images = [im.to(dev) for im in images]
    k_mats = torch.as_tensor(np.asarray(Ks, np.float32), device=dev)
    factors = {factor for _, factor in options.resolution_schedule} | {1}
    levels = {f: downscaled(images, k_mats, f, train) for f in sorted(factors)}
    return _TrainingViews(
        images=images,
        poses=torch.as_tensor(np.asarray(cam_from_world, np.float32), device=dev),
        k_mats=k_mats,
        background=torch.tensor(options.background, dtype=torch.float32, device=dev),
        cam_from_world=np.asarray(cam_from_world, np.float64),
        train=train,
        render=render_fn,
        levels=levels,
        scale=float(scale),
        pose_views=pose_views_of(train, pose_views, options.refine_poses),
        depth_levels=depth_levels(depths, levels, dev) if options.depth_weight > 0 else {},
    )


def unit_float(image: torch.Tensor) -> torch.Tensor:
    """A view as float32 in [0, 1]: uint8 ones divided by 255, float ones as they are.

    The views are kept as they come (uint8 photos: a quarter of float32's memory; 500 frames of 640x480
    held 1.8 GB as float32) and each step converts the one it reads.
    """
    return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()


def downscaled(
    images: list[torch.Tensor], k_mats: torch.Tensor, factor: int, views: Sequence[int]
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """``views`` of ``images`` (``[H, W, 3]``) area-averaged by ``factor`` and their intrinsics
    ``[N, 3, 3]``; the other views are left as they are.

    Under COLMAP's pixel-centre rule image coordinates scale linearly (the top-left corner is at 0), so
    ``fx, cx`` are multiplied by ``new_width / width`` and ``fy, cy`` by ``new_height / height``.
    """
    if factor == 1:
        return images, k_mats
    out, ks = list(images), k_mats.clone()
    for i in views:
        h, w = images[i].shape[:2]
        size = (max(1, round(h / factor)), max(1, round(w / factor)))
        small = F.interpolate(unit_float(images[i]).permute(2, 0, 1)[None], size=size, mode="area")[0]
        out[i] = small.permute(1, 2, 0).to(torch.float16)  # (half the memory; a step reads it through unit_float)
        ks[i, 0] *= size[1] / w
        ks[i, 1] *= size[0] / h
    return out, ks


def resolution_factor(options: OptimizeOptions, fraction: float) -> int:
    """The downscale factor of the resolution schedule at ``fraction`` of the plan."""
    factor = 1
    for start, f in options.resolution_schedule:
        if fraction >= start:
            factor = f
    return factor


def _trainable(
    gaussians: Gaussians, options: OptimizeOptions, scale: float, num_views: int, refine_poses: bool
) -> tuple[dict[str, torch.Tensor], torch.optim.Adam]:
    """Leaf tensors by name and their Adam, one param group (and learning rate) per name.

    The SH coefficients are split into ``sh_dc [N, 1, 3]`` and ``sh_rest [N, B - 1, 3]``, which
    3DGS trains at different rates. With ``refine_poses`` (some view's pose optimised), ``pose_rotation``
    and ``pose_translation`` (``[num_views, 3]``, zero) hold a correction per view (see :func:`refined_pose`). With
    ``appearance``, ``color_deltas`` (``[num_views, 3, 4]``, zero) holds a colour transform per view
    (see :func:`_color_transform`). A tensor whose rate is 0 stays exactly as it is: Adam's update is then
    ``-0 * m / (sqrt(v) + eps)``.
    """
    o = options
    dev = torch.device(o.device)
    g = gaussians.with_sh_degree(o.sh_degree)
    params = {k: getattr(g, k).to(dev).clone().requires_grad_(True) for k in Gaussians.PARAMS}
    params["sh_dc"] = params["sh"][:, :1].detach().clone().requires_grad_(True)
    params["sh_rest"] = params.pop("sh")[:, 1:].detach().clone().requires_grad_(True)
    lrs = {
        "means": o.lr_means * scale,
        "quats_wxyz": o.lr_quats,
        "log_scales": o.lr_scales,
        "opacity_logits": o.lr_opacity,
        "sh_dc": o.lr_sh_dc,
        "sh_rest": o.lr_sh_rest,
    }
    if refine_poses:
        params["pose_rotation"] = torch.zeros(num_views, 3, device=dev, requires_grad=True)
        params["pose_translation"] = torch.zeros(num_views, 3, device=dev, requires_grad=True)
        lrs.update(pose_rotation=o.lr_pose_rotation, pose_translation=o.lr_pose_translation * scale)
    if o.appearance:
        params["color_deltas"] = torch.zeros(num_views, 3, 4, device=dev, requires_grad=True)
        lrs["color_deltas"] = o.lr_appearance
    groups = [{"params": [params[name]], "lr": lr, "name": name} for name, lr in lrs.items()]
    # fused: one multi-threaded pass over every tensor; torch's default on the CPU is a per-tensor loop of
    # separate operations, 15 ms a step for 88k Gaussians on 2 cores against 1.5 ms fused (about a tenth
    # of a training step at 640x480). Same update rule, float rounding aside.
    return params, torch.optim.Adam(groups, betas=(0.9, 0.999), eps=1e-15, fused=True)


def _set_lr(optimizer: torch.optim.Optimizer, name: str, lr: float) -> None:
    for group in optimizer.param_groups:
        if group["name"] == name:
            group["lr"] = lr


def _as_gaussians(params: dict[str, torch.Tensor]) -> Gaussians:
    """The Gaussians the trainable tensors describe (SH bands joined again; shares their storage)."""
    return Gaussians(
        params["means"],
        params["quats_wxyz"],
        params["log_scales"],
        params["opacity_logits"],
        torch.cat([params["sh_dc"], params["sh_rest"]], dim=1),
    )


def _view_pose(params: dict[str, torch.Tensor], views: _TrainingViews, view: int) -> torch.Tensor:
    """``[3, 4]`` cam_from_world of ``view`` with its correction (only the views in ``views.pose_views`` have one)."""
    pose = views.poses[view]
    if "pose_rotation" in params and view in views.pose_views:
        pose = refined_pose(pose, params["pose_rotation"][view], params["pose_translation"][view])
    return pose


def _color_transform(params: dict[str, torch.Tensor], views: _TrainingViews, view: int) -> torch.Tensor:
    """``[3, 4]`` ``[A | b]`` of training ``view``: ``[I | 0] + d_view - mean_train(d)`` of the deltas
    ``d = params["color_deltas"]``, so that the training views' transforms average ``[I | 0]`` (gauge)."""
    deltas = params["color_deltas"]
    eye = torch.eye(3, 4, dtype=deltas.dtype, device=deltas.device)
    return eye + deltas[view] - deltas[views.train].mean(dim=0)


def _current_color_transforms(params: dict[str, torch.Tensor], views: _TrainingViews) -> np.ndarray:
    """``[N, 3, 4]`` float64: the training views' colour transforms; ``[I | 0]`` for the others and
    without ``appearance``."""
    out = identity_transforms(len(views.poses), dtype=torch.float64).numpy()
    if "color_deltas" in params:
        with torch.no_grad():
            for i in views.train:
                out[i] = _color_transform(params, views, i).cpu().double().numpy()
    return out


def _current_poses(params: dict[str, torch.Tensor], views: _TrainingViews) -> np.ndarray:
    """``[N, 3, 4]`` float64: the input poses with the training views' corrections applied."""
    if "pose_rotation" not in params:
        return views.cam_from_world
    with torch.no_grad():
        out = views.cam_from_world.copy()
        for i in views.pose_views:
            out[i] = _view_pose(params, views, i).cpu().numpy()
        return out


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


def _densify(
    densifier: Densifier, params: dict[str, torch.Tensor], optimizer: torch.optim.Optimizer
) -> dict[str, torch.Tensor]:
    """Clone, split and prune; returns the new tensors (already swapped into ``optimizer``).

    Only the per-Gaussian tensors change; the per-view ones (pose corrections, colour transforms)
    are returned as they are and keep their optimiser state."""
    new, keep, num_new = densifier.step(_as_gaussians(params))
    resized = {
        k: getattr(new, k).detach().clone().requires_grad_(True)
        for k in ("means", "quats_wxyz", "log_scales", "opacity_logits")
    }
    resized["sh_dc"] = new.sh[:, :1].detach().clone().requires_grad_(True)
    resized["sh_rest"] = new.sh[:, 1:].detach().clone().requires_grad_(True)
    replace_rows(optimizer, resized, keep, num_new)
    return {**params, **resized}


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
