"""Similarity transforms (Sim(3)) and their least-squares estimation.

The confidence-weighted Umeyama fit is written here because pycolmap's ``estimate_sim3d`` has no
weighted variant, and chunk merging weights points by the model's confidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ffrecon.checks import check_shape, require_finite
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import rotation_angle_deg


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

    def compose(self, a_from_c: Sim3) -> Sim3:
        """``b_from_c = b_from_a . a_from_c`` (this transform after ``a_from_c``)."""
        return Sim3(
            self.scale * a_from_c.scale,
            self.rotation @ a_from_c.rotation,
            self.scale * self.rotation @ a_from_c.translation + self.translation,
        )

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


def collinear(points: np.ndarray, ratio: float = 0.05) -> bool:
    """Whether ``[N, 3]`` points lie near one line (or one point): the second singular value of the centred
    points is under ``ratio`` of the first. A Sim(3) fitted to such points leaves the rotation about that line
    free (camera centres of a straight walk).

    >>> collinear(np.array([[0, 0, 0], [1, 0.01, 0], [2, 0, 0.01], [3, 0, 0]], float))
    True
    """
    centred = np.asarray(points, np.float64) - np.mean(points, axis=0)
    sing = np.linalg.svd(centred, compute_uv=False)
    return bool(len(points) < 3 or sing[1] < ratio * max(sing[0], 1e-300))


def flat(points: np.ndarray, ratio: float = 0.2) -> bool:
    """Whether ``[N, 3]`` points lie near one plane (fewer than four always do): the third singular value of
    the centred points is under ``ratio`` of the first. A Sim(3) fitted to such points holds the plane's tilt
    only as well as the points' small offsets from it (camera centres of an orbit at one height).

    >>> flat(np.array([[0, 0, 0], [1, 0, 0.01], [0, 1, 0], [1, 1, 0.02]], float))
    True
    >>> flat(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float))
    False
    """
    centred = np.asarray(points, np.float64) - np.mean(points, axis=0)
    sing = np.linalg.svd(centred, compute_uv=False)
    return bool(len(points) < 4 or sing[-1] < ratio * max(sing[0], 1e-300))


def sim3_from_cameras(src_cam_from_world: np.ndarray, dst_cam_from_world: np.ndarray) -> Sim3:
    """``dst_from_src`` for two sets of the same ``[N, 3, 4]`` cameras: the rotation from their orientations
    (the chordal mean of each camera's ``R_dst^T R_src``, projected on SO(3) by SVD), then scale and
    translation from their centres by least squares. Unlike :func:`umeyama` on the centres alone, this is
    determined when the centres are collinear.

    >>> rot = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    >>> src = np.stack([np.concatenate([np.eye(3), [[-x], [0], [0]]], axis=1) for x in range(3)])
    >>> dst = Sim3(2.0, rot, np.ones(3)).transform_cam_from_world(src)
    >>> fit = sim3_from_cameras(src, dst)
    >>> bool(np.allclose(fit.rotation, rot)), round(fit.scale, 6), bool(np.allclose(fit.translation, 1))
    (True, 2.0, True)
    """
    src_rot, dst_rot = src_cam_from_world[:, :, :3], dst_cam_from_world[:, :, :3]
    u, _, vt = np.linalg.svd(np.einsum("nji,njk->ik", dst_rot, src_rot))  # sum of R_dst^T R_src
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rot = u @ fix @ vt
    src_c = -np.einsum("nji,nj->ni", src_rot, src_cam_from_world[:, :, 3])
    dst_c = -np.einsum("nji,nj->ni", dst_rot, dst_cam_from_world[:, :, 3])
    turned = (src_c - src_c.mean(0)) @ rot.T
    scale = float(np.sum(turned * (dst_c - dst_c.mean(0))) / max(float(np.sum(turned**2)), 1e-300))
    return Sim3(scale, rot, dst_c.mean(0) - scale * rot @ src_c.mean(0))


def robust_sim3_from_cameras(
    src_cam_from_world: np.ndarray, dst_cam_from_world: np.ndarray, max_angle_deg: float | None = None
) -> Sim3:
    """:func:`sim3_from_cameras` without the cameras whose orientation is more than three times the median angle
    from the fit (a frame the model turned far off must not tilt the rest), then its scale and translation
    refitted without the centres far from a median-based fit (:func:`_robust_centres`).

    The cameras kept are first those near the medoid of the cameras' own rotation differences (``R_dst^T R_src``
    of the camera whose median angle to the others' is least): within three times the others' median angle to it
    (four cameras or more), and within ``max_angle_deg`` of it (three or more; None: no such bound). Started from
    the mean of all, one frame 25 deg off among four tilts the mean 6 deg, the good frames end 5-7 deg from it
    and the bad one 18, inside three times their median (held-out room 356: a part of four frames placed 6 deg
    off by it); among three, no median tells one camera 25 deg off from two that agree (held-out room 364: a part
    placed 8 deg off), a bound in degrees does.
    """
    src_rot, dst_rot = src_cam_from_world[:, :, :3], dst_cam_from_world[:, :, :3]
    each = np.einsum("nji,njk->nik", dst_rot, src_rot)  # R_dst^T R_src, the rotation each camera alone gives
    keep = np.ones(len(each), dtype=bool)
    if len(each) >= 3:
        traces = np.einsum("ikl,jkl->ij", each, each)  # trace(each_i each_j^T), every pair at once
        between = np.degrees(np.arccos(np.clip((traces - 1.0) / 2.0, -1.0, 1.0)))
        medoid = int(np.argmin(np.median(between, axis=1)))
        bar = 3 * np.median(np.delete(between[medoid], medoid)) + 1e-9 if len(each) >= 4 else np.inf
        keep = between[medoid] <= min(bar, np.inf if max_angle_deg is None else max_angle_deg)
    sim = sim3_from_cameras(src_cam_from_world[keep], dst_cam_from_world[keep])
    moved = np.einsum("nij,kj->nik", src_rot, sim.rotation)  # R_src rot^T, as R_dst
    angles = np.array([rotation_angle_deg(m @ d.T) for m, d in zip(moved, dst_rot)])
    keep = angles <= 3 * np.median(angles) + 1e-9
    if 3 <= keep.sum() < len(keep):
        sim = sim3_from_cameras(src_cam_from_world[keep], dst_cam_from_world[keep])
    return _robust_centres(sim, camera_centers(src_cam_from_world), camera_centers(dst_cam_from_world))


def _robust_centres(sim: Sim3, src: np.ndarray, dst: np.ndarray) -> Sim3:
    """``sim`` with its scale and translation refitted (least squares, its rotation kept) without the centres
    more than three times the median residual from a fit on medians; ``sim`` itself when none is that far.

    A least-squares scale follows one centre far off: on the repeated-tile street (tuning seed 203, drift,
    ``--quick``) an adjustment sent one frame's centre 3,800 units away (its points fixed its rotation only)
    and the fit's scale came out -1.8e-5, which put every point behind its cameras. The medians' fit (spread
    over spread, about the median centres) is not moved by a few such centres.

    >>> src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [500, 0, 900]])
    >>> dst = np.vstack([2 * src[:4], [[0.0, 0, 1]]])  # the last centre far off in src
    >>> round(_robust_centres(Sim3(1e-5, np.eye(3), np.zeros(3)), src, dst).scale, 6)
    2.0
    """
    if len(src) < 3:
        return sim
    turned = src @ sim.rotation.T
    mid_t, mid_d = np.median(turned, axis=0), np.median(dst, axis=0)
    spread_t = float(np.median(np.linalg.norm(turned - mid_t, axis=1)))
    if spread_t <= 1e-300:
        return sim
    scale0 = float(np.median(np.linalg.norm(dst - mid_d, axis=1))) / spread_t
    residual = np.linalg.norm(scale0 * (turned - mid_t) - (dst - mid_d), axis=1)
    keep = residual <= 3 * np.median(residual) + 1e-12
    if keep.all() or keep.sum() < 3:
        return sim
    t, d = turned[keep] - turned[keep].mean(0), dst[keep] - dst[keep].mean(0)
    scale = float(np.sum(t * d) / max(float(np.sum(t**2)), 1e-300))
    scale = scale if scale > 0 else scale0
    return Sim3(scale, sim.rotation, dst[keep].mean(0) - scale * sim.rotation @ src[keep].mean(0))


def robust_umeyama(src: np.ndarray, dst: np.ndarray) -> Sim3:
    """:func:`umeyama`, refitted once without the points whose residual exceeds three times the median."""
    sim = umeyama(src, dst)
    residual = np.linalg.norm(sim.apply(src) - dst, axis=1)
    keep = residual <= 3 * np.median(residual) + 1e-12
    if 3 <= keep.sum() < len(keep):
        sim = umeyama(src[keep], dst[keep])
    return sim


def _inliers(errors: np.ndarray) -> np.ndarray:
    return errors <= 3 * np.median(errors) + 1e-12


def centre_fit_rotation_std_deg(sim: Sim3, src: np.ndarray, dst: np.ndarray) -> float:
    """How well a Sim(3) fitted to ``[N, 3]`` centres holds its rotation: the standard deviation (degrees) of
    its worst-held axis, from the fit's residuals (per coordinate, 7 parameters taken out) over the lever
    the centres' spread gives that axis (the two smaller singular values of the moved, centred points).
    Inf for fewer than 4 points."""
    residual = np.linalg.norm(sim.apply(src) - dst, axis=1)
    keep = _inliers(residual)
    if keep.sum() < 4:
        return float("inf")
    noise = np.sqrt(np.sum(residual[keep] ** 2) / max(3 * keep.sum() - 7, 1))
    moved = sim.apply(src[keep])
    sing = np.linalg.svd(moved - moved.mean(0), compute_uv=False)
    return float(np.degrees(noise / max(np.hypot(sing[1], sing[2]), 1e-300)))


def orientation_fit_rotation_std_deg(
    sim: Sim3, src_cam_from_world: np.ndarray, dst_cam_from_world: np.ndarray
) -> float:
    """How well a Sim(3) whose rotation is the cameras' mean orientation difference holds it: the standard
    deviation (degrees) of that mean about one axis, from the cameras' angles to the fit (per axis, one
    rotation's parameters taken out). Inf for fewer than 2 cameras."""
    moved = np.einsum("nij,kj->nik", src_cam_from_world[:, :, :3], sim.rotation)
    angles = np.array([rotation_angle_deg(m @ d.T) for m, d in zip(moved, dst_cam_from_world[:, :, :3])])
    keep = _inliers(angles)
    n = int(keep.sum())
    if n < 2:
        return float("inf")
    return float(np.sqrt(np.sum(angles[keep] ** 2) / (3 * (n - 1)) / n))


