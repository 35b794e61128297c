"""Depth Anything 3 (PyPI ``depth-anything-3``) to ONNX with ffrecon's ``da3`` contract.

Input ``images [S, 3, H, W]`` float32 RGB in [0, 1] (the wrapper applies DA3's ImageNet
normalisation); outputs ``depth [1, S, H, W]`` (z-depth), ``depth_conf [1, S, H, W]`` (>= 1),
``extrinsics [1, S, 3, 4]`` (OpenCV cam_from_world; the world is the camera of the reference view
DA3 picks, see :data:`REF_VIEW_STRATEGY`) and ``intrinsics [1, S, 3, 3]`` (network pixels). S is
dynamic; H and W are fixed per file. ``DepthAnything3Net.forward`` itself turns the camera decoder's
pose encoding into these matrices with upstream's ``pose_encoding_to_extri_intri`` and
``affine_inverse``, so the file outputs exactly what upstream's API returns before its numpy step.

What the TorchScript exporter cannot take as shipped, and what stands in for it during the trace
(each computes the same numbers; the verification compares with the unpatched code):

- reference-view selection runs only when ``x.shape[1] >= THRESH_FOR_REF_SELECTION`` (3), a Python
  branch the tracer would freeze at the traced frame count, and builds its indices with
  ``torch.arange(S)`` / ``torch.eye(S)``. :func:`export_rewrites` always takes the branch
  and applies the frame-count rule inside the graph (index 0 below 3 frames), with indices built
  from the data's own shape, so the same file is right for 1, 2 or many frames;
- ``utils.geometry.affine_inverse`` is a ``torch.jit.script`` function using ``Tensor.mT``, which
  has no ONNX symbolic: :func:`affine_inverse` (the same formula with ``transpose(-1, -2)``) stands
  in for it in ``model.da3``;
- DINOv2's position-table resize and the rotary ``cartesian_prod`` / ``int(positions.max())``:
  the shared rewrites in :mod:`.patches`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
from collections.abc import Iterator
from pathlib import Path

import torch

from ffrecon.errors import InputError
from ffrecon.models import da3 as contract
from ffrecon.models.exporting.common import ExportSpec, ModelExportOptions, random_images
from ffrecon.models.exporting.patches import frozen_position_embeddings
from ffrecon.models.exporting.upstream import import_upstream
from ffrecon.models.exporting.weights import load_into, load_state_dict

log = logging.getLogger("ffrecon.export_model")

INPUT_NAMES = (contract.INPUT_NAME,)
OUTPUT_NAMES = contract.OUTPUT_NAMES
PATCH_SIZE = contract.PATCH_SIZE
DEFAULT_SIZE_HW = (378, 504)  # a 4:3 landscape photo under the reference upper_bound_resize
IMAGENET_MEAN = (0.485, 0.456, 0.406)  # InputProcessor.NORMALIZE
IMAGENET_STD = (0.229, 0.224, 0.225)
REF_VIEW_STRATEGY = "saddle_balanced"  # upstream's default (api.inference, DepthAnything3Net.forward)
REF_SELECTION_MIN_FRAMES = 3  # depth_anything_3.utils.constants.THRESH_FOR_REF_SELECTION
# Configs with a camera decoder (the any-view series). Mono/metric/nested ones have no cameras.
CAMERA_CONFIGS = {384: "da3-small", 768: "da3-base", 1024: "da3-large", 1536: "da3-giant"}  # by ViT width
RANDOM_INIT_CONFIG = "da3-giant"  # the largest any-view model (1.15 B parameters, gs head dropped)
PLAUSIBLE_FOV_DEG = 60.0  # what --random-init gives the untrained camera decoder (its ReLU may give 0)
UNUSED_PREFIXES = ("gs_head.", "gs_adapter.")  # 3D Gaussian branch: not exported


class DA3ForOnnx(torch.nn.Module):
    """``images [S, 3, H, W]`` in [0, 1] to ``(depth, depth_conf, extrinsics, intrinsics)``."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN, dtype=torch.float32).view(3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD, dtype=torch.float32).view(3, 1, 1), persistent=False)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        x = ((images - self.mean) / self.std)[None]  # torchvision Normalize's arithmetic; [1, S, 3, H, W]
        out = self.net(x, None, None, [], False, False, REF_VIEW_STRATEGY)
        return out.depth, out.depth_conf, out.extrinsics, out.intrinsics


