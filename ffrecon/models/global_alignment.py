"""DUSt3R-style global alignment: one pose, focal and depth map per view from pairwise point maps.

Each pair ``(i, j)`` gives view i's points and view j's points, both in view i's camera frame and
in a scale of the pair's own. The unknowns are, per view, a ``world_from_cam`` rigid pose, one
focal length (principal point at the image centre, COLMAP pixel-centre rule) and a depth map; per
pair, a similarity ``world_from_pair`` placing the pair's frame (view i's camera) in the world.

1. Initialisation: a maximum spanning tree over the views, each edge weighted by the mean
   confidences of its best pair, is walked from view 0; every new view's points are brought into
   the world with a confidence-weighted Umeyama fit on the view already placed. Poses come from
   fitting each view's own-frame points to its world points, focals from pixel rays vs points
   (:mod:`ffrecon.models.alignment_init`).
2. Refinement: Adam on the confidence-weighted 3D alignment loss
   ``sum_pairs sum_{v in (i, j)} w * || world point of v from (pose, focal, depth) - world_from_pair * pair point ||``
   with a fixed gauge: view 0's pose is the identity and the mean log pair scale keeps its initial
   value (so the world is view 0's camera frame, in the scale of the pairs).

Everything here works on plain arrays; no ONNX. The optimisation is deterministic (no random step).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from ffrecon.checks import require_finite
from ffrecon.errors import FFReconError, ModelError
from ffrecon.geometry.poses import invert_pose
from ffrecon.geometry.projection import pixel_centers

# AlignmentOptions and PairPrediction live beside the initialisation (no torch there); still importable from here
from ffrecon.models.alignment_init import AlignmentOptions, PairPrediction, _Init, _weights, initialise

MODEL_FIX = (
    "the pairs come from the feed-forward model: check it on two photos with `ffrecon inspect-model` and re-export "
    "it in fp32 (fp16 overflow is a common cause)"
)

log = logging.getLogger("ffrecon.models.global_alignment")


@dataclass(frozen=True)
class AlignmentResult:
    """Globally aligned views in network pixels; world = view 0's camera frame.

    ``cam_from_world``: ``[N, 3, 4]`` float64, OpenCV; ``focal``: ``[N]`` float64 pixels (principal
    point at ``(W/2, H/2)``); ``depth``: ``[N, H, W]`` float32 z-depth; ``conf``: ``[N, H, W]``
    float32, the best confidence any pair gave the pixel. ``loss`` is the weighted mean distance
    of the returned iterate (``initial_loss`` after initialisation), in the units of ``depth``.
    """

    cam_from_world: np.ndarray
    focal: np.ndarray
    depth: np.ndarray
    conf: np.ndarray
    size_hw: tuple[int, int]
    loss: float
    initial_loss: float
    iterations: int  # Adam steps taken
    best_iteration: int  # the step whose parameters are returned (0: the initialisation)
    initial_cam_from_world: np.ndarray  # [N, 3, 4], after the spanning-tree initialisation
    initial_focal: np.ndarray  # [N]

    def K(self, i: int) -> np.ndarray:
        """``[3, 3]`` intrinsics of view i in network pixels."""
        h, w = self.size_hw
        return np.array([[self.focal[i], 0.0, w / 2], [0.0, self.focal[i], h / 2], [0.0, 0.0, 1.0]])


def _check_pairs(pairs: Sequence[PairPrediction], size_hw: tuple[int, int]) -> int:
    if not pairs:
        raise FFReconError(
            "global alignment needs at least one pair", "pass the pairs of a pair graph over two or more views"
        )
    h, w = size_hw
    for p in pairs:
        shapes = (p.pts_i_in_i.shape, p.conf_i.shape, p.pts_j_in_i.shape, p.conf_j.shape)
        if shapes != ((h, w, 3), (h, w), (h, w, 3), (h, w)):
            raise FFReconError(
                f"pair ({p.i}, {p.j}) has shapes {shapes}; expected points [{h}, {w}, 3] and confidences [{h}, {w}]",
                "pass pairs predicted at image_size_hw",
            )
        require_finite(
            f"global alignment, pair ({p.i}, {p.j})",
            pts3d=p.pts_i_in_i,
            conf=p.conf_i,
            pts3d_in_other_view=p.pts_j_in_i,
            conf_in_other_view=p.conf_j,
            fix=MODEL_FIX,
        )
        if p.i == p.j or min(p.i, p.j) < 0:
            raise FFReconError(
                f"pair ({p.i}, {p.j}) is not a pair of two views", "use make_pairs to build the pair graph"
            )
    num_views = max(max(p.i, p.j) for p in pairs) + 1
    seen = {p.i for p in pairs} | {p.j for p in pairs}
    if len(seen) != num_views:
        raise FFReconError(
            f"views {sorted(set(range(num_views)) - seen)} are in no pair",
            "every view 0..N-1 must be in at least one pair",
        )
    return num_views


def global_align(
    pairs: Sequence[PairPrediction], image_size_hw: tuple[int, int], options: AlignmentOptions = AlignmentOptions()
) -> AlignmentResult:
    """One pose, focal and depth map per view from all pairs (spanning-tree init, then Adam).

    Args:
        pairs: pairwise predictions over views ``0..N-1`` at network size ``image_size_hw``.
        image_size_hw: ``(H, W)`` of the point maps.
    Returns:
        :class:`AlignmentResult`; world = view 0's camera frame, lengths in the pairs' scale.
    """
    size_hw = (int(image_size_hw[0]), int(image_size_hw[1]))
    num_views = _check_pairs(pairs, size_hw)
    init = initialise(pairs, num_views, size_hw, options.confidence_weight)
    unit = float(np.median(init.depth[init.depth > 0])) if (init.depth > 0).any() else 1.0
    problem = _Problem(pairs, init, size_hw, unit, options)
    with torch.no_grad():
        initial_loss = problem.loss().item() * unit
    initial_cam_from_world, initial_focal = problem.export()[:2]
    best_loss, best_step = _optimise(problem, options)
    cam_from_world, focal, depth = problem.export()
    final_loss = best_loss * unit
    log.info(
        "global alignment of %d views, %d pairs: loss %.4g -> %.4g (best at step %d of %d)",
        num_views,
        len(pairs),
        initial_loss,
        final_loss,
        best_step,
        options.iterations,
    )
    return AlignmentResult(
        cam_from_world,
        focal,
        depth,
        _best_confidence(pairs, num_views, size_hw),
        size_hw,
        final_loss,
        initial_loss,
        options.iterations,
        best_step,
        initial_cam_from_world,
        initial_focal,
    )


def _optimise(problem: _Problem, options: AlignmentOptions) -> tuple[float, int]:
    """Adam on ``problem.loss()`` with a cosine learning-rate schedule; leaves ``problem`` at the kept iterate.

    Returns ``(loss, step)`` of the kept iterate, the loss in normalised units.
    """
    optimiser = torch.optim.Adam(problem.parameters(), lr=options.lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
        optimiser, T_max=max(options.iterations, 1), eta_min=options.lr_min
    )
    # Adam takes steps of about lr whatever the gradient's size, so from a very good start it can
    # wander along weak directions (near-planar views): by default keep the lowest-loss iterate.
    best_loss, best_step, best_state = math.inf, 0, None
    for step in range(options.iterations + 1):
        optimiser.zero_grad()
        loss = problem.loss()
        if not math.isfinite(loss.item()):
            log.warning("global alignment: non-finite loss at step %d, keeping step %d", step, best_step)
            break
        if loss.item() < best_loss or not options.keep_best:
            best_loss, best_step = loss.item(), step
            best_state = {k: v.detach().clone() for k, v in problem.named_parameters()}
        if step == options.iterations:
            break
        loss.backward()
        optimiser.step()
        schedule.step()
        if step % 100 == 0:
            log.debug("global alignment step %d: loss %.6g", step, loss.item() * problem.unit)
    if best_state is None:
        raise ModelError(
            "global alignment failed: the initial alignment of the pairs is not finite",
            "check the pairwise model's outputs (they must be finite point maps with z > 0)",
        )
    with torch.no_grad():
        for name, value in problem.named_parameters():
            value.copy_(best_state[name])
    return best_loss, best_step


def _best_confidence(pairs: Sequence[PairPrediction], num_views: int, size_hw: tuple[int, int]) -> np.ndarray:
    """``[N, H, W]`` float32: the best confidence any pair gave each pixel of each view."""
    conf = np.zeros((num_views, *size_hw), np.float32)
    for p in pairs:
        conf[p.i] = np.maximum(conf[p.i], p.conf_i)
        conf[p.j] = np.maximum(conf[p.j], p.conf_j)
    return conf


class _Problem(torch.nn.Module):
    """The unknowns and the alignment loss, in lengths divided by ``unit`` (median initial depth)."""

    def __init__(
        self,
        pairs: Sequence[PairPrediction],
        init: _Init,
        size_hw: tuple[int, int],
        unit: float,
        options: AlignmentOptions,
    ) -> None:
        super().__init__()
        f32 = torch.float32
        n, e = len(init.focal), len(pairs)
        self.size_hw, self.unit, self.options = size_hw, unit, options
        self.register_buffer("rot0", torch.tensor(init.world_from_cam[:, :, :3], dtype=f32))
        self.register_buffer("free", (torch.arange(n) > 0).to(f32)[:, None])  # view 0 is the gauge
        self.rot_delta = torch.nn.Parameter(torch.zeros(n, 3))
        self.trans = torch.nn.Parameter(torch.tensor(init.world_from_cam[:, :, 3] / unit, dtype=f32))
        self.log_focal = torch.nn.Parameter(
            torch.tensor(np.log(init.focal), dtype=f32), requires_grad=options.optimize_focal
        )
        log_depth = torch.tensor(np.log(np.maximum(init.depth / unit, 1e-4)), dtype=f32)[:, None]
        k = options.depth_downsample
        if k > 1:
            log_depth = F.adaptive_avg_pool2d(log_depth, (math.ceil(size_hw[0] / k), math.ceil(size_hw[1] / k)))
        self.log_depth = torch.nn.Parameter(log_depth)
        h, w = size_hw  # pixel-centre offsets from the principal point (W/2, H/2)
        self.register_buffer("ray_xy", torch.tensor(pixel_centers(h, w) - np.array([w / 2, h / 2]), dtype=f32))
        # Pairs: the similarity world_from_pair, and the stacked point maps and weights.
        self.register_buffer("pair_rot0", torch.tensor(np.stack([s.rotation for s in init.world_from_pair]), dtype=f32))
        self.pair_rot_delta = torch.nn.Parameter(torch.zeros(e, 3))
        self.pair_trans = torch.nn.Parameter(
            torch.tensor(np.stack([s.translation for s in init.world_from_pair]) / unit, dtype=f32)
        )
        self.register_buffer(
            "pair_log_scale0", torch.tensor([math.log(s.scale / unit) for s in init.world_from_pair], dtype=f32)
        )
        self.pair_log_scale_delta = torch.nn.Parameter(torch.zeros(e))
        self.register_buffer("idx_i", torch.tensor([p.i for p in pairs]))
        self.register_buffer("idx_j", torch.tensor([p.j for p in pairs]))
        self.register_buffer("pts_i", torch.tensor(np.stack([p.pts_i_in_i for p in pairs]), dtype=f32))
        self.register_buffer("pts_j", torch.tensor(np.stack([p.pts_j_in_i for p in pairs]), dtype=f32))
        self.register_buffer(
            "w_i", torch.tensor(np.stack([_weights(p.conf_i, options.confidence_weight) for p in pairs]))
        )
        self.register_buffer(
            "w_j", torch.tensor(np.stack([_weights(p.conf_j, options.confidence_weight) for p in pairs]))
        )

    def depth(self) -> torch.Tensor:
        """``[N, H, W]`` depth, normalised units."""
        log_depth = self.log_depth
        if self.options.depth_downsample > 1:
            log_depth = F.interpolate(log_depth, size=self.size_hw, mode="bilinear", align_corners=False)
        return log_depth[:, 0].exp()

    def world_from_cam(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``([N, 3, 3] rotation, [N, 3] translation)``; view 0 stays at its initial pose."""
        rot = self.rot0 @ axis_angle_to_rotation_matrix(self.rot_delta * self.free)
        return rot, self.trans * self.free + self.trans.detach() * (1 - self.free)

    def world_points(self) -> torch.Tensor:
        """``[N, H, W, 3]`` world points of every view from pose, focal and depth."""
        depth = self.depth()
        focal = self.log_focal.exp()[:, None, None, None]
        xy = self.ray_xy[None] / focal * depth[..., None]
        pts_cam = torch.cat([xy, depth[..., None]], dim=-1)
        rot, trans = self.world_from_cam()
        return torch.einsum("nij,nhwj->nhwi", rot, pts_cam) + trans[:, None, None, :]

    def loss(self) -> torch.Tensor:
        world = self.world_points()
        rot = self.pair_rot0 @ axis_angle_to_rotation_matrix(self.pair_rot_delta)
        log_scale = self.pair_log_scale0 + self.pair_log_scale_delta - self.pair_log_scale_delta.mean()
        scaled_rot = log_scale.exp()[:, None, None] * rot
        total = torch.zeros(())
        for pts, weight, idx in ((self.pts_i, self.w_i, self.idx_i), (self.pts_j, self.w_j, self.idx_j)):
            aligned = torch.einsum("eij,ehwj->ehwi", scaled_rot, pts) + self.pair_trans[:, None, None, :]
            total = total + (weight * (world[idx] - aligned).norm(dim=-1)).sum()
        return total / (2 * self.w_i.numel())

    @torch.no_grad()
    def export(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(cam_from_world [N, 3, 4] float64, focal [N] float64, depth [N, H, W] float32)`` in pair units."""
        rot, trans = self.world_from_cam()
        world_from_cam = np.concatenate([rot.double().numpy(), trans.double().numpy()[:, :, None] * self.unit], axis=2)
        # Re-orthonormalise (float32 products drift by ~1e-7).
        u, _, vt = np.linalg.svd(world_from_cam[:, :, :3])
        world_from_cam[:, :, :3] = u @ vt
        depth = (self.depth() * self.unit).numpy().astype(np.float32)
        return invert_pose(world_from_cam), self.log_focal.exp().double().numpy(), depth
