"""EWA projection of 3D Gaussians into a pinhole camera, forward and backward as compiled kernels (numba).

The same mathematics as the PyTorch formulation it replaces (and as 3DGS / gsplat): the camera-frame
centre ``p = R m + t``; the pixel ``(fx x / z + cx, fy y / z + cy)``; the Jacobian of the perspective
map evaluated with ``x / z`` and ``y / z`` clamped to 1.3 times the field of view; the 2D covariance
``J R Sigma R^T J^T + eps2d I`` with ``Sigma = Rq diag(s)^2 Rq^T``; its inverse (the conic); and
``log sigmoid`` of the opacity logit. Written by hand because, per Gaussian, it is a few hundred
flops on 3x3 matrices: autograd over batched tiny matmuls spent ~35 ms per 60k-Gaussian view on it
(a third of a training step), the kernels below ~3 ms. The backward is the chain rule in the same
order, step by step; the finite-difference tests of the renderer check it (pose included).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch
from numba import njit, prange

import ffrecon.splat.raster  # noqa: F401  (selects numba's threading layer before any parallel call)
from ffrecon.splat.raster import ALPHA_MIN

_LOG_ALPHA_MIN = math.log(ALPHA_MIN)


@njit(cache=True)
def _mm(a, b, out):
    """``out = a b`` for small matrices (pass ``x.T`` for a transpose: a view, no copy). Written out because
    numba's ``@`` calls BLAS through SciPy (not a dependency), and into ``out`` because a heap allocation per
    Gaussian costs more than the maths."""
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            total = 0.0
            for k in range(a.shape[1]):
                total += a[i, k] * b[k, j]
            out[i, j] = total
    return out


@njit(cache=True)
def _quat_to_matrix(w, x, y, z, r):
    """Rotation matrix of the unit quaternion ``(w, x, y, z)`` (scalar first), into ``r [3, 3]``."""
    r[0, 0], r[0, 1], r[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r[1, 0], r[1, 1], r[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r[2, 0], r[2, 1], r[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


@njit(cache=True)
def _camera_terms(i, means, rot, trans, cam, near, p, jac):
    """Camera-frame centre ``p [3]`` and Jacobian ``jac [2, 3]`` of Gaussian ``i`` (written in place).

    ``cam`` is ``(fx, fy, cx, cy, width, height)``. Returns ``(in_front, zs, clamped_x, clamped_y, tx,
    ty)``: the safe depth, whether ``x / z`` (``y / z``) hit the field-of-view clamp, and ``z`` times the
    clamped ratios."""
    fx, fy, cx, cy, width, height = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5]
    for r in range(3):
        p[r] = rot[r, 0] * means[i, 0] + rot[r, 1] * means[i, 1] + rot[r, 2] * means[i, 2] + trans[r]
    in_front = p[2] > near
    zs = p[2] if in_front else 1.0
    lo_x, hi_x = -(cx / fx + 0.15 * width / fx), (width - cx) / fx + 0.15 * width / fx
    lo_y, hi_y = -(cy / fy + 0.15 * height / fy), (height - cy) / fy + 0.15 * height / fy
    rx, ry = p[0] / zs, p[1] / zs
    clamped_x, clamped_y = not (lo_x <= rx <= hi_x), not (lo_y <= ry <= hi_y)
    tx, ty = zs * min(max(rx, lo_x), hi_x), zs * min(max(ry, lo_y), hi_y)
    jac[0, 0], jac[0, 1], jac[0, 2] = fx / zs, 0.0, -fx * tx / (zs * zs)
    jac[1, 0], jac[1, 1], jac[1, 2] = 0.0, fy / zs, -fy * ty / (zs * zs)
    return in_front, zs, clamped_x, clamped_y, tx, ty


@njit(cache=True)
def _gaussian_factor(i, quats, log_scales, m, qn, rq, s):
    """``M = Rq diag(s)`` (so ``Sigma = M M^T``) into ``m``, the unit quaternion into ``qn``, ``Rq`` into
    ``rq`` and the scales into ``s``; returns the quaternion's norm."""
    norm = math.sqrt(quats[i, 0] ** 2 + quats[i, 1] ** 2 + quats[i, 2] ** 2 + quats[i, 3] ** 2)
    for j in range(4):
        qn[j] = quats[i, j] / norm
    _quat_to_matrix(qn[0], qn[1], qn[2], qn[3], rq)
    for j in range(3):
        s[j] = math.exp(log_scales[i, j])
    for r in range(3):
        for j in range(3):
            m[r, j] = rq[r, j] * s[j]
    return norm