def config_name(options: ModelExportOptions) -> str:
    """Which upstream config to build: ``options.variant`` when given, else the checkpoint's, else the largest."""
    registry = import_upstream("depth_anything_3.registry", options.upstream, family="depth_anything_3").MODEL_REGISTRY
    name = getattr(options, "variant", None)  # ModelExportOptions.variant (proposed), e.g. "da3-large"
    if name is None and options.checkpoint is not None:
        name = _checkpoint_config_name(Path(options.checkpoint))
    name = name or RANDOM_INIT_CONFIG
    if name not in registry:
        raise InputError(f"'{name}' is not a Depth Anything 3 config", f"use one of: {', '.join(sorted(registry))}")
    if name not in CAMERA_CONFIGS.values():
        raise InputError(
            f"{name} has no camera decoder (a monocular, metric or nested model): ffrecon's da3 contract needs cameras",
            f"export one of {', '.join(CAMERA_CONFIGS.values())}",
        )
    return name


def _checkpoint_config_name(path: Path) -> str | None:
    """``model_name`` from a downloaded Hugging Face folder's config.json, else from the ViT width."""
    config = (path if path.is_dir() else path.parent) / "config.json"
    if config.is_file():
        try:
            name = json.loads(config.read_text()).get("model_name")
        except (json.JSONDecodeError, AttributeError) as exc:
            raise InputError(f"cannot read {config}: {exc}", "download the checkpoint folder again") from exc
        if name:
            return str(name)
    state = load_state_dict(path)
    token = next((v for k, v in state.items() if k.endswith("backbone.pretrained.cls_token")), None)
    return CAMERA_CONFIGS.get(int(token.shape[-1])) if token is not None else None


def build_tiny(upstream: Path | None) -> torch.nn.Module:
    """Upstream's own classes at a small configuration: the DA3-Small layout (DINOv2 with camera
    token, alternating local/global attention, QK-norm and RoPE from block 2, concatenated local
    and global tokens, DualDPT head, camera encoder/decoder) with 6 blocks of width 64."""
    da3 = import_upstream("depth_anything_3.model.da3", upstream, family="depth_anything_3")
    dinov2 = import_upstream("depth_anything_3.model.dinov2.dinov2", upstream, family="depth_anything_3")
    vit = import_upstream("depth_anything_3.model.dinov2.vision_transformer", upstream, family="depth_anything_3")
    dualdpt = import_upstream("depth_anything_3.model.dualdpt", upstream, family="depth_anything_3")
    cam_dec = import_upstream("depth_anything_3.model.cam_dec", upstream, family="depth_anything_3")
    cam_enc = import_upstream("depth_anything_3.model.cam_enc", upstream, family="depth_anything_3")
    dim, blocks, alt = 64, 6, 2
    backbone = dinov2.DinoV2.__new__(dinov2.DinoV2)  # DinoV2.__init__ always builds a 12-block ViT-S or larger
    torch.nn.Module.__init__(backbone)
    backbone.name, backbone.out_layers = "vits", [2, 3, 4, 5]
    backbone.alt_start = backbone.qknorm_start = backbone.rope_start = alt
    backbone.cat_token = True
    backbone.pretrained = vit.DinoVisionTransformer(
        img_size=518,
        patch_size=PATCH_SIZE,
        embed_dim=dim,
        depth=blocks,
        num_heads=2,
        mlp_ratio=4,
        alt_start=alt,
        qknorm_start=alt,
        rope_start=alt,
        cat_token=True,
    )
    head = dualdpt.DualDPT(dim_in=2 * dim, output_dim=2, features=16, out_channels=[8, 16, 32, 32])
    return da3.DepthAnything3Net(
        backbone,
        head,
        cam_dec=cam_dec.CameraDec(dim_in=2 * dim),
        cam_enc=cam_enc.CameraEnc(dim_out=dim, num_heads=2, trunk_depth=1),
    )


def build_net(options: ModelExportOptions) -> tuple[torch.nn.Module, str]:
    """The upstream ``DepthAnything3Net`` (weights loaded when a checkpoint is given) and its description."""
    if options.tiny:
        return build_tiny(options.upstream), "tiny configuration"
    cfg = import_upstream("depth_anything_3.cfg", options.upstream, family="depth_anything_3")
    registry = import_upstream("depth_anything_3.registry", options.upstream, family="depth_anything_3").MODEL_REGISTRY
    name = config_name(options)
    log.info("building Depth Anything 3 from upstream config %s", name)
    config = cfg.load_config(registry[name])
    for key in ("gs_head", "gs_adapter"):  # the 3D Gaussian branch runs only with infer_gs (and imports evo)
        if key in config:
            del config[key]
    net = cfg.create_object(config)
    net.gs_head = net.gs_adapter = None
    if options.checkpoint:
        state = load_state_dict(Path(options.checkpoint))
        if all(k.startswith("model.") for k in state):  # DepthAnything3 (the API class) holds the net as .model
            state = {k.removeprefix("model."): v for k, v in state.items()}
        load_into(net, _with_shared_names(net, state), ignore_prefixes=UNUSED_PREFIXES, source=options.checkpoint)
    return net, name


