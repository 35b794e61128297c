"""Rotation conversions on numpy arrays.

Written by hand (a few vectorised lines each) because the pipeline's decoding and metrics work on
plain float64 numpy arrays; kornia's equivalents are torch-only and pycolmap's are per-element.
Quaternions name their ordering: ``quat_xyzw`` is scalar-last (VGGT, pycolmap), ``quat_wxyz``
scalar-first (3DGS PLY files).
"""

from __future__ import annotations

import numpy as np


def quat_xyzw_to_matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternions (normalised here) to rotation matrices.

    Args:
        quat_xyzw: ``[..., 4]`` scalar-last quaternions.
    Returns:
        ``[..., 3, 3]`` rotation matrices.

    >>> np.allclose(quat_xyzw_to_matrix(np.array([0.0, 0.0, 0.0, 1.0])), np.eye(3))
    True
    """
    q = np.asarray(quat_xyzw, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    q = q / np.where(norm > 0, norm, np.nan)  # a zero quaternion is no rotation: NaN, which the callers report
    x, y, z, w = np.moveaxis(q, -1, 0)
    rot = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return rot.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat_xyzw(rot: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` to unit quaternions ``[..., 4]`` (xyzw, w >= 0).

    Uses the largest-diagonal branch for each matrix (numerically stable everywhere).

    >>> matrix_to_quat_xyzw(np.eye(3))
    array([0., 0., 0., 1.])
    """
    m = np.asarray(rot, dtype=np.float64)
    batch = m.shape[:-2]
    m = m.reshape(-1, 3, 3)
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    # Candidate quaternions (scaled) for each of the four branches, as in Shepperd's method.
    cand = np.stack(
        [
            np.stack(
                [1 + m00 - m11 - m22, m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 2, 1] - m[:, 1, 2]], -1
            ),
            np.stack(
                [m[:, 0, 1] + m[:, 1, 0], 1 - m00 + m11 - m22, m[:, 1, 2] + m[:, 2, 1], m[:, 0, 2] - m[:, 2, 0]], -1
            ),
            np.stack(
                [m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1], 1 - m00 - m11 + m22, m[:, 1, 0] - m[:, 0, 1]], -1
            ),
            np.stack(
                [m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1], 1 + m00 + m11 + m22], -1
            ),
        ],
        axis=1,
    )
    choice = np.argmax(np.stack([m00, m11, m22, m00 + m11 + m22], -1), axis=-1)
    q = cand[np.arange(len(m)), choice]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[:, 3:4] < 0, -q, q)
    return q.reshape(batch + (4,))


def axis_angle_to_matrix(axis_angle: np.ndarray) -> np.ndarray:
    """Rodrigues: ``[..., 3]`` axis times angle (radians) to ``[..., 3, 3]`` rotations."""
    v = np.asarray(axis_angle, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = angle / 2
    # sin(x/2)/x with its limit 1/2 at 0.
    scale = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-12), 0.5)
    quat_xyzw = np.concatenate([v * scale, np.cos(half)], axis=-1)
    return quat_xyzw_to_matrix(quat_xyzw)


def matrix_to_axis_angle(rot: np.ndarray) -> np.ndarray:
    """``[..., 3]`` axis times angle (radians) of ``[..., 3, 3]`` rotations whose angle is below 180 deg (from the
    skew-symmetric part; near 180 deg the axis loses precision). The inverse of :func:`axis_angle_to_matrix`.

    >>> v = np.array([0.3, -0.2, 0.1])
    >>> bool(np.allclose(matrix_to_axis_angle(axis_angle_to_matrix(v)), v))
    True
    """
    rot = np.asarray(rot, dtype=np.float64)
    vee = 0.5 * np.stack(
        [rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]], -1
    )
    sin = np.linalg.norm(vee, axis=-1)  # sin(angle) times the unit axis: vee
    cos = 0.5 * (np.trace(rot, axis1=-2, axis2=-1) - 1)
    angle = np.arctan2(sin, cos)
    # angle / sin(angle) with its limit 1 at the identity
    ratio = np.where(sin > 1e-300, angle / np.maximum(sin, 1e-300), 1.0)
    return vee * ratio[..., None]


def rotation_angle_deg(rot: np.ndarray) -> np.ndarray:
    """Angle in degrees of rotation matrices ``[..., 3, 3]`` (robust near 0 and 180 degrees).

    >>> round(float(rotation_angle_deg(axis_angle_to_matrix(np.array([0.0, 0.0, np.pi / 2])))), 9)
    90.0
    """
    q = matrix_to_quat_xyzw(rot)
    vec = np.linalg.norm(q[..., :3], axis=-1)
    return np.degrees(2 * np.arctan2(vec, np.abs(q[..., 3])))


def nearest_rotation(matrices: np.ndarray) -> np.ndarray:
    """The rotations nearest (Frobenius) to ``[..., 3, 3]`` matrices, by SVD: a rotation, never a reflection.

    >>> nearest_rotation(2.0 * np.eye(3)).tolist() == np.eye(3).tolist()
    True
    """
    u, _, vt = np.linalg.svd(matrices)
    u[..., :, 2] *= np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)[..., None]
    return u @ vt


def chordal_mean(rotations: np.ndarray) -> np.ndarray:
    """The chordal L2 mean of ``[N, 3, 3]`` rotations: their sum projected onto SO(3) by SVD.

    >>> turn = axis_angle_to_matrix(np.array([0.0, 0.0, 0.2]))
    >>> round(float(rotation_angle_deg(chordal_mean(np.stack([turn, turn.T])))), 9)
    0.0
    """
    return nearest_rotation(np.sum(rotations, axis=0))


def random_rotation(rng: np.random.Generator, size: int | None = None) -> np.ndarray:
    """Uniformly random rotations ``[size, 3, 3]`` (or ``[3, 3]``) from normalised Gaussians."""
    q = rng.normal(size=(1 if size is None else size, 4))
    rot = quat_xyzw_to_matrix(q)
    return rot[0] if size is None else rot
