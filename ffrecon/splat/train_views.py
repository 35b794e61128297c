"""What the splat optimiser trains on (:mod:`ffrecon.splat.optimize`): the views on the optimisation device,
at every downscale factor of the resolution schedule, with their intrinsics and depth priors."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from ffrecon.splat.optimize_options import OptimizeOptions
from ffrecon.splat.poses import depth_levels, pose_views_of
from ffrecon.splat.render import render


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
