"""Pi3 (yyfz/Pi3) to ONNX with ffrecon's Pi3 contract (docs/models.md; docs/contracts.md, "Other multi-view families").

Input ``images [N, 3, H, W]`` float32 RGB in [0, 1]; outputs, exactly as ``Pi3.forward`` returns
them with its batch axis of 1: ``points [1, N, H, W, 3]`` (world frame of the call),
``local_points [1, N, H, W, 3]`` (each camera's frame), ``conf [1, N, H, W, 1]`` (a logit) and
``camera_poses [1, N, 4, 4]`` (world_from_cam, OpenCV axes). N is dynamic; H and W are fixed per file.

What the TorchScript exporter cannot take in Pi3, and what stands in for it during the trace only
(each rewrite gives upstream's numbers; the export is verified against the unpatched model):

- ``torch.cartesian_prod`` (the RoPE position grid) and DINOv2's antialiased bicubic resize of its
  position table: the shared rewrites in :mod:`.patches` (size-only tables, frozen per export).
- ``int(positions.max())`` in the slow PyTorch RoPE2D: size-only, frozen by the tracer (see patches).
- ``torch.svd`` in ``CameraHead.svd_orthogonalize`` has no ONNX operator: replaced by
  :func:`closest_rotation`, the same projection onto SO(3) (nearest rotation to the row-normalised
  3x3 output, reflection removed along the smallest singular direction) computed with unrolled
  Jacobi sweeps on ``M^T M``, which ONNX expresses with MatMul and element-wise ops.
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import torch
from torch import nn

from ffrecon.models import pi3 as contract
from ffrecon.models.exporting.common import ExportSpec, ModelExportOptions, random_images
from ffrecon.models.exporting.patches import frozen_position_embeddings
from ffrecon.models.exporting.upstream import import_upstream
from ffrecon.models.exporting.weights import load_into, load_state_dict

INPUT_NAMES = (contract.INPUT_NAME,)
OUTPUT_NAMES = ("points", "local_points", "conf", "camera_poses")
DEFAULT_SIZE_HW = contract.network_size_hw(480, 640)  # (434, 574): 4:3 photos under the reference pixel limit
PATCH_SIZE = contract.PATCH_SIZE
JACOBI_SWEEPS = 6  # 3x3 cyclic Jacobi converges quadratically: float32 is exact to rounding after ~4
PLAUSIBLE_FOV_DEG = 60.0  # what --random-init/--tiny give the untrained point head's rays


class Pi3ForOnnx(nn.Module):
    """``images [N, 3, H, W]`` in [0, 1] to Pi3's four outputs (leading batch axis of 1)."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        predictions = self.model(images[None])  # Pi3 takes [B, N, 3, H, W]
        return tuple(predictions[k] for k in OUTPUT_NAMES)


