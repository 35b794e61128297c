"""Optional CUDA rasteriser: an adapter from ffrecon's :func:`~ffrecon.splat.render.render` API to
gsplat's ``rasterization`` (install ``ffrecon[gpu]``; imported lazily, only when used).

gsplat takes world-to-camera 4x4 matrices (``viewmats``), batched intrinsics (``Ks``), linear scales
and opacities in [0, 1]; those names stay inside this module. Its conventions match the CPU renderer
(OpenCV camera, pixel centres at +0.5, ``eps2d`` low-pass, alpha clamp 0.999, cut at 1/255, SH with
+0.5 and a clamp at 0); it also stops compositing once the transmittance falls below 1e-4, which the
CPU renderer does not, so the two differ by at most about 1e-4 per channel there.
"""

from __future__ import annotations

import importlib.util
import logging

import numpy as np
import torch

from ffrecon.gaussians import Gaussians
from ffrecon.splat.render import RasterOptions, RenderOutput, render_view
from ffrecon.types import PinholeCamera

logger = logging.getLogger("ffrecon.splat")


def gsplat_available() -> bool:
    """True when CUDA is usable and the ``gsplat`` package is installed."""
    return torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


def render_gsplat(
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
    options: RasterOptions | None = None,
) -> RenderOutput:
    """Same inputs and outputs as :func:`ffrecon.splat.render.render`, on CUDA tensors via gsplat.

    ``RenderOutput.layout`` is None here (gsplat bins internally) and ``means2d`` is gsplat's
    ``[1, N, 2]`` tensor (the one in the graph, so ``retain_grad()`` on it works).
    """
    import gsplat  # optional dependency: ffrecon[gpu]

    options = options or RasterOptions()
    device = means.device
    dtype = means.dtype
    cam_from_world_4x4 = torch.eye(4, device=device, dtype=dtype)  # what gsplat calls a "viewmat"
    cam_from_world_4x4[:3] = cam_from_world[:3].to(dtype)
    bg = (
        torch.zeros(3, device=device, dtype=dtype) if background is None else background.to(device=device, dtype=dtype)
    )  # gsplat appends depth's 0
    colors_gs = colors[:, : (sh_degree + 1) ** 2] if sh_degree is not None else colors
    out, alphas, meta = gsplat.rasterization(
        means=means,
        quats=quats_wxyz,  # gsplat: wxyz, normalised inside
        scales=torch.exp(log_scales),
        opacities=torch.sigmoid(opacity_logits),
        colors=colors_gs,
        viewmats=cam_from_world_4x4[None],
        Ks=K.to(dtype)[None],
        width=width,
        height=height,
        near_plane=options.near,
        eps2d=options.eps2d,
        sh_degree=sh_degree,
        packed=False,
        tile_size=16,
        backgrounds=bg[None],
        render_mode="RGB+D" if with_depth else "RGB",
        rasterize_mode="classic",
    )
    means2d = meta["means2d"]  # [1, N, 2]: keep the tensor of the graph so that retain_grad() works
    radii = meta["radii"].reshape(1, len(means), -1)[0]
    visible = (radii > 0).any(dim=-1)
    img = out[0]
    return RenderOutput(
        rgb=img[..., :3],
        alpha=alphas[0, ..., 0],
        depth=img[..., 3] if with_depth else None,
        means2d=means2d,
        visible=visible,
        extent=radii.float().expand(-1, 2) if radii.shape[-1] == 1 else radii.float(),
        layout=None,
    )


def render_view_on(
    device: str,
    g: Gaussians,
    cam_from_world: np.ndarray,
    camera: PinholeCamera,
    *,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    raster: RasterOptions | None = None,
) -> torch.Tensor:
    """:func:`~ffrecon.splat.render.render_view` on ``device``: ``"cuda"`` renders with gsplat (``g`` is
    moved there unless it is there already; move it once before rendering many views), anything else with
    the CPU renderer. Returns ``[H, W, 3]`` in [0, 1] on the CPU, no gradient."""
    if device != "cuda":
        return render_view(g, cam_from_world, camera, background=background, raster=raster)
    g = g.to("cuda")
    with torch.no_grad():
        out = render_gsplat(
            g.means,
            g.quats_wxyz,
            g.log_scales,
            g.opacity_logits,
            g.sh,
            torch.tensor(cam_from_world, dtype=torch.float32, device="cuda"),
            torch.tensor(camera.K, dtype=torch.float32, device="cuda"),
            camera.width,
            camera.height,
            background=torch.tensor(background, dtype=torch.float32, device="cuda"),
            sh_degree=g.sh_degree,
            with_depth=False,
            options=raster or RasterOptions(),
        )
    return out.rgb.clamp(0, 1).cpu()
