"""The 3DGS densify-and-prune policy, and the optimiser-state surgery that goes with it.

:class:`Densifier` decides which Gaussians to clone, split and prune; :func:`replace_rows` then
swaps the resized tensors into the ``torch.optim.Adam`` that optimises them, keeping the moments of
the surviving rows and starting the new rows from zero.
"""

from __future__ import annotations

import logging
import math

import kornia
import torch

from ffrecon.gaussians import Gaussians
from ffrecon.splat.optimize_options import DensifyOptions  # defined there, without torch; still importable here

logger = logging.getLogger("ffrecon.splat")


def replace_rows(
    optimizer: torch.optim.Optimizer, params: dict[str, torch.Tensor], keep: torch.Tensor, num_new: int
) -> None:
    """Swap resized tensors into ``optimizer`` and carry their Adam moments along.

    Densification replaces each per-Gaussian tensor ``old [N, ...]`` with ``new [keep.sum() + num_new, ...]``
    whose rows are ``old[keep]`` followed by ``num_new`` fresh rows. For every param group whose
    ``"name"`` is a key of ``params``, this puts the new tensor in the group and rebuilds the moment
    buffers the same way: kept rows keep their ``exp_avg`` and ``exp_avg_sq``, fresh rows start at zero.
    The ``step`` count is kept as it is (one per tensor, as ``torch.optim.Adam`` keeps it). Groups whose
    name is not in ``params`` (the camera corrections) are left alone. The same surgery as gsplat's
    strategy operations, on ``torch.optim.Adam`` state.

    Args:
        optimizer: built with one param group per named tensor, each with a ``"name"`` key.
        params: name -> new leaf tensor (requires grad).
        keep: ``[N]`` bool mask of the old rows that survive, in order.
        num_new: rows appended after the kept ones.

    >>> old = torch.ones(3, 2, requires_grad=True)
    >>> adam = torch.optim.Adam([{"params": [old], "lr": 0.1, "name": "means"}])
    >>> old.grad = torch.ones(3, 2)
    >>> adam.step()
    >>> new = torch.zeros(4, 2, requires_grad=True)
    >>> replace_rows(adam, {"means": new}, torch.tensor([True, False, True]), num_new=2)
    >>> adam.state[new]["exp_avg"][:, 0]
    tensor([0.1000, 0.1000, 0.0000, 0.0000])
    >>> int(adam.state[new]["step"])
    1
    """
    kept = int(keep.sum())
    for group in optimizer.param_groups:
        name = group.get("name")
        if name not in params:
            continue
        old, new = group["params"][0], params[name]
        if len(new) != kept + num_new or new.shape[1:] != old.shape[1:]:
            raise ValueError(
                f"replace_rows: {name} has shape {tuple(new.shape)}, expected {kept} kept + {num_new} new rows "
                f"of shape {tuple(old.shape[1:])}"
            )
        state = optimizer.state.pop(old, {})
        for key in ("exp_avg", "exp_avg_sq"):
            if key in state:
                rows = state[key][keep]
                state[key] = torch.cat([rows, rows.new_zeros((num_new, *rows.shape[1:]))])
        group["params"] = [new]
        if state:
            optimizer.state[new] = state


class Densifier:
    """Accumulates view-space gradients and clones, splits and prunes every ``every`` iterations."""

    def __init__(
        self, num: int, options: DensifyOptions, scene_scale: float, max_gaussians: int, seed: int, device: str = "cpu"
    ) -> None:
        self.options = options
        self.scene_scale = scene_scale
        self.max_gaussians = max_gaussians
        self.device = torch.device(device)
        self.grad_sum = torch.zeros(num, device=self.device)
        self.count = torch.zeros(num, device=self.device)
        self.generator = torch.Generator().manual_seed(seed)
        self.rounds = 0

    def accumulate(self, means2d_grad: torch.Tensor, visible: torch.Tensor, width: int, height: int) -> None:
        """Add one view's ``[N, 2]`` pixel-space gradient norms (converted to NDC units) for visible Gaussians."""
        g = means2d_grad.detach().reshape(-1, 2) * torch.tensor([width / 2.0, height / 2.0], device=means2d_grad.device)
        self.grad_sum[visible] += g[visible].norm(dim=1)
        self.count[visible] += 1

    def due(self, iteration: int, fraction: float) -> bool:
        o = self.options
        return iteration >= o.start_iteration and iteration % o.every == 0 and fraction < o.stop_fraction

    @torch.no_grad()
    def step(self, g: Gaussians) -> tuple[Gaussians, torch.Tensor, int]:
        """Densify and prune. Returns ``(new Gaussians, keep [N_old] bool, number of appended rows)``."""
        o = self.options
        n = len(g)
        mean_grad = self.grad_sum / self.count.clamp_min(1)
        big = torch.exp(g.log_scales).amax(1) > o.percent_dense * self.scene_scale
        hot = mean_grad >= o.grad_threshold
        room = max(0, self.max_gaussians - n)
        candidates = torch.nonzero(hot).squeeze(1)
        # A split adds one Gaussian net, a clone one: cap the additions at the room left.
        if len(candidates) > room:
            candidates = candidates[torch.argsort(mean_grad[candidates], descending=True)[:room]]
        clone = candidates[~big[candidates]]
        split = candidates[big[candidates]]
        new_rows = [getattr(g, k)[clone] for k in Gaussians.PARAMS]
        if len(split):
            # Two samples from each Gaussian (local axes scaled, then rotated), each 1.6x smaller.
            scale = torch.exp(g.log_scales[split])
            r = kornia.geometry.conversions.quaternion_to_rotation_matrix(
                torch.nn.functional.normalize(g.quats_wxyz[split], dim=1)
            )
            samples = []
            for _ in range(2):
                local = torch.randn(len(split), 3, generator=self.generator).to(scale.device) * scale
                samples.append(g.means[split] + (r @ local[:, :, None])[:, :, 0])
            split_rows = [
                torch.cat(samples),
                g.quats_wxyz[split].repeat(2, 1),
                (g.log_scales[split] - math.log(1.6)).repeat(2, 1),
                g.opacity_logits[split].repeat(2),
                g.sh[split].repeat(2, 1, 1),
            ]
            new_rows = [torch.cat([a, b]) for a, b in zip(new_rows, split_rows)]
        keep = torch.ones(n, dtype=torch.bool, device=g.means.device)
        keep[split] = False
        keep &= torch.sigmoid(g.opacity_logits) >= o.prune_opacity
        if self.rounds > 0:
            keep &= torch.exp(g.log_scales).amax(1) <= o.max_world_size * self.scene_scale
        num_new = len(new_rows[0])
        out = Gaussians(*[torch.cat([getattr(g, k).detach()[keep], r]) for k, r in zip(Gaussians.PARAMS, new_rows)])
        logger.debug(
            "densify: %d cloned, %d split, %d pruned -> %d",
            len(clone),
            len(split),
            int((~keep).sum()) - len(split),
            len(out),
        )
        self.grad_sum = torch.zeros(len(out), device=self.device)
        self.count = torch.zeros(len(out), device=self.device)
        self.rounds += 1
        return out, keep, num_new