@njit(cache=True)
def _scratch(threads):
    """Per-thread work arrays: p, jac, m, qn, rq, s, t_mat, tmp23, sigma, tmp33, d_cov, tmp22, dt23."""
    return (
        np.empty((threads, 3)),
        np.empty((threads, 2, 3)),
        np.empty((threads, 3, 3)),
        np.empty((threads, 4)),
        np.empty((threads, 3, 3)),
        np.empty((threads, 3)),
        np.empty((threads, 2, 3)),
        np.empty((threads, 2, 3)),
        np.empty((threads, 3, 3)),
        np.empty((threads, 3, 3)),
        np.empty((threads, 2, 2)),
        np.empty((threads, 2, 2)),
        np.empty((threads, 2, 3)),
    )


@njit(cache=True, parallel=True)
def _project(
    means, quats, log_scales, logits, rot, trans, cam, near, eps2d, means2d, conics, depths, log_op, extent, ok, threads
):
    """Forward: per Gaussian the pixel centre, conic, depth, log opacity, the box half-size outside
    which alpha < 1/255 and whether it can be drawn (in front, positive-definite, alpha can reach 1/255)."""
    ps, jacs, ms, qns, rqs, ss, ts, as_, _, _, _, _, _ = _scratch(threads)
    for i in prange(means.shape[0]):
        me = numba.get_thread_id()
        p, jac, m, t_mat, a_mat = ps[me], jacs[me], ms[me], ts[me], as_[me]
        in_front, zs, _, _, _, _ = _camera_terms(i, means, rot, trans, cam, near, p, jac)
        _gaussian_factor(i, quats, log_scales, m, qns[me], rqs[me], ss[me])
        _mm(_mm(jac, rot, t_mat), m, a_mat)  # cov2d = A A^T
        a = a_mat[0, 0] ** 2 + a_mat[0, 1] ** 2 + a_mat[0, 2] ** 2 + eps2d
        b = a_mat[0, 0] * a_mat[1, 0] + a_mat[0, 1] * a_mat[1, 1] + a_mat[0, 2] * a_mat[1, 2]
        c = a_mat[1, 0] ** 2 + a_mat[1, 1] ** 2 + a_mat[1, 2] ** 2 + eps2d
        det = a * c - b * b
        good = in_front and det > 0 and math.isfinite(det)
        det_safe = det if good else 1.0
        means2d[i, 0] = cam[0] * p[0] / zs + cam[2]
        means2d[i, 1] = cam[1] * p[1] / zs + cam[3]
        conics[i, 0], conics[i, 1], conics[i, 2] = c / det_safe, -b / det_safe, a / det_safe
        depths[i] = p[2]
        x = float(logits[i])
        lo = -math.log1p(math.exp(-x)) if x >= 0 else x - math.log1p(math.exp(x))  # log sigmoid, stable
        log_op[i] = lo
        level = lo - _LOG_ALPHA_MIN  # alpha >= 1/255 needs sigma <= level
        ok[i] = good and level > 0
        level = max(level, 0.0)
        extent[i, 0] = math.sqrt(2 * level * max(a, 0.0)) * 1.001 + 1e-3
        extent[i, 1] = math.sqrt(2 * level * max(c, 0.0)) * 1.001 + 1e-3


@njit(cache=True)
def _quat_backward(qn, dr, dqn):
    """``dqn [4]``: the gradient of the unit quaternion from that of its rotation matrix ``dr [3, 3]``."""
    w, x, y, z = qn[0], qn[1], qn[2], qn[3]
    dqn[0] = 2 * (-z * dr[0, 1] + y * dr[0, 2] + z * dr[1, 0] - x * dr[1, 2] - y * dr[2, 0] + x * dr[2, 1])
    dqn[1] = 2 * (
        y * dr[0, 1] + z * dr[0, 2] + y * dr[1, 0] - 2 * x * dr[1, 1] - w * dr[1, 2] + z * dr[2, 0]
        + w * dr[2, 1] - 2 * x * dr[2, 2]
    )  # fmt: skip
    dqn[2] = 2 * (
        -2 * y * dr[0, 0] + x * dr[0, 1] + w * dr[0, 2] + x * dr[1, 0] + z * dr[1, 2] - w * dr[2, 0]
        + z * dr[2, 1] - 2 * y * dr[2, 2]
    )  # fmt: skip
    dqn[3] = 2 * (
        -2 * z * dr[0, 0] - w * dr[0, 1] + x * dr[0, 2] + w * dr[1, 0] - 2 * z * dr[1, 1] + y * dr[1, 2]
        + x * dr[2, 0] + y * dr[2, 1]
    )  # fmt: skip


