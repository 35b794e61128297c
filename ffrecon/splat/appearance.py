"""Per-image colour: affine exposure and white-balance changes, learnt or fitted.

Real photos change exposure and white balance from frame to frame. Both uses here model such a
change as one affine map of the stored RGB values, ``c' = A c + b`` with ``A [3, 3]`` and ``b [3]``,
kept together as a ``[3, 4]`` matrix ``[A | b]`` (identity: ``[I | 0]``):

- while optimising, each training image has one, applied to the rendered colours before the
  photometric loss and pulled towards the identity (:func:`appearance_penalty`); the Gaussians then
  hold the colours common to all images, and the exported splat carries no per-image part;
- when scoring a held-out image, whose own exposure nobody learnt, :func:`fit_color_transform` fits
  one by least squares from the render to the photo before the colour-corrected PSNR and SSIM.

:func:`random_color_changes` and :func:`change_photo_colors` make such changes on purpose, for tests
and benchmarks.
"""

from __future__ import annotations

import numpy as np
import torch


def identity_transforms(num: int, *, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
    """``[num, 3, 4]`` copies of ``[I | 0]``.

    >>> identity_transforms(2)[1]
    tensor([[1., 0., 0., 0.],
            [0., 1., 0., 0.],
            [0., 0., 1., 0.]])
    """
    eye = torch.eye(3, 4, dtype=dtype, device=device)
    return eye.expand(num, 3, 4).clone()


def apply_color_transform(rgb: torch.Tensor, transform: torch.Tensor) -> torch.Tensor:
    """``A c + b`` for every colour ``c`` of ``rgb [..., 3]``, with ``transform [3, 4] = [A | b]``.

    No clamping (the optimiser needs the gradient of out-of-range values too).

    >>> apply_color_transform(torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([[2.0, 0, 0, 0.1]] + [[0, 1.0, 0, 0]] * 2))
    tensor([[1.1000, 0.5000, 0.5000]])
    """
    return rgb @ transform[:, :3].T + transform[:, 3]


def appearance_penalty(transform: torch.Tensor) -> torch.Tensor:
    """Squared Frobenius distance of ``transform [..., 3, 4]`` from ``[I | 0]`` (summed over leading dims).

    >>> round(float(appearance_penalty(torch.eye(3, 4) * 1.1)), 6)
    0.03
    """
    return ((transform - torch.eye(3, 4, dtype=transform.dtype, device=transform.device)) ** 2).sum()


def fit_color_transform(source: torch.Tensor, target: torch.Tensor, *, ridge: float = 1e-4) -> torch.Tensor:
    """``[3, 4]`` float64 ``[A | b]`` mapping the colours of ``source`` to those of ``target`` by least squares.

    Minimises ``mean_p ||A s_p + b - t_p||^2 + ridge ||[A | b] - [I | 0]||^2`` in closed form (ridge
    regression towards the identity, so a flat or tiny image gives a tame answer). Pixels where
    ``target`` is clipped (a channel at 0 or 1) do not follow an affine change and are left out when
    at least 16 others remain.

    Args:
        source: ``[H, W, 3]`` (or ``[P, 3]``) float RGB in [0, 1], e.g. a render.
        target: the same shape, e.g. the photo.

    >>> src = torch.rand(100, 3, generator=torch.Generator().manual_seed(0))
    >>> dst = src * torch.tensor([0.8, 1.0, 1.2]) * 0.7 + 0.1
    >>> fit_color_transform(src, dst, ridge=0.0).diagonal().round(decimals=3)
    tensor([0.5600, 0.7000, 0.8400], dtype=torch.float64)
    """
    s = source.reshape(-1, 3).double()
    t = target.reshape(-1, 3).double()
    unclipped = ((t > 0) & (t < 1)).all(dim=1)
    if int(unclipped.sum()) >= 16:
        s, t = s[unclipped], t[unclipped]
    x = torch.cat([s, torch.ones_like(s[:, :1])], dim=1)  # [P, 4]
    prior = torch.eye(4, 3, dtype=torch.float64, device=x.device)  # [I | 0] transposed
    n = len(x)
    lhs = x.T @ x + ridge * n * torch.eye(4, dtype=torch.float64, device=x.device)
    rhs = x.T @ t + ridge * n * prior
    return torch.linalg.solve(lhs, rhs).T


def random_color_changes(
    num: int, *, gain_spread: float = 0.3, offset_spread: float = 0.03, seed: int = 0
) -> np.ndarray:
    """``[num, 3, 4]`` float64 synthetic exposure and white-balance changes, for tests and benchmarks.

    Each ``[A | b]`` has a diagonal ``A`` (per-channel gains uniform in ``[1 - gain_spread, 1 + gain_spread]``)
    and ``b`` uniform in ``[-offset_spread, offset_spread]`` (RGB in [0, 1]).

    >>> changes = random_color_changes(4, seed=1)
    >>> changes.shape, bool(np.all(np.abs(changes[:, :, 3]) <= 0.03))
    ((4, 3, 4), True)
    """
    rng = np.random.default_rng(seed)
    gains = rng.uniform(1 - gain_spread, 1 + gain_spread, (num, 3))
    offsets = rng.uniform(-offset_spread, offset_spread, (num, 3))
    return np.concatenate([gains[:, :, None] * np.eye(3), offsets[:, :, None]], axis=2)


def change_photo_colors(image: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """``image [H, W, 3]`` uint8 RGB after ``transform [3, 4]`` (on values in [0, 1]), rounded and clipped.

    >>> change_photo_colors(np.full((1, 1, 3), 100, np.uint8), np.eye(3, 4) * 2)[0, 0]
    array([200, 200, 200], dtype=uint8)
    """
    rgb = image.astype(np.float64) / 255.0
    out = rgb @ transform[:, :3].T + transform[:, 3]
    return np.clip(np.rint(255.0 * out), 0, 255).astype(np.uint8)
