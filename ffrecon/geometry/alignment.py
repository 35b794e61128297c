"""Similarity transforms (Sim(3)) and their least-squares estimation.

The confidence-weighted Umeyama fit is written here because pycolmap's ``estimate_sim3d`` has no
weighted variant, and chunk merging weights points by the model's confidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ffrecon.checks import check_shape, require_finite


@dataclass(frozen=True)
class Sim3:
    """``b_from_a``: ``x_b = scale * rotation @ x_a + translation``."""

    scale: float
    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3]

    @staticmethod
    def identity() -> "Sim3":
        return Sim3(1.0, np.eye(3), np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map ``[..., 3]`` points from frame a to frame b."""
        return self.scale * points @ self.rotation.T + self.translation

    def inverse(self) -> "Sim3":
        rot_t = self.rotation.T
        return Sim3(1.0 / self.scale, rot_t, -rot_t @ self.translation / self.scale)

    def transform_cam_from_world(self, cam_from_a: np.ndarray) -> np.ndarray:
        """Re-express ``[..., 3, 4]`` cam_from_a poses as cam_from_b (metric part scaled)."""
        rot = cam_from_a[..., :3, :3] @ self.rotation.T
        trans = self.scale * cam_from_a[..., :3, 3] - np.einsum("...ij,j->...i", rot, self.translation)
        return np.concatenate([rot, trans[..., None]], axis=-1)

    def matrix(self) -> np.ndarray:
        """``[4, 4]`` homogeneous matrix."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> Sim3:
    """Least-squares Sim(3) ``dst_from_src`` (Umeyama 1991), optionally weighted.

    Args:
        src, dst: ``[N, 3]`` corresponding points, N >= 3 and not collinear.
        weights: ``[N]`` non-negative weights, or None for equal weights.

    >>> rng = np.random.default_rng(0); a = rng.normal(size=(10, 3))
    >>> fit = umeyama(a, 2 * a + 1)
    >>> round(fit.scale, 6), np.allclose(fit.translation, 1)
    (2.0, True)
    """
    check_shape("src", src, (None, 3))
    check_shape("dst", dst, (src.shape[0], 3))
    require_finite("Sim(3) fit", src=src, dst=dst, **({} if weights is None else {"weights": weights}))
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    s0, d0 = src - mu_s, dst - mu_d
    cov = (d0 * w[:, None]).T @ s0
    u, sing, vt = np.linalg.svd(cov)
    fix = np.eye(3)
    fix[2, 2] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rot = u @ fix @ vt
    var_s = float(w @ (s0**2).sum(1))
    scale = float(np.trace(np.diag(sing) @ fix) / max(var_s, 1e-300))
    return Sim3(scale, rot, mu_d - scale * rot @ mu_s)
