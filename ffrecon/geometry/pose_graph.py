"""Sim(3) pose-graph optimisation: nodes are similarity transforms, edges measure relative ones.

Chunked feed-forward inference chains chunks by a Sim(3) fitted on their shared frames; each link adds a
small error, so a long path drifts. A loop chunk (frames from both ends of a revisit in one model call)
measures how the chain should close; this spreads the disagreement over every link (each edge's error
weighted alike unless told otherwise).

Written here because pycolmap has no Sim(3) pose-graph solver (its ``PoseGraph`` is the global mapper's view
graph of two-view geometries) and the problem is small, one node per chunk: Gauss-Newton (with a little
Levenberg-Marquardt damping) with a dense solve, a bounded number of iterations. Each node moves by
``exp(omega) R``, ``t + tau``, ``exp(sigma) s`` from the current estimate. An edge's rotation residual is its
error rotation's axis times angle, the translation residual is in units of ``length_scale``, the scale
residual is the log.

In numpy, the Jacobian by central differences over every parameter at once (one batched evaluation of the
residuals; error of order ``step**2``, ~1e-12 here): with torch's autograd (``torch.func.jacrev``) the
solve took 1.3-2.4 CPU s for 13 nodes on the 2-core machine, plus 1.1 s to import torch in a run that
otherwise never loads it (``--quick --no-splat`` at 96 frames, issue 40); now a few milliseconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ffrecon.checks import check_number
from ffrecon.errors import InputError
from ffrecon.geometry.alignment import Sim3
from ffrecon.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle


@dataclass(frozen=True, kw_only=True)
class PoseGraphOptions:
    max_iterations: int = 20
    tolerance: float = 1e-10  # stop once the largest parameter step is below this
    damping: float = 1e-6  # Levenberg-Marquardt damping, relative to the normal matrix's diagonal
    difference_step: float = 1e-6  # of the central differences that give the Jacobian (radians, lengths, log)

    def __post_init__(self) -> None:
        check_number("PoseGraphOptions.max_iterations", self.max_iterations, low=1, integer=True)
        check_number("PoseGraphOptions.tolerance", self.tolerance, low=0, low_open=True)
        check_number("PoseGraphOptions.damping", self.damping, low=0)
        check_number("PoseGraphOptions.difference_step", self.difference_step, low=0, low_open=True, high=0.1)


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


class _Graph:
    """The nodes' current estimate and the edges (float64); residuals of parameter steps."""

    def __init__(self, nodes: Sequence[Sim3], edges: Sequence[Sim3Edge], length_scale: float) -> None:
        self.rot = np.stack([n.rotation for n in nodes]).astype(np.float64)
        self.trans = np.stack([n.translation for n in nodes]).astype(np.float64)
        self.log_scale = np.log([n.scale for n in nodes]).astype(np.float64)
        self.a = np.array([e.a for e in edges], np.int64)
        self.b = np.array([e.b for e in edges], np.int64)
        inv = [e.b_from_a.inverse() for e in edges]  # Z^-1
        self.z_rot = np.stack([z.rotation for z in inv]).astype(np.float64)
        self.z_trans = np.stack([z.translation for z in inv]).astype(np.float64)
        self.z_log_scale = np.log([z.scale for z in inv]).astype(np.float64)
        self.sqrt_weight = np.sqrt(np.array([e.weight for e in edges], np.float64))
        self.length_scale = length_scale

    def _moved(self, step: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every node's rotation, translation and log scale after ``step`` ``[..., K - 1, 7]`` (node 0 stays)."""
        full = np.concatenate([np.zeros((*step.shape[:-2], 1, 7)), step], -2)
        rot = axis_angle_to_matrix(full[..., :3]) @ self.rot
        return rot, self.trans + full[..., 3:6], self.log_scale + full[..., 6]

    def residuals(self, step: np.ndarray) -> np.ndarray:
        """``[..., E, 7]`` weighted residuals of ``Z^-1 . X_b^-1 . X_a`` per edge, per step ``[..., K - 1, 7]``."""
        rot, trans, log_scale = self._moved(step)
        ra, rb, ta, tb = rot[..., self.a, :, :], rot[..., self.b, :, :], trans[..., self.a, :], trans[..., self.b, :]
        rel_rot = np.swapaxes(rb, -1, -2) @ ra
        rel_trans = np.einsum("...eji,...ej->...ei", rb, ta - tb) * np.exp(-log_scale[..., self.b])[..., None]
        err_rot = self.z_rot @ rel_rot
        err_trans = np.exp(self.z_log_scale)[:, None] * np.einsum("eij,...ej->...ei", self.z_rot, rel_trans)
        err_trans = err_trans + self.z_trans
        err_log_scale = self.z_log_scale + log_scale[..., self.a] - log_scale[..., self.b]
        res = np.concatenate(
            [matrix_to_axis_angle(err_rot), err_trans / self.length_scale, err_log_scale[..., None]], -1
        )
        return res * self.sqrt_weight[:, None]

    def jacobian(self, h: float) -> np.ndarray:
        """``[E * 7, (K - 1) * 7]`` Jacobian of the flattened residuals at the current estimate (central differences
        of step ``h``)."""
        params = (len(self.rot) - 1) * 7
        steps = np.concatenate([np.eye(params) * h, np.eye(params) * -h]).reshape(2 * params, -1, 7)
        res = self.residuals(steps).reshape(2 * params, -1)
        return ((res[:params] - res[params:]) / (2 * h)).T

    def fold(self, step: np.ndarray) -> None:
        self.rot, self.trans, self.log_scale = self._moved(step)

    def nodes(self) -> tuple[Sim3, ...]:
        return tuple(
            Sim3(float(np.exp(s)), r.copy(), t.copy()) for r, t, s in zip(self.rot, self.trans, self.log_scale)
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
    nodes = len(world_from_node)
    bad = [(e.a, e.b) for e in edges if not (0 <= e.a < nodes and 0 <= e.b < nodes) or e.a == e.b]
    if bad or not np.isfinite(length_scale) or length_scale <= 0:
        raise InputError(
            f"pose graph of {nodes} nodes: edges {bad[:3]} name no two distinct nodes, or length scale {length_scale}",
            "build edges between existing nodes and pass a positive length scale",
        )
    graph = _Graph(world_from_node, edges, float(length_scale))
    zero = np.zeros((nodes - 1, 7))
    cost_before = cost = float((graph.residuals(zero) ** 2).sum())
    iterations = 0
    while nodes > 1 and edges and iterations < options.max_iterations:
        iterations += 1
        res = graph.residuals(zero).reshape(-1)
        jac = graph.jacobian(options.difference_step)
        normal = jac.T @ jac
        normal = normal + options.damping * np.diag(np.maximum(np.diagonal(normal), 1e-12))
        try:
            step = np.linalg.solve(normal, -jac.T @ res)
        except np.linalg.LinAlgError:
            break
        if not np.isfinite(step).all():
            break
        trial = float((graph.residuals(step.reshape(nodes - 1, 7)) ** 2).sum())
        if trial > cost:
            break  # no descent from here (at the optimum, up to rounding)
        graph.fold(step.reshape(nodes - 1, 7))
        cost = trial
        if float(np.abs(step).max()) < options.tolerance:
            break
    final = graph.residuals(zero)
    weight = np.maximum(graph.sqrt_weight, 1e-300)
    return PoseGraphResult(
        world_from_node=graph.nodes(),
        iterations=iterations,
        cost_before=cost_before,
        cost_after=cost,
        edge_rotation_deg=np.degrees(np.linalg.norm(final[:, :3], axis=1) / weight),
        edge_scale_error=np.abs(final[:, 6]) / weight,
    )
