"""Differentiable rendering of 3D Gaussians on the CPU: torch tensors in and out, compiled kernels inside.

``render`` is a pure function: EWA projection of each Gaussian to a 2D Gaussian
(:mod:`ffrecon.splat.project`), binning to tiles and depth-sorted alpha compositing
(:mod:`ffrecon.splat.raster`), each with a hand-written backward. Gradients reach means, rotations,
scales, opacities, colours / SH and, when the pose tensor requires grad, the camera pose.

Conventions: OpenCV camera, ``cam_from_world`` ``[3, 4]``, pinhole ``K`` for a ``width x height``
image with COLMAP's pixel-centre rule (the centre of pixel (row v, column u) is at (u + 0.5, v +
0.5)), so a Gaussian centred on camera point ``(x, y, z)`` lands at ``(fx x / z + cx, fy y / z +
cy)`` with no half-pixel terms. As in 3DGS and gsplat, the 2D covariance gets ``eps2d`` pixels^2
added on its diagonal (a low-pass filter), and the Jacobian is evaluated with x/z, y/z clamped to
1.3 times the field of view so Gaussians far outside it do not blow up.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from ffrecon.concurrency import interrupts_deferred
from ffrecon.gaussians import Gaussians, sh_to_rgb
from ffrecon.splat.optimize_options import RasterOptions  # defined there, without torch; still importable here
from ffrecon.splat.project import project_gaussians
from ffrecon.splat.raster import TileLayout, bin_gaussians, composite
from ffrecon.types import PinholeCamera


@dataclass(frozen=True)
class RenderOutput:
    rgb: torch.Tensor  # [H, W, 3] float32, composited over the background
    alpha: torch.Tensor  # [H, W] accumulated opacity, 1 - final transmittance
    depth: torch.Tensor | None  # [H, W] alpha-weighted camera z (divide by alpha for the mean depth)
    means2d: torch.Tensor  # [N, 2] projected centres; call .retain_grad() before backward for densification
    visible: torch.Tensor  # [N] bool, Gaussians that touched at least one tile
    extent: torch.Tensor  # [N, 2] pixels
    layout: TileLayout | None  # None from the gsplat adapter


def render(
    means: torch.Tensor,
    quats_wxyz: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    colors: torch.Tensor,
    cam_from_world: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    background: torch.Tensor | None = None,
    sh_degree: int | None = None,
    with_depth: bool = True,
    options: RasterOptions = RasterOptions(),
) -> RenderOutput:
    """Render N Gaussians (world frame) into one pinhole camera, differentiably.

    Args:
        means, quats_wxyz, log_scales, opacity_logits: as in :func:`project_gaussians`.
        colors: ``[N, 3]`` RGB, or ``[N, B, 3]`` SH coefficients when ``sh_degree`` is given
            (bands above ``sh_degree`` are ignored).
        cam_from_world: ``[3, 4]`` OpenCV pose; K: ``[3, 3]`` for a ``width x height`` image.
        background: ``[3]`` RGB behind everything (default black).
        with_depth: also composite the camera z (training leaves it off).
    Returns:
        :class:`RenderOutput` with ``rgb [H, W, 3]``, ``alpha [H, W]``, ``depth [H, W]`` (or None).
    """
    warm_up()
    dtype = means.dtype
    gaussians = (means, quats_wxyz, log_scales, opacity_logits)
    proj = project_gaussians(*gaussians, cam_from_world, K, width, height, near=options.near, eps2d=options.eps2d)
    rgb = _view_colors(colors, means, cam_from_world, sh_degree)
    screen = (proj.means2d, proj.conics, proj.log_opacity)
    layout = bin_gaussians(*screen, proj.extent, proj.depths, proj.visible, width, height, tile_size=options.tile_size)
    feat, bg = _features(rgb, proj.depths, background, with_depth, dtype)
    img, alpha = composite(*screen, feat, bg, layout, width, height)
    visible = torch.zeros(len(means), dtype=torch.bool)
    visible[torch.from_numpy(layout.pair_gauss)] = True
    return RenderOutput(
        rgb=img[..., :3],
        alpha=alpha,
        depth=img[..., 3] if with_depth else None,
        means2d=proj.means2d,
        visible=visible,
        extent=proj.extent,
        layout=layout,
    )


def _view_colors(
    colors: torch.Tensor, means: torch.Tensor, cam_from_world: torch.Tensor, sh_degree: int | None
) -> torch.Tensor:
    """``[N, 3]`` RGB of each Gaussian seen from the camera: ``colors`` as they are without ``sh_degree``,
    else the SH coefficients ``[N, B, 3]`` evaluated along the ray from the camera centre to the mean."""
    if sh_degree is None:
        return colors
    rot, trans = cam_from_world[:3, :3], cam_from_world[:3, 3]
    center = -(rot.T @ trans)
    dirs = torch.nn.functional.normalize(means - center, dim=1)
    return sh_to_rgb(colors, dirs, sh_degree)


def _features(
    rgb: torch.Tensor, depths: torch.Tensor, background: torch.Tensor | None, with_depth: bool, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(feat [N, F], background [F])`` to composite, in ``dtype``: RGB, and with ``with_depth`` the camera z
    (over a background depth of 0); the background is black when None."""
    feat = torch.cat([rgb, depths[:, None]], dim=1) if with_depth else rgb
    bg = torch.zeros(3, dtype=dtype) if background is None else background.to(dtype)
    if with_depth:
        bg = torch.cat([bg, bg.new_zeros(1)])
    return feat.to(dtype), bg