@njit(cache=True)
def _conic_backward(i, d_conics, cov, eps2d, in_front, d_cov):
    """``d_cov [2, 2]``: the gradient of the 2D covariance from that of Gaussian ``i``'s conic (``cov [2, 2]``
    is the covariance before ``eps2d``; an undrawable one is inverted with determinant 1, as the forward)."""
    a, b, c = cov[0, 0] + eps2d, cov[0, 1], cov[1, 1] + eps2d
    det = a * c - b * b
    if not (in_front and det > 0 and math.isfinite(det)):
        det = 1.0
    # conic = (c, -b, a) / det, the entries of S^-1 (off-diagonal once): dS = -S^-1 G S^-1.
    i00, i01, i11 = c / det, -b / det, a / det
    g00, g01, g11 = d_conics[i, 0], 0.5 * d_conics[i, 1], d_conics[i, 2]
    h00, h01, h10, h11 = i00 * g00 + i01 * g01, i00 * g01 + i01 * g11, i01 * g00 + i11 * g01, i01 * g01 + i11 * g11
    d_cov[0, 0] = -(h00 * i00 + h01 * i01)
    d_cov[0, 1] = d_cov[1, 0] = -(h00 * i01 + h01 * i11)
    d_cov[1, 1] = -(h10 * i01 + h11 * i11)


@njit(cache=True)
def _shape_backward(i, d_cov, t_mat, sigma, m, rq, s, qn, qnorm, out, tmp23, tmp33, dt23):
    """From ``d_cov`` through ``cov2d = T Sigma T^T`` and ``Sigma = M M^T``, ``M = Rq diag(s)``: Gaussian
    ``i``'s log scales and quaternion (``out[i, 3:10]``); returns ``dT [2, 3]`` (in ``dt23``). Overwrites
    ``sigma`` (with ``dM``), ``tmp23`` and ``tmp33``."""
    # cov2d = T Sigma T^T: dT = 2 dC T Sigma, dSigma = T^T dC T
    d_c_t = _mm(d_cov, t_mat, tmp23)
    d_t = _mm(d_c_t, sigma, dt23)
    for r in range(2):
        for col in range(3):
            d_t[r, col] *= 2.0
    d_sigma = _mm(t_mat.T, d_c_t, tmp33)
    # Sigma = M M^T, M = Rq diag(s): dM = 2 dSigma M (into sigma's buffer, no longer needed)
    d_m = _mm(d_sigma, m, sigma)
    for j in range(3):
        d_s = 2.0 * (d_m[0, j] * rq[0, j] + d_m[1, j] * rq[1, j] + d_m[2, j] * rq[2, j])
        out[i, 7 + j] = d_s * s[j]  # s = exp(log s)
        for r in range(3):
            d_m[r, j] *= 2.0 * s[j]  # now d Rq
    d_qn = out[i, 3:7]
    _quat_backward(qn, d_m, d_qn)
    proj = qn[0] * d_qn[0] + qn[1] * d_qn[1] + qn[2] * d_qn[2] + qn[3] * d_qn[3]
    for j in range(4):
        d_qn[j] = (d_qn[j] - qn[j] * proj) / qnorm  # q_unit = q / |q|
    return d_t


