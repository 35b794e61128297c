"""Per-view camera corrections and the depth prior of the splat optimiser (:mod:`ffrecon.splat.optimize`).

A view's pose correction is left-multiplied, ``[exp(r) | t] * cam_from_world``, bounded in size after
every step; the depth prior compares the rendered mean depth with the model's, relative to the latter.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.liegroup import So3


def refined_pose(cam_from_world: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """``[3, 4]``: a left-multiplied correction ``[exp(rotation) | translation] * cam_from_world``."""
    delta = So3.exp(rotation).matrix()
    return torch.cat([delta @ cam_from_world[:, :3], (delta @ cam_from_world[:, 3:]) + translation[:, None]], dim=1)


def pose_views_of(train: list[int], pose_views: Sequence[int] | None, refine_all: bool) -> tuple[int, ...]:
    """The training views whose poses are optimised: ``pose_views``, or with None every one but the first
    when ``refine_all`` (see :func:`ffrecon.splat.optimize.optimize`); one always stays fixed (gauge)."""
    if pose_views is None:
        return tuple(train[1:]) if refine_all else ()
    chosen = [v for v in train if v in set(pose_views)]
    return tuple(chosen[1:] if len(chosen) == len(train) else chosen)


def depth_levels(depths, levels: dict, device) -> dict[int, list[torch.Tensor | None]]:
    """Each view's depth prior resized (nearest: no blending across depth edges) to each level's image size."""
    if depths is None:
        return {}
    out = {}
    for factor, (images, _) in levels.items():
        out[factor] = []
        for image, depth in zip(images, depths):
            if depth is None:
                out[factor].append(None)
                continue
            d = torch.as_tensor(np.nan_to_num(np.asarray(depth, np.float32)), device=device)
            out[factor].append(F.interpolate(d[None, None], size=image.shape[:2], mode="nearest")[0, 0])
    return out


def bound_poses(params: dict[str, torch.Tensor], max_rotation_deg: float, max_translation: float) -> None:
    """Shrink each view's correction (``pose_rotation``, ``pose_translation``) back inside the bounds."""
    if "pose_rotation" not in params:
        return
    limits = (("pose_rotation", math.radians(max_rotation_deg)), ("pose_translation", max_translation))
    with torch.no_grad():
        for name, limit in limits:
            value = params[name]
            norm = value.norm(dim=1, keepdim=True)
            value.mul_(torch.clamp(limit / norm.clamp_min(1e-12), max=1.0))


def depth_loss(out, prior: torch.Tensor) -> torch.Tensor:
    """Mean ``|rendered depth / prior - 1|`` where the prior is known and the render mostly opaque."""
    valid = (prior > 0) & (out.alpha.detach() > 0.5)
    if not bool(valid.any()):
        return out.rgb.new_zeros(())
    depth = out.depth / out.alpha.clamp_min(1e-6)
    return (depth[valid] / prior[valid] - 1).abs().mean()
