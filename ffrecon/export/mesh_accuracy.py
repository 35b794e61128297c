"""How close a reconstructed surface is to the true one: Chamfer distance and F-score, with open3d's nearest
neighbours.

Both surfaces are point sets (a mesh is sampled uniformly by area first: :func:`sample_surface`). With
``d(a, B)`` the distance from a point ``a`` to its nearest neighbour in ``B``:

- accuracy = mean over estimated points of ``d(est, truth)``; completeness = mean over true points of
  ``d(truth, est)``; Chamfer = their mean (DTU's "overall");
- precision = share of estimated points within ``threshold`` of the truth, recall = share of true points
  within ``threshold`` of the estimate, F-score = their harmonic mean.

Distances are reported as fractions of ``extent`` (the diagonal of the true points' bounding box).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from ffrecon.checks import check_number, check_shape


@dataclass(frozen=True)
class SurfaceAccuracy:
    accuracy: float  # mean distance estimate -> truth, fraction of the extent
    completeness: float  # mean distance truth -> estimate, fraction of the extent
    chamfer: float  # (accuracy + completeness) / 2
    precision: float  # share of estimated points within the threshold of the truth
    recall: float  # share of true points within the threshold of the estimate
    fscore: float  # harmonic mean of precision and recall (0 when both are 0)
    threshold: float  # fraction of the extent


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))


def sample_surface(mesh: o3d.geometry.TriangleMesh, count: int, seed: int = 0) -> np.ndarray:
    """``[count, 3]`` points drawn uniformly by area on ``mesh`` (the same ``seed``, the same points);
    ``[0, 3]`` for a mesh without triangles."""
    if len(mesh.triangles) == 0:
        return np.zeros((0, 3))
    o3d.utility.random.seed(seed)
    return np.asarray(mesh.sample_points_uniformly(number_of_points=count).points)


def surface_accuracy(
    estimate: np.ndarray, truth: np.ndarray, extent: float, threshold: float = 0.01
) -> SurfaceAccuracy:
    """Chamfer distance and F-score of ``estimate [M, 3]`` against ``truth [P, 3]`` (same frame and units),
    as fractions of ``extent``; ``threshold`` is the F-score's distance, a fraction of ``extent`` too.
    An empty estimate is infinitely far (Chamfer inf, F-score 0).

    >>> truth = np.array([[0.0, 0, 0], [1, 0, 0]])
    >>> r = surface_accuracy(np.array([[0.0, 0, 0.05]]), truth, extent=1.0, threshold=0.1)
    >>> round(r.accuracy, 3), round(r.completeness, 3), r.precision, r.recall
    (0.05, 0.526, 1.0, 0.5)
    """
    check_shape("estimate", estimate, (None, 3))
    check_shape("truth", truth, (None, 3))
    check_number("extent", extent, low=0, low_open=True)
    if len(truth) == 0:
        raise ValueError("no true point to compare with")
    if len(estimate) == 0:
        return SurfaceAccuracy(np.inf, np.inf, np.inf, 0.0, 0.0, 0.0, threshold)
    est, ref = _cloud(estimate), _cloud(truth)
    to_truth = np.asarray(est.compute_point_cloud_distance(ref)) / extent
    to_estimate = np.asarray(ref.compute_point_cloud_distance(est)) / extent
    precision = float(np.mean(to_truth <= threshold))
    recall = float(np.mean(to_estimate <= threshold))
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    accuracy, completeness = float(to_truth.mean()), float(to_estimate.mean())
    return SurfaceAccuracy(accuracy, completeness, (accuracy + completeness) / 2, precision, recall, fscore, threshold)


def bounding_diagonal(points: np.ndarray) -> float:
    """The diagonal of the axis-aligned bounding box of ``points [P, 3]``.

    >>> bounding_diagonal(np.array([[0.0, 0, 0], [3, 4, 0]]))
    5.0
    """
    return float(np.linalg.norm(np.max(points, axis=0) - np.min(points, axis=0)))