def render_view(
    g: Gaussians,
    cam_from_world: np.ndarray,
    camera: PinholeCamera,
    *,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    raster: RasterOptions | None = None,
) -> torch.Tensor:
    """``[H, W, 3]`` render of ``g`` seen by ``camera`` at ``cam_from_world [3, 4]``, on the CPU (no gradient)."""
    with torch.no_grad(), interrupts_deferred():
        out = render(
            g.means,
            g.quats_wxyz,
            g.log_scales,
            g.opacity_logits,
            g.sh,
            torch.tensor(cam_from_world, dtype=torch.float32),
            torch.tensor(camera.K, dtype=torch.float32),
            camera.width,
            camera.height,
            background=torch.tensor(background, dtype=torch.float32),
            sh_degree=g.sh_degree,
            with_depth=False,
            options=raster or RasterOptions(),
        )
    return out.rgb.clamp(0, 1)


_READY = False  # set once warm_up has run in this process


def warm_up() -> float:
    """Compile (first use) or load from numba's cache every CPU kernel a training step calls, on a tiny
    float32 scene, with Ctrl-C held until it is done (see :func:`interrupts_deferred`). Runs once per
    process: :func:`render` calls it, and an optimiser calls it before starting its clock so the cost is
    not counted. Returns the seconds it took (~10 s on first use, well under one from the cache, 0 after)."""
    global _READY
    if _READY:
        return 0.0
    _READY = True  # first: the warm-up renders through render() itself
    try:
        with interrupts_deferred(), torch.enable_grad():  # render() may be called under no_grad
            return _warm_up()
    except BaseException:
        _READY = False
        raise


def _warm_up() -> float:
    from ffrecon.splat.ssim import ssim_mean

    start = time.perf_counter()
    gen = torch.Generator().manual_seed(0)
    n = 4
    params = [
        (torch.rand(n, 3, generator=gen) - 0.5) + torch.tensor([0.0, 0.0, 3.0]),
        torch.rand(n, 4, generator=gen),
        torch.full((n, 3), -2.0),
        torch.zeros(n),
        torch.rand(n, 4, 3, generator=gen),
    ]
    for p in params:
        p.requires_grad_(True)
    K = torch.tensor([[20.0, 0.0, 8.0], [0.0, 20.0, 8.0], [0.0, 0.0, 1.0]])
    out = render(*params, torch.eye(4)[:3], K, 16, 16, sh_degree=1, with_depth=False)
    loss = ssim_mean(out.rgb.permute(2, 0, 1), torch.rand(3, 16, 16, generator=gen)) + out.rgb.mean()
    loss.backward()
    return time.perf_counter() - start
