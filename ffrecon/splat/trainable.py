"""The splat optimiser's trainable tensors and their Adam (:mod:`ffrecon.splat.optimize`): built from the
seed, read back as Gaussians, poses and colour transforms, and resized by densification with the optimiser
state kept row by row."""

from __future__ import annotations

import numpy as np
import torch

from ffrecon.gaussians import Gaussians
from ffrecon.splat.appearance import identity_transforms
from ffrecon.splat.densify import Densifier, replace_rows
from ffrecon.splat.optimize_options import OptimizeOptions
from ffrecon.splat.poses import refined_pose
from ffrecon.splat.train_views import _TrainingViews


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
