"""The Gaussian splat model: parameter tensors and real spherical harmonics.

Parameters are stored the way optimisers and the 3DGS PLY format want them (docs/contracts.md):
log scales, opacity logits, unnormalised rotation quaternions ``quat_wxyz`` (scalar first) and SH
coefficients whose band 0 is the DC term, ``rgb = 0.5 + SH_C0 * dc``. The basis and its signs are
the ones every 3DGS viewer uses, so a file written from these tensors looks the same everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi)), the constant band
SH_C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel up to ``degree`` (0..3).

    >>> [num_sh_bases(d) for d in range(4)]
    [1, 4, 9, 16]
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    return (degree + 1) ** 2


def rgb_to_sh_dc(rgb: torch.Tensor | np.ndarray):
    """Colour in [0, 1] to the DC coefficient (same type as the input).

    >>> float(rgb_to_sh_dc(np.array(0.5)))
    0.0
    """
    return (rgb - 0.5) / SH_C0


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis values for unit directions.

    Args:
        dirs: ``[N, 3]`` unit vectors (world frame, from the camera centre towards the Gaussian).
        degree: 0..3.
    Returns:
        ``[N, (degree + 1) ** 2]`` in the 3DGS ordering and sign convention.
    """
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def sh_to_rgb(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Evaluate colours ``[N, 3]`` (clamped at 0 below, as 3DGS does) from ``sh [N, B, 3]``.

    Only the first ``(degree + 1) ** 2`` coefficients are used, so higher bands can be switched on
    during optimisation.
    """
    n_bases = num_sh_bases(degree)
    basis = sh_basis(dirs, degree)  # [N, B']
    rgb = torch.einsum("nb,nbc->nc", basis, sh[:, :n_bases]) + 0.5
    return rgb.clamp_min(0.0)


@dataclass
class Gaussians:
    """A splat: N anisotropic 3D Gaussians (world frame). Mutable: the optimiser replaces tensors."""

    means: torch.Tensor  # [N, 3] float32, world frame
    quats_wxyz: torch.Tensor  # [N, 4] float32, unnormalised rotation (local to world)
    log_scales: torch.Tensor  # [N, 3] float32, log of the standard deviations along the local axes
    opacity_logits: torch.Tensor  # [N] float32, opacity = sigmoid(logit)
    sh: torch.Tensor  # [N, (d + 1) ** 2, 3] float32 SH coefficients, band 0 = DC

    PARAMS = ("means", "quats_wxyz", "log_scales", "opacity_logits", "sh")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return round(self.sh.shape[1] ** 0.5) - 1

    def detached(self) -> Gaussians:
        return Gaussians(**{k: getattr(self, k).detach().clone() for k in self.PARAMS})

    def to(self, device: str | torch.device) -> Gaussians:
        return Gaussians(**{k: getattr(self, k).to(device) for k in self.PARAMS})

    def subset(self, keep: torch.Tensor) -> Gaussians:
        """The Gaussians selected by a ``[N]`` bool mask or an index tensor (detached copies)."""
        return Gaussians(**{k: getattr(self, k).detach()[keep].clone() for k in self.PARAMS})

    def with_sh_degree(self, degree: int) -> Gaussians:
        """Pad with zero coefficients or truncate to ``degree``."""
        n_bases, have = num_sh_bases(degree), self.sh.shape[1]
        sh = self.sh.detach()
        if n_bases > have:
            sh = torch.cat([sh, sh.new_zeros(len(self), n_bases - have, 3)], dim=1)
        return Gaussians(
            self.means.detach(),
            self.quats_wxyz.detach(),
            self.log_scales.detach(),
            self.opacity_logits.detach(),
            sh[:, :n_bases].clone(),
        )

    def colors_dc(self) -> torch.Tensor:
        """``[N, 3]`` view-independent colour (band 0 only), clamped to [0, 1]."""
        return (0.5 + SH_C0 * self.sh[:, 0]).clamp(0.0, 1.0)

    @staticmethod
    def from_points(
        xyz: np.ndarray, rgb: np.ndarray, log_scales: np.ndarray, *, opacity: float = 0.1, sh_degree: int = 0
    ) -> Gaussians:
        """Isotropic, identity-rotation Gaussians at ``xyz [M, 3]`` with colours ``rgb [M, 3]`` in [0, 1].

        ``log_scales`` is ``[M]`` (isotropic) or ``[M, 3]``; ``opacity`` is the starting opacity.
        """
        m = len(xyz)
        ls = np.broadcast_to(np.asarray(log_scales, np.float32).reshape(m, -1), (m, 3))
        sh = np.zeros((m, num_sh_bases(sh_degree), 3), np.float32)
        sh[:, 0] = rgb_to_sh_dc(np.asarray(rgb, np.float32))
        quats = np.zeros((m, 4), np.float32)
        quats[:, 0] = 1.0
        logit = float(np.log(opacity / (1.0 - opacity)))
        return Gaussians(
            means=torch.as_tensor(np.asarray(xyz, np.float32)).clone(),
            quats_wxyz=torch.as_tensor(quats),
            log_scales=torch.from_numpy(np.array(ls, np.float32)),  # a copy: ls may be a read-only broadcast
            opacity_logits=torch.full((m,), logit, dtype=torch.float32),
            sh=torch.as_tensor(sh),
        )