def _with_shared_names(net: torch.nn.Module, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``state`` plus every name of a tensor the net shares under several names.

    DualDPT reuses one LayerNorm in its four auxiliary output blocks; safetensors' ``save_model``
    (what the Hugging Face upload used) stores such a tensor under one of its names only.
    """
    groups: dict[int, list[str]] = {}
    for key, value in net.state_dict(keep_vars=True).items():
        groups.setdefault(value.data_ptr(), []).append(key)
    state = dict(state)
    for names in groups.values():
        present = next((n for n in names if n in state), None)
        for n in names:
            if present is not None and n not in state:
                state[n] = state[present]
    return state


def plausible_fov(net: torch.nn.Module, size_hw: tuple[int, int], fov_w_deg: float = PLAUSIBLE_FOV_DEG) -> str:
    """Give an untrained camera decoder a plausible field of view; returns the note for the metadata.

    ``CameraDec.fc_fov`` is ``Linear -> ReLU``: random weights give fov 0 (a focal of W/2 / 1e-6
    after upstream's clamp) for about half the outputs. Setting its bias to (fov_h, fov_w) of a
    ``fov_w_deg`` camera with square pixels keeps the random weights but centres the decoded fields
    of view there.
    """
    h, w = size_hw
    fov_w = math.radians(fov_w_deg)
    fov_h = 2 * math.atan(math.tan(fov_w / 2) * h / w)
    with torch.no_grad():
        net.cam_dec.fc_fov[0].bias.copy_(torch.tensor([fov_h, fov_w]))
    return (
        f"random weights; camera decoder fc_fov bias set to fov_h/fov_w {math.degrees(fov_h):.1f}/{fov_w_deg:.1f} deg "
        "so the untrained decoder gives a plausible focal"
    )


# ---------------------------------------------------------------------------------------------
# Reference-view selection in a form the tracer keeps dynamic (same values as upstream's).
# ---------------------------------------------------------------------------------------------


def _view_positions(x: torch.Tensor) -> torch.Tensor:
    """``[B, S]`` int64 ``0 .. S-1`` built from ``x``'s shape inside the graph (``x``: ``[B, S, ...]``)."""
    ones = torch.ones_like(x.reshape(x.shape[0], x.shape[1], -1)[:, :, 0], dtype=torch.int64)
    return torch.cumsum(ones, dim=1) - 1


def select_reference_view(x: torch.Tensor, strategy: str = REF_VIEW_STRATEGY) -> torch.Tensor:
    """``reference_view_selector.select_reference_view`` plus the caller's frame-count rule.

    ``x``: ``[B, S, N, C]`` tokens. Returns ``[B]`` int64: upstream's choice when S >= 3, else 0
    (upstream then does not select; index 0 leaves the order unchanged).
    """
    pos = _view_positions(x)
    count = pos[:, -1] + 1  # [B] = S
    if strategy == "first":
        return torch.zeros_like(count)
    if strategy == "middle":
        chosen = count // 2
    elif strategy in ("saddle_balanced", "saddle_sim_range"):
        feat = x[:, :, 0]
        img_class_feat = feat / feat.norm(dim=-1, keepdim=True)
        sim = torch.matmul(img_class_feat, img_class_feat.transpose(1, 2))
        eye = (pos[:, :, None] == pos[:, None, :]).to(sim.dtype)  # torch.eye(S)
        sim_no_diag = sim - eye
        if strategy == "saddle_balanced":
            sim_score = sim_no_diag.sum(dim=-1) / (count[:, None] - 1).to(sim.dtype)
            score = _balance(sim_score) + _balance(feat.norm(dim=-1)) + _balance(img_class_feat.var(dim=-1))
            chosen = score.argmin(dim=1)
        else:
            chosen = (sim_no_diag.max(dim=-1).values - sim_no_diag.min(dim=-1).values).argmax(dim=1)
    else:
        raise ValueError(f"unknown reference view strategy {strategy}")
    return torch.where(count >= REF_SELECTION_MIN_FRAMES, chosen, torch.zeros_like(chosen))


def _balance(metric: torch.Tensor) -> torch.Tensor:
    """``|normalize_metric(m) - 0.5|`` as in upstream's saddle_balanced score."""
    low = metric.min(dim=1, keepdim=True).values
    high = metric.max(dim=1, keepdim=True).values
    return ((metric - low) / (high - low + 1e-8) - 0.5).abs()


def _gather_views(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x[b, index[b, s]]`` for ``x [B, S, ...]`` and ``index [B, S]``."""
    shape = index.shape + (1,) * (x.dim() - 2)
    return torch.gather(x, 1, index.reshape(shape).expand_as(x))


def reorder_by_reference(x: torch.Tensor, b_idx: torch.Tensor) -> torch.Tensor:
    """Upstream's reorder (reference view first, the others in order) with dynamic indices."""
    pos = _view_positions(x)
    ref = b_idx[:, None]
    index = torch.where((pos > 0) & (pos <= ref), pos - 1, pos)
    return _gather_views(x, torch.where(pos == 0, ref.expand_as(pos), index))


def restore_original_order(x: torch.Tensor, b_idx: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`reorder_by_reference`, as upstream's restore."""
    pos = _view_positions(x)
    ref = b_idx[:, None]
    index = torch.where(pos < ref, pos + 1, pos)
    return _gather_views(x, torch.where(pos == ref, torch.zeros_like(pos), index))


def affine_inverse(A: torch.Tensor) -> torch.Tensor:
    """``utils.geometry.affine_inverse`` (``[..., 3 or 4, 4]``) without ``Tensor.mT``."""
    R = A[..., :3, :3]
    T = A[..., :3, 3:]
    P = A[..., 3:, :]
    R_t = R.transpose(-1, -2)
    return torch.cat([torch.cat([R_t, -R_t @ T], dim=-1), P], dim=-2)


@contextlib.contextmanager
def _replaced(owner: object, replacements: dict[str, object]) -> Iterator[None]:
    saved = {k: getattr(owner, k) for k in replacements}
    for k, v in replacements.items():
        setattr(owner, k, v)
    try:
        yield
    finally:
        for k, v in saved.items():
            setattr(owner, k, v)


@contextlib.contextmanager
def export_rewrites(upstream: Path | None) -> Iterator[None]:
    """Swap the rewrites above into DA3's modules for one export (originals restored on exit)."""
    vit = import_upstream("depth_anything_3.model.dinov2.vision_transformer", upstream, family="depth_anything_3")
    da3 = import_upstream("depth_anything_3.model.da3", upstream, family="depth_anything_3")
    if vit.THRESH_FOR_REF_SELECTION != REF_SELECTION_MIN_FRAMES:
        raise InputError(
            f"this depth_anything_3 selects a reference view from {vit.THRESH_FOR_REF_SELECTION} frames, "
            f"ffrecon's rewrite from {REF_SELECTION_MIN_FRAMES}",
            "install depth-anything-3==0.1.1, or report the version you use",
        )
    view_selection = {
        "THRESH_FOR_REF_SELECTION": 1,  # always take the branch; the frame-count rule is in select_reference_view
        "select_reference_view": select_reference_view,
        "reorder_by_reference": reorder_by_reference,
        "restore_original_order": restore_original_order,
    }
    with _replaced(vit, view_selection), _replaced(da3, {"affine_inverse": affine_inverse}):
        yield


def trace_context(upstream: Path | None):
    @contextlib.contextmanager
    def context(module: torch.nn.Module):
        with frozen_position_embeddings(module), export_rewrites(upstream):
            yield

    return context


def build(options: ModelExportOptions, size_hw: tuple[int, int]) -> ExportSpec:
    torch.manual_seed(options.seed)
    net, name = build_net(options)
    net = net.eval().float()
    notes = [
        f"reference view strategy {REF_VIEW_STRATEGY} from {REF_SELECTION_MIN_FRAMES} frames (upstream's default): "
        "extrinsics are relative to the chosen view"
    ]
    if options.checkpoint is None and not options.keep_untrained_heads:
        notes.append(plausible_fov(net, size_hw))
    elif options.checkpoint is None:
        notes.append("random weights; camera decoder left as initialised (its fov may decode to 0)")
    h, w = size_hw
    return ExportSpec(
        family="da3",
        module=DA3ForOnnx(net).eval(),
        input_names=INPUT_NAMES,
        output_names=OUTPUT_NAMES,
        dynamic_axes={INPUT_NAMES[0]: {0: "S"}, **{k: {1: "S"} for k in OUTPUT_NAMES}},
        make_inputs=lambda n, rng: (random_images(n, size_hw, rng),),
        size_hw=size_hw,
        contract="da3",
        description=f"Depth Anything 3 ({name}, weights: {options.weights}) exported by ffrecon export-model, "
        f"input {w}x{h}",
        notes=notes,
        extra_metadata={"ffrecon.da3.config": name, "ffrecon.da3.ref_view_strategy": REF_VIEW_STRATEGY},
        trace_context=trace_context(options.upstream),
    )


def size_for_photo(height: int, width: int) -> tuple[int, int]:
    """The network input size DA3's reference processing (upper_bound_resize, 504) gives a photo.

    >>> size_for_photo(480, 640), size_for_photo(640, 480), size_for_photo(3000, 4000)
    ((378, 504), (504, 378), (378, 504))
    """
    return contract.network_size_hw(height, width, contract.DEFAULT_METHOD)
