"""Sim(3) pose-graph optimisation: nodes are similarity transforms, edges measure relative ones.

Chunked feed-forward inference chains chunks by a Sim(3) fitted on their shared frames; each link adds a
small error, so a long path drifts. A loop chunk (frames from both ends of a revisit in one model call)
measures how the chain should close; this spreads the disagreement over every link (each edge's error
weighted alike unless told otherwise).

Written here with torch because pycolmap has no Sim(3) pose-graph solver (its ``PoseGraph`` is the global
mapper's view graph of two-view geometries) and the problem is small, one node per chunk: Gauss-Newton
(with a little Levenberg-Marquardt damping) on autograd's Jacobian with a dense solve, a bounded number of
iterations. Each node moves by ``exp(omega) R``, ``t + tau``, ``exp(sigma) s`` from the current estimate.
An edge's rotation residual is its error rotation's axis times angle, the translation residual is in units
of ``length_scale``, the scale residual is the log.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ffrecon.checks import check_number
from ffrecon.errors import InputError
from ffrecon.geometry.alignment import Sim3

if TYPE_CHECKING:  # torch (0.9 s to import) is imported by the functions that solve: every run loads the options
    import torch


@dataclass(frozen=True, kw_only=True)
class PoseGraphOptions:
    max_iterations: int = 20
    tolerance: float = 1e-10  # stop once the largest parameter step is below this
    damping: float = 1e-6  # Levenberg-Marquardt damping, relative to the normal matrix's diagonal

    def __post_init__(self) -> None:
        check_number("PoseGraphOptions.max_iterations", self.max_iterations, low=1, integer=True)
        check_number("PoseGraphOptions.tolerance", self.tolerance, low=0, low_open=True)
        check_number("PoseGraphOptions.damping", self.damping, low=0)


@dataclass(frozen=True)
class Sim3Edge:
    """A measurement ``b_from_a`` of ``world_from_b^-1 . world_from_a`` between nodes ``a`` and ``b``."""

    a: int
    b: int
    b_from_a: Sim3
    weight: float = 1.0


@dataclass(frozen=True)
class PoseGraphResult:
    world_from_node: tuple[Sim3, ...]  # node 0 is held where it was (the gauge)
    iterations: int
    cost_before: float  # sum of squared weighted residuals
    cost_after: float
    edge_rotation_deg: np.ndarray  # [E] each edge's remaining rotation error
    edge_scale_error: np.ndarray  # [E] |log| of each edge's remaining scale error


def _hat(omega: torch.Tensor) -> torch.Tensor:
    """``[..., 3, 3]`` skew matrices of ``[..., 3]`` vectors."""
    import torch

    zero = torch.zeros_like(omega[..., 0])
    x, y, z = omega.unbind(-1)
    return torch.stack(
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2
    )


def _log_rotation(rot: torch.Tensor) -> torch.Tensor:
    """``[..., 3]`` axis * angle of ``[..., 3, 3]`` rotations (angle below 180 deg). The skew part's norm is
    padded by 1e-30 under the root so that the gradient stays finite at the identity."""
    import torch

    skew = 0.5 * (rot - rot.transpose(-1, -2))
    vee = torch.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], -1)  # sin(angle) * axis
    sin = torch.sqrt((vee**2).sum(-1) + 1e-30)
    cos = 0.5 * (torch.diagonal(rot, dim1=-2, dim2=-1).sum(-1) - 1)
    return vee * (torch.atan2(sin, cos) / sin)[..., None]


class _Graph:
    """The nodes' current estimate and the edges, as float64 tensors; residuals of a parameter step."""

    def __init__(self, nodes: Sequence[Sim3], edges: Sequence[Sim3Edge], length_scale: float) -> None:
        import torch

        def stack(values) -> torch.Tensor:
            return torch.as_tensor(np.asarray(values, np.float64))

        self.rot = stack([n.rotation for n in nodes])
        self.trans = stack([n.translation for n in nodes])
        self.log_scale = stack([np.log(n.scale) for n in nodes])
        self.a = torch.as_tensor([e.a for e in edges])
        self.b = torch.as_tensor([e.b for e in edges])
        inv = [e.b_from_a.inverse() for e in edges]  # Z^-1
        self.z_rot, self.z_trans = stack([z.rotation for z in inv]), stack([z.translation for z in inv])
        self.z_log_scale = stack([np.log(z.scale) for z in inv])
        self.sqrt_weight = stack([np.sqrt(e.weight) for e in edges])
        self.length_scale = length_scale

    def _moved(self, step: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every node's rotation, translation and log scale after ``step`` ``[K - 1, 7]`` (node 0 stays)."""
        import torch

        full = torch.cat([torch.zeros(1, 7, dtype=step.dtype), step])
        rot = torch.linalg.matrix_exp(_hat(full[:, :3])) @ self.rot
        return rot, self.trans + full[:, 3:6], self.log_scale + full[:, 6]

    def residuals(self, step: torch.Tensor) -> torch.Tensor:
        """``[E, 7]`` weighted residuals of ``Z^-1 . X_b^-1 . X_a`` for every edge."""
        import torch

        rot, trans, log_scale = self._moved(step)
        ra, rb, ta, tb = rot[self.a], rot[self.b], trans[self.a], trans[self.b]
        rel_rot = rb.transpose(1, 2) @ ra
        rel_trans = torch.einsum("eji,ej->ei", rb, ta - tb) * torch.exp(-log_scale[self.b])[:, None]
        err_rot = self.z_rot @ rel_rot
        err_trans = torch.exp(self.z_log_scale)[:, None] * torch.einsum("eij,ej->ei", self.z_rot, rel_trans)
        err_trans = err_trans + self.z_trans
        err_log_scale = self.z_log_scale + log_scale[self.a] - log_scale[self.b]
        rot_res = _log_rotation(err_rot)
        res = torch.cat([rot_res, err_trans / self.length_scale, err_log_scale[:, None]], 1)
        return res * self.sqrt_weight[:, None]

    def fold(self, step: torch.Tensor) -> None:
        self.rot, self.trans, self.log_scale = (v.detach() for v in self._moved(step))

    def nodes(self) -> tuple[Sim3, ...]:
        import torch

        return tuple(
            Sim3(float(torch.exp(s)), r.numpy().copy(), t.numpy().copy())
            for r, t, s in zip(self.rot, self.trans, self.log_scale)
        )


def optimize_pose_graph(
    world_from_node: Sequence[Sim3],
    edges: Sequence[Sim3Edge],
    length_scale: float,
    options: PoseGraphOptions = PoseGraphOptions(),
) -> PoseGraphResult:
    """Move nodes 1..K-1 (node 0 stays) to minimise the edges' squared residuals; ``length_scale`` makes
    translation errors comparable to rotation ones (e.g. the typical distance between cameras).

    >>> turn = Sim3(1.0, np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), np.zeros(3))
    >>> result = optimize_pose_graph([Sim3.identity()] * 2, [Sim3Edge(0, 1, turn.inverse())], 1.0)
    >>> np.allclose(result.world_from_node[1].rotation, turn.rotation), result.cost_after < 1e-20
    (True, True)
    """
    import torch

    nodes = len(world_from_node)
    bad = [(e.a, e.b) for e in edges if not (0 <= e.a < nodes and 0 <= e.b < nodes) or e.a == e.b]
    if bad or not np.isfinite(length_scale) or length_scale <= 0:
        raise InputError(
            f"pose graph of {nodes} nodes: edges {bad[:3]} name no two distinct nodes, or length scale {length_scale}",
            "build edges between existing nodes and pass a positive length scale",
        )
    graph = _Graph(world_from_node, edges, float(length_scale))
    zero = torch.zeros(nodes - 1, 7, dtype=torch.float64)
    cost_before = cost = float((graph.residuals(zero) ** 2).sum())
    iterations = 0
    while nodes > 1 and edges and iterations < options.max_iterations:
        iterations += 1
        res = graph.residuals(zero).reshape(-1)
        jac = torch.func.jacrev(lambda p: graph.residuals(p.reshape(nodes - 1, 7)).reshape(-1))(zero.reshape(-1))
        normal = jac.T @ jac
        normal = normal + options.damping * torch.diag(torch.diagonal(normal).clamp_min(1e-12))
        step = torch.linalg.solve(normal, -jac.T @ res)
        if not torch.isfinite(step).all():
            break
        trial = float((graph.residuals(step.reshape(nodes - 1, 7)) ** 2).sum())
        if trial > cost:
            break  # no descent from here (at the optimum, up to rounding)
        graph.fold(step.reshape(nodes - 1, 7))
        cost = trial
        if float(step.abs().max()) < options.tolerance:
            break
    final = graph.residuals(zero).detach()
    angle = torch.linalg.norm(final[:, :3], dim=1) / graph.sqrt_weight.clamp_min(1e-300)
    return PoseGraphResult(
        world_from_node=graph.nodes(),
        iterations=iterations,
        cost_before=cost_before,
        cost_after=cost,
        edge_rotation_deg=np.degrees(angle.numpy()),
        edge_scale_error=np.abs(final[:, 6].numpy()) / graph.sqrt_weight.clamp_min(1e-300).numpy(),
    )