def camera_sim3(
    src_cam_from_world: np.ndarray, dst_cam_from_world: np.ndarray, max_angle_deg: float | None = None
) -> Sim3:
    """``dst_from_src`` for two sets of the same ``[N, 3, 4]`` cameras, robust to a few cameras far off.

    Two fits: Umeyama on the camera centres (:func:`robust_umeyama`) and the cameras' orientations
    (:func:`robust_sim3_from_cameras`). Centres on one line leave the rotation about it free and centres
    near one plane hold its tilt weakly, so those take the orientations. Otherwise the fit whose rotation
    its own residuals say is held better wins: centres bunched up relative to their noise (a room
    photographed from its middle: on a synthetic furnished room the centre fit turned 9.5 degrees where
    the orientations were 1.6 off) take the orientations too. ``max_angle_deg``: see
    :func:`robust_sim3_from_cameras`.
    """
    src = -np.einsum("nji,nj->ni", src_cam_from_world[:, :, :3], src_cam_from_world[:, :, 3])
    dst = -np.einsum("nji,nj->ni", dst_cam_from_world[:, :, :3], dst_cam_from_world[:, :, 3])
    by_orientation = robust_sim3_from_cameras(src_cam_from_world, dst_cam_from_world, max_angle_deg)
    if len(src) < 4 or collinear(src) or collinear(dst) or flat(src) or flat(dst):
        return by_orientation
    by_centres = robust_umeyama(src, dst)
    centre_std = centre_fit_rotation_std_deg(by_centres, src, dst)
    orientation_std = orientation_fit_rotation_std_deg(by_orientation, src_cam_from_world, dst_cam_from_world)
    return by_centres if centre_std <= orientation_std else by_orientation