def build_tiny(upstream: Path | None) -> nn.Module:
    """A ``Pi3`` instance made of upstream's own classes at a small configuration.

    ``Pi3.__init__`` always builds a ViT-L encoder (and ``decoder_size='small'`` fails upstream), so
    the attributes it sets are set here with small parts: a 1-block DINOv2 with registers (antialiased
    position-table resize, as ViT-L/14-reg), two alternating frame/global ``BlockRope`` decoder
    blocks (Pi3 concatenates the last two), and 1-block point, confidence and camera decoders with
    ``LinearPts3d`` and ``CameraHead``. ``Pi3.forward`` and ``Pi3.decode`` then run unchanged.
    """
    pi3_mod = import_upstream("pi3.models.pi3", upstream, family="pi3")
    dim, heads = 32, 2
    model = pi3_mod.Pi3.__new__(pi3_mod.Pi3)
    nn.Module.__init__(model)
    model.encoder = _tiny_encoder(upstream, dim, heads)
    del model.encoder.mask_token  # as Pi3.__init__ does
    model.patch_size = PATCH_SIZE
    model.pos_type = "rope100"
    model.rope = pi3_mod.RoPE2D(freq=100.0)
    model.position_getter = pi3_mod.PositionGetter()
    model.decoder = nn.ModuleList([_tiny_decoder_block(pi3_mod, dim, heads, model.rope) for _ in range(2)])
    model.dec_embed_dim = dim
    model.patch_start_idx = 5
    model.register_token = nn.Parameter(torch.randn(1, 1, 5, dim) * 1e-6)
    head = dict(in_dim=2 * dim, dec_embed_dim=dim, dec_num_heads=heads, depth=1, rope=model.rope)
    model.point_decoder = pi3_mod.TransformerDecoder(out_dim=dim, **head)
    model.point_head = pi3_mod.LinearPts3d(patch_size=PATCH_SIZE, dec_embed_dim=dim, output_dim=3)
    model.conf_decoder = copy.deepcopy(model.point_decoder)
    model.conf_head = pi3_mod.LinearPts3d(patch_size=PATCH_SIZE, dec_embed_dim=dim, output_dim=1)
    model.camera_decoder = pi3_mod.TransformerDecoder(out_dim=dim, use_checkpoint=False, **head)
    model.camera_head = pi3_mod.CameraHead(dim=dim)
    model.register_buffer("image_mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
    model.register_buffer("image_std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
    return model


def _tiny_encoder(upstream: Path | None, dim: int, heads: int) -> nn.Module:
    """Upstream's 1-block DINOv2 with 4 registers, antialiased position-table resize (as ViT-L/14-reg)."""
    vit_mod = import_upstream("pi3.models.dinov2.models.vision_transformer", upstream, family="pi3")
    dino_block = import_upstream("pi3.models.dinov2.layers.block", upstream, family="pi3")
    dino_attn = import_upstream("pi3.models.dinov2.layers.attention", upstream, family="pi3")
    return vit_mod.DinoVisionTransformer(
        img_size=518,
        patch_size=PATCH_SIZE,
        embed_dim=dim,
        depth=1,
        num_heads=heads,
        mlp_ratio=4,
        init_values=1.0,
        block_chunks=0,
        block_fn=partial(dino_block.Block, attn_class=dino_attn.MemEffAttention),
        num_register_tokens=4,
        interpolate_antialias=True,
        interpolate_offset=0.0,
    )


def _tiny_decoder_block(pi3_mod, dim: int, heads: int, rope: nn.Module) -> nn.Module:
    """One of upstream's ``BlockRope`` decoder blocks, configured as ``Pi3.__init__`` configures them."""
    return pi3_mod.BlockRope(
        dim=dim,
        num_heads=heads,
        mlp_ratio=4,
        qkv_bias=True,
        proj_bias=True,
        ffn_bias=True,
        drop_path=0.0,
        norm_layer=partial(nn.LayerNorm, eps=1e-6),
        act_layer=nn.GELU,
        ffn_layer=pi3_mod.Mlp,
        init_values=0.01,
        qk_norm=True,
        attn_class=pi3_mod.FlashAttentionRope,
        rope=rope,
    )


def plausible_rays(model: nn.Module, size_hw: tuple[int, int], fov_deg: float = PLAUSIBLE_FOV_DEG) -> str:
    """Give an untrained point head rays that upstream's focal recovery reads as a pinhole camera.

    ``local_points = (x z, y z, z)`` with ``(x, y, log z)`` from a per-token linear layer unshuffled
    into 14x14 pixels. With random weights, ``x`` and ``y`` do not grow with the pixel column and
    row, so the least-squares focal (:func:`ffrecon.models.pi3.focal_from_local_points`) is near 0
    or negative. Here the x/y rows of that layer are zeroed and their biases set to each sub-pixel's
    offset from its patch centre divided by the focal of a ``fov_deg`` camera at the export's
    width: each patch then holds an exact pinhole ray fan, and the fit returns that focal for both
    axes (the sums over patches cancel). Depth (the log-z rows), confidence and poses stay random.
    Returns the note for the metadata.
    """
    proj = (
        model.point_head.proj
    )  # Linear(dim, 3 * 14 * 14); output channel c of sub-pixel (i, j) is row c*196 + i*14 + j
    p = PATCH_SIZE
    offsets = torch.arange(p, dtype=torch.float32) - (p - 1) / 2
    focal = (size_hw[1] / 2) / math.tan(math.radians(fov_deg) / 2)
    with torch.no_grad():
        proj.weight[: 2 * p * p] = 0.0
        proj.bias[: p * p] = (offsets[None, :] / focal).expand(p, p).reshape(-1)  # x: column offset
        proj.bias[p * p : 2 * p * p] = (offsets[:, None] / focal).expand(p, p).reshape(-1)  # y: row offset
    return (
        f"random weights; point head x/y rows zeroed and their biases set to a pinhole ray fan per 14x14 patch "
        f"(focal {focal:.1f} px: {fov_deg:g} deg over the {size_hw[1]} px width) "
        "so the untrained rays decode to a plausible focal"
    )


def closest_rotation(m: torch.Tensor, sweeps: int = JACOBI_SWEEPS) -> torch.Tensor:
    """``CameraHead.svd_orthogonalize`` without ``torch.svd``: the rotation nearest the row-normalised ``m``.

    Args:
        m: ``[B, 9]`` or ``[B, 3, 3]`` float32 (the camera head's 9-D rotation output).
    Returns:
        ``[B, 3, 3]`` rotations: ``U diag(1, 1, det(U V^T)) V^T`` for ``M = U S V^T`` (singular
        values descending), ``M = normalize(m, dim=-1)``; the same matrix upstream's SVD form gives.

    ``M^T M = V S^2 V^T`` is diagonalised by ``sweeps`` cyclic Jacobi rotations, its eigenpairs are
    sorted descending by three compare-and-swaps, then ``u_i = M v_i / s_i`` (Gram-Schmidt for the
    second) and ``u_3 = det(V) (u_1 x u_2)`` so that ``det R = +1``. The smallest singular direction
    never needs dividing by its (possibly tiny) singular value.
    """
    m = nn.functional.normalize(m.reshape(-1, 3, 3), p=2, dim=-1)
    a = m.transpose(-1, -2) @ m
    v = torch.eye(3, dtype=m.dtype).expand_as(a)
    eye = torch.eye(3, dtype=m.dtype)
    for _ in range(sweeps):
        for p, q in ((0, 1), (0, 2), (1, 2)):
            diag = torch.zeros(3, 3, dtype=m.dtype)
            diag[p, p] = diag[q, q] = 1.0
            anti = torch.zeros(3, 3, dtype=m.dtype)
            anti[p, q], anti[q, p] = 1.0, -1.0
            apq, app, aqq = a[:, p, q], a[:, p, p], a[:, q, q]
            nonzero = apq.abs() > 1e-30
            theta = (aqq - app) / torch.where(nonzero, 2 * apq, torch.ones_like(apq))
            sign = torch.where(theta >= 0, torch.ones_like(theta), -torch.ones_like(theta))
            t = torch.where(nonzero, sign / (theta.abs() + torch.sqrt(theta * theta + 1)), torch.zeros_like(theta))
            c = 1 / torch.sqrt(t * t + 1)
            jac = (
                eye + (c - 1)[:, None, None] * diag + (t * c)[:, None, None] * anti
            )  # [[c, s], [-s, c]] in the (p, q) plane
            a = jac.transpose(-1, -2) @ a @ jac
            v = v @ jac
    lam = torch.diagonal(a, dim1=-2, dim2=-1)
    cols = [v[:, :, 0], v[:, :, 1], v[:, :, 2]]
    vals = [lam[:, 0], lam[:, 1], lam[:, 2]]
    for i, j in ((0, 1), (1, 2), (0, 1)):  # sort descending
        swap = vals[i] < vals[j]
        vals[i], vals[j] = torch.where(swap, vals[j], vals[i]), torch.where(swap, vals[i], vals[j])
        cols[i], cols[j] = torch.where(swap[:, None], cols[j], cols[i]), torch.where(swap[:, None], cols[i], cols[j])
    v1, v2, v3 = cols
    u1 = nn.functional.normalize((m @ v1[:, :, None])[:, :, 0], dim=-1)
    b2 = (m @ v2[:, :, None])[:, :, 0]
    u2 = nn.functional.normalize(b2 - (u1 * b2).sum(-1, keepdim=True) * u1, dim=-1)
    det_v = (v1 * _cross(v2, v3)).sum(-1, keepdim=True)
    u3 = torch.where(det_v >= 0, torch.ones_like(det_v), -torch.ones_like(det_v)) * _cross(u1, u2)
    return u1[:, :, None] * v1[:, None, :] + u2[:, :, None] * v2[:, None, :] + u3[:, :, None] * v3[:, None, :]


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``[..., 3]`` cross product from slices (``torch.linalg.cross`` has no ONNX symbolic)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], dim=-1)


