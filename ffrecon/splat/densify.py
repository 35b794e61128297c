"""A small Adam and the 3DGS densify-and-prune policy, with their state kept explicit.

The optimiser is written here (a dozen lines) rather than taken from ``torch.optim`` so that
densification can grow and shrink its moment buffers along with the Gaussians without reaching
into private optimiser state.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import kornia
import torch

from ffrecon.splat.gaussians import Gaussians

logger = logging.getLogger("ffrecon.splat")


class Adam:
    """Adam over named tensors, each with its own learning rate (changed between steps)."""

    def __init__(
        self,
        params: dict[str, torch.Tensor],
        lrs: dict[str, float],
        *,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-15,
    ) -> None:
        self.params = params
        self.lrs = dict(lrs)
        self.betas, self.eps = betas, eps
        self.m = {k: torch.zeros_like(v) for k, v in params.items()}
        self.v = {k: torch.zeros_like(v) for k, v in params.items()}
        self.steps = {k: 0 for k in params}

    @torch.no_grad()
    def step(self) -> None:
        b1, b2 = self.betas
        for k, p in self.params.items():
            if p.grad is None or self.lrs[k] == 0.0:
                continue
            self.steps[k] += 1
            self.m[k].lerp_(p.grad, 1 - b1)
            self.v[k].mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
            t = self.steps[k]
            step_size = self.lrs[k] / (1 - b1**t)
            denom = (self.v[k] / (1 - b2**t)).sqrt_().add_(self.eps)
            p.addcdiv_(self.m[k], denom, value=-step_size)

    def zero_grad(self) -> None:
        for p in self.params.values():
            p.grad = None

    def rebuild(self, params: dict[str, torch.Tensor], keep: torch.Tensor, num_new: int) -> None:
        """Switch to new tensors whose rows are ``old[keep]`` followed by ``num_new`` fresh rows."""
        for k, p in params.items():
            if k not in self.params or p.shape[1:] != self.params[k].shape[1:] or k.startswith("pose"):
                continue
            for buf in (self.m, self.v):
                old = buf[k][keep]
                buf[k] = torch.cat([old, old.new_zeros((num_new,) + tuple(old.shape[1:]))])
        self.params = params


@dataclass(frozen=True, kw_only=True)
class DensifyOptions:
    start_iteration: int = 100  # first densification (3DGS: 500 of 30k; brief runs start earlier)
    every: int = 100
    stop_fraction: float = 0.6  # no densification after this fraction of the budget
    grad_threshold: float = 0.0002  # mean view-space gradient norm (NDC units, as 3DGS)
    percent_dense: float = 0.01  # clone if largest scale <= this * scene scale, else split
    prune_opacity: float = 0.005
    max_world_size: float = 0.1  # prune Gaussians larger than this * scene scale (after the first round)


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