@njit(cache=True)
def _camera_backward(i, d_t, rot, jac, p, cam, terms, d_means2d, d_depths, tmp23, d_rot):
    """From ``dT`` (``T = J R``), the pixel and the depth of Gaussian ``i`` to its camera-frame centre: returns
    ``(dpx, dpy, dpz)`` and writes ``dR`` (this term of it) into ``d_rot [3, 3]``. ``terms``: what
    :func:`_camera_terms` returned. Overwrites ``tmp23``."""
    in_front, zs, clamped_x, clamped_y, tx, ty = terms
    # T = J R_cam: dJ = dT R^T, dR += J^T dT
    d_jac = _mm(d_t, rot.T, tmp23)
    _mm(jac.T, d_t, d_rot)
    fx, fy = cam[0], cam[1]
    d_zs = (
        -d_jac[0, 0] * fx / zs**2 + 2 * d_jac[0, 2] * fx * tx / zs**3
        - d_jac[1, 1] * fy / zs**2 + 2 * d_jac[1, 2] * fy * ty / zs**3
    )  # fmt: skip
    d_tx, d_ty = -d_jac[0, 2] * fx / zs**2, -d_jac[1, 2] * fy / zs**2
    # tx = zs clamp(x / zs): x where unclamped, zs * limit where clamped
    dpx = dpy = 0.0
    if clamped_x:
        d_zs += d_tx * tx / zs
    else:
        dpx += d_tx
    if clamped_y:
        d_zs += d_ty * ty / zs
    else:
        dpy += d_ty
    # pixel = (fx x / zs + cx, fy y / zs + cy); depth = z
    du, dv = d_means2d[i, 0], d_means2d[i, 1]
    dpx += du * fx / zs
    dpy += dv * fy / zs
    d_zs += -du * fx * p[0] / zs**2 - dv * fy * p[1] / zs**2
    dpz = d_depths[i] + (d_zs if in_front else 0.0)
    return dpx, dpy, dpz


@njit(cache=True, parallel=True)
def _project_backward(
    means,
    quats,
    log_scales,
    logits,
    rot,
    trans,
    cam,
    near,
    eps2d,
    d_means2d,
    d_conics,
    d_depths,
    d_logop,
    out,
    pose,
    threads,
):
    """Backward: ``out [N, 11]`` (means 3, quaternion 4, log scales 3, logit 1) and the pose's
    ``pose [threads, 12]`` (d rot row-major, then d trans), summed by the caller.

    The chain rule of :func:`_project` in the reverse order of its steps: the conic
    (:func:`_conic_backward`), the 3D covariance's shape (:func:`_shape_backward`), the camera
    (:func:`_camera_backward`), then the centre, the pose and the opacity here.
    """
    ps, jacs, ms, qns, rqs, ss, ts, tmp23s, sigmas, tmp33s, d_covs, tmp22s, dt23s = _scratch(threads)
    for i in prange(means.shape[0]):
        me = numba.get_thread_id()
        p, jac, m, qn, rq, s, t_mat = ps[me], jacs[me], ms[me], qns[me], rqs[me], ss[me], ts[me]
        tmp23, sigma, tmp33, d_cov, tmp22, dt23 = tmp23s[me], sigmas[me], tmp33s[me], d_covs[me], tmp22s[me], dt23s[me]
        terms = _camera_terms(i, means, rot, trans, cam, near, p, jac)
        qnorm = _gaussian_factor(i, quats, log_scales, m, qn, rq, s)
        _mm(jac, rot, t_mat)
        _mm(m, m.T, sigma)
        _mm(t_mat, sigma, tmp23)
        _mm(tmp23, t_mat.T, tmp22)  # cov2d without eps2d
        _conic_backward(i, d_conics, tmp22, eps2d, terms[0], d_cov)
        d_t = _shape_backward(i, d_cov, t_mat, sigma, m, rq, s, qn, qnorm, out, tmp23, tmp33, dt23)
        d_rot = tmp33
        dpx, dpy, dpz = _camera_backward(i, d_t, rot, jac, p, cam, terms, d_means2d, d_depths, tmp23, d_rot)
        # p = R m + t
        for j in range(3):
            out[i, j] = rot[0, j] * dpx + rot[1, j] * dpy + rot[2, j] * dpz
        for r, d_pr in enumerate((dpx, dpy, dpz)):
            for col in range(3):
                pose[me, 3 * r + col] += d_rot[r, col] + d_pr * means[i, col]
            pose[me, 9 + r] += d_pr
        out[i, 10] = d_logop[i] / (1.0 + math.exp(float(logits[i])))  # d log sigmoid(x) / dx = sigmoid(-x)