@contextlib.contextmanager
def svd_free_camera_head(model: nn.Module) -> Iterator[int]:
    """Route every ``CameraHead.svd_orthogonalize`` in ``model`` through :func:`closest_rotation`.

    Instance attributes shadow the method for the duration; yields how many heads were patched.
    """
    heads = [sub for sub in model.modules() if callable(getattr(sub, "svd_orthogonalize", None))]
    for head in heads:
        head.svd_orthogonalize = closest_rotation
    try:
        yield len(heads)
    finally:
        for head in heads:
            del head.svd_orthogonalize


@contextlib.contextmanager
def trace_context(module: nn.Module) -> Iterator[None]:
    """Pi3's rewrites for the trace: DINOv2's frozen position table and the SVD-free camera head."""
    with frozen_position_embeddings(module), svd_free_camera_head(module):
        yield


def build(options: ModelExportOptions, size_hw: tuple[int, int]) -> ExportSpec:
    torch.manual_seed(options.seed)
    notes: list[str] = []
    if options.tiny:
        model = build_tiny(options.upstream)
    else:
        pi3_mod = import_upstream("pi3.models.pi3", options.upstream, family="pi3")
        model = pi3_mod.Pi3()  # ViT-L encoder, 36-block 'large' decoder: the published checkpoint's architecture
        if options.checkpoint:
            load_into(model, load_state_dict(Path(options.checkpoint)), source=options.checkpoint)
    model = model.eval().float()
    if options.checkpoint is None and not options.keep_untrained_heads:
        notes.append(plausible_rays(model, size_hw))
    elif options.checkpoint is None:
        notes.append("random weights; point head left as initialised (its rays may decode to no usable focal)")
    notes.append("camera head: torch.svd replaced in the trace by an equivalent Jacobi-based projection onto SO(3)")
    kind = "tiny configuration" if options.tiny else "Pi3 architecture (ViT-L encoder, large decoder)"
    return ExportSpec(
        family="pi3",
        module=Pi3ForOnnx(model).eval(),
        input_names=INPUT_NAMES,
        output_names=OUTPUT_NAMES,
        dynamic_axes={INPUT_NAMES[0]: {0: "N"}, **{k: {1: "N"} for k in OUTPUT_NAMES}},
        make_inputs=lambda n, rng: (random_images(n, size_hw, rng),),
        size_hw=size_hw,
        contract="pi3",
        description=f"Pi3 ({kind}, weights: {options.weights}) exported by ffrecon export-model, "
        f"input {size_hw[1]}x{size_hw[0]}",
        notes=notes,
        trace_context=trace_context,
    )


def size_for_photo(height: int, width: int) -> tuple[int, int]:
    """The network input size Pi3's reference preprocessing (``load_images_as_tensor``) gives a photo."""
    return contract.network_size_hw(height, width)