def _arr(x: torch.Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


_BACKWARD_READY: set[np.dtype] = set()


def _compile_backward(dtype: np.dtype) -> None:
    """Compile (or load from numba's cache) the backward kernel for ``dtype`` in the forward, not inside
    torch's autograd engine, where a Ctrl-C during code generation hangs the process (see
    :func:`ffrecon.splat.raster._compile_backward`)."""
    if dtype in _BACKWARD_READY:
        return
    z = np.zeros
    threads = numba.get_num_threads()
    grads = (z((1, 2)), z((1, 3)), z(1), z(1))
    inputs = (np.ones((1, 3), dtype), np.ones((1, 4), dtype), z((1, 3), dtype), z(1, dtype))
    pose = (np.eye(3), z(3), np.ones(6), 0.01, 0.3)
    _project_backward(*inputs, *pose, *grads, z((1, 11)), z((threads, 12)), threads)
    _BACKWARD_READY.add(dtype)


@dataclass(frozen=True)
class Projected:
    """Per-Gaussian screen-space quantities for one camera."""

    means2d: torch.Tensor  # [N, 2] pixels, COLMAP convention
    conics: torch.Tensor  # [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]], 1/pixels^2
    depths: torch.Tensor  # [N] camera-frame z of the centres
    log_opacity: torch.Tensor  # [N]
    extent: torch.Tensor  # [N, 2] half-size in pixels of the box outside which alpha < 1/255 (no grad)
    visible: torch.Tensor  # [N] bool: in front of the near plane and able to reach alpha 1/255


class _Project(torch.autograd.Function):
    """``(means, quats_wxyz, log_scales, opacity_logits, cam_from_world [3, 4]) -> (means2d, conics,
    depths, log_opacity, extent, visible)``; the last two carry no gradient."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, logits, cam_from_world, cam, near, eps2d):
        n, dtype = means.shape[0], means.dtype
        pose = cam_from_world.detach().double().numpy()
        rot, trans = np.ascontiguousarray(pose[:3, :3]), np.ascontiguousarray(pose[:3, 3])
        inputs = (_arr(means), _arr(quats), _arr(log_scales), _arr(logits))
        outs = [np.empty(shape, np.float64) for shape in ((n, 2), (n, 3), (n,), (n,), (n, 2))]
        ok = np.empty(n, np.bool_)
        _project(*inputs, rot, trans, cam, near, eps2d, *outs, ok, numba.get_num_threads())
        if any(ctx.needs_input_grad[:5]):
            _compile_backward(inputs[0].dtype)
        ctx.saved = (inputs, rot, trans, cam, near, eps2d)
        ctx.pose_shape = cam_from_world.shape
        result = [torch.from_numpy(o).to(dtype) for o in outs]
        ctx.mark_non_differentiable(result[4])
        visible = torch.from_numpy(ok)
        ctx.mark_non_differentiable(visible)
        return (*result, visible)

    @staticmethod
    def backward(ctx, d_means2d, d_conics, d_depths, d_logop, _extent, _visible):
        inputs, rot, trans, cam, near, eps2d = ctx.saved
        n, dtype = inputs[0].shape[0], d_means2d.dtype
        grads = [
            np.zeros(shape) if g is None else g.detach().double().contiguous().numpy()
            for g, shape in ((d_means2d, (n, 2)), (d_conics, (n, 3)), (d_depths, (n,)), (d_logop, (n,)))
        ]
        out = np.empty((n, 11))
        pose = np.zeros((numba.get_num_threads(), 12))
        _project_backward(*inputs, rot, trans, cam, near, eps2d, *grads, out, pose, pose.shape[0])
        out_t = torch.from_numpy(out).to(dtype)
        pose = pose.sum(0)
        d_pose = torch.zeros(ctx.pose_shape, dtype=dtype)
        d_pose[:3, :3] = torch.from_numpy(pose[:9].reshape(3, 3))
        d_pose[:3, 3] = torch.from_numpy(pose[9:])
        ctx.saved = None
        return out_t[:, :3], out_t[:, 3:7], out_t[:, 7:10], out_t[:, 10], d_pose, None, None, None


def project_gaussians(
    means: torch.Tensor,
    quats_wxyz: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    cam_from_world: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    near: float = 0.01,
    eps2d: float = 0.3,
) -> Projected:
    """EWA projection of 3D Gaussians (world frame) into a pinhole camera, on the CPU, differentiable in
    the Gaussians and ``cam_from_world`` (on CUDA the splat renders with gsplat instead).

    Args:
        means: ``[N, 3]`` world positions.
        quats_wxyz: ``[N, 4]`` rotations, scalar first, any norm.
        log_scales: ``[N, 3]``.
        opacity_logits: ``[N]``.
        cam_from_world: ``[3, 4]`` (or ``[4, 4]``) OpenCV pose; may require grad.
        K: ``[3, 3]`` intrinsics for ``width x height``.
    """
    k = K.detach().double()
    cam = np.array([float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), float(width), float(height)])
    args = (means, quats_wxyz, log_scales, opacity_logits, cam_from_world, cam, float(near), float(eps2d))
    return Projected(*_Project.apply(*args))
