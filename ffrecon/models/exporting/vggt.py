"""VGGT (facebookresearch/vggt) to ONNX with the VGGT contract (docs/contracts.md, "Multi-view models").

Input ``input_images [S, 3, H, W]`` float32 RGB in [0, 1]; outputs ``pose_enc [1, S, 9]``,
``depth [1, S, H, W, 1]``, ``depth_conf [1, S, H, W]``, ``world_points [1, S, H, W, 3]``,
``world_points_conf [1, S, H, W]``. S is dynamic; H and W are fixed per file.
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path

import torch

from ffrecon.models import vggt as contract
from ffrecon.models.exporting.common import ExportSpec, ModelExportOptions, random_images
from ffrecon.models.exporting.patches import frozen_functions, frozen_position_embeddings
from ffrecon.models.exporting.upstream import import_upstream
from ffrecon.models.exporting.weights import load_into, load_state_dict

INPUT_NAMES = (contract.INPUT_NAME,)
OUTPUT_NAMES = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")
DEFAULT_SIZE_HW = (392, 518)  # 4:3 photos in the reference crop mode
PATCH_SIZE = contract.PATCH_SIZE
PLAUSIBLE_FOV_DEG = 60.0  # what --random-init gives the untrained camera head (its ReLU would give 0)
CAMERA_ITERATIONS = 4  # CameraHead.forward's default refinement iterations


class VGGTForOnnx(torch.nn.Module):
    """``input_images [S, 3, H, W]`` in [0, 1] to the contract outputs (leading batch axis of 1)."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, input_images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        predictions = self.model(input_images)  # VGGT adds the batch axis to [S, 3, H, W] itself
        return tuple(predictions[k] for k in OUTPUT_NAMES)


def build_tiny(upstream: Path | None, size_hw: tuple[int, int]) -> torch.nn.Module:
    """Upstream's own classes at a small configuration (the aggregator, camera head and DPT heads of
    VGGT-1B with fewer and narrower layers, a 1-block DINOv2 patch embedding) without the track head."""
    vggt_mod = import_upstream("vggt.models.vggt", upstream, family="vggt")
    aggregator_mod = import_upstream("vggt.models.aggregator", upstream, family="vggt")
    vit_mod = import_upstream("vggt.layers.vision_transformer", upstream, family="vggt")
    camera_mod = import_upstream("vggt.heads.camera_head", upstream, family="vggt")
    dpt_mod = import_upstream("vggt.heads.dpt_head", upstream, family="vggt")
    dim = 64
    model = vggt_mod.VGGT.__new__(vggt_mod.VGGT)  # VGGT.__init__ always builds the 1.2 B-parameter parts
    torch.nn.Module.__init__(model)
    model.aggregator = aggregator_mod.Aggregator(
        img_size=max(size_hw), patch_size=14, embed_dim=dim, depth=4, num_heads=4, patch_embed="conv"
    )
    # The full model embeds patches with DINOv2 (learnt position table, bicubic resize); keep that op path.
    model.aggregator.patch_embed = vit_mod.DinoVisionTransformer(
        img_size=518,
        patch_size=14,
        embed_dim=dim,
        depth=1,
        num_heads=4,
        num_register_tokens=4,
        block_chunks=0,
        init_values=1.0,
        interpolate_antialias=True,
    )
    model.camera_head = camera_mod.CameraHead(dim_in=2 * dim, trunk_depth=1, num_heads=4)
    dpt = dict(dim_in=2 * dim, features=32, out_channels=[16, 32, 64, 64], intermediate_layer_idx=[0, 1, 2, 3])
    model.depth_head = dpt_mod.DPTHead(output_dim=2, activation="exp", conf_activation="expp1", **dpt)
    model.point_head = dpt_mod.DPTHead(output_dim=4, activation="inv_log", conf_activation="expp1", **dpt)
    model.track_head = None
    return model


def plausible_fov(model: torch.nn.Module, size_hw: tuple[int, int], fov_w_deg: float = PLAUSIBLE_FOV_DEG) -> str:
    """Give an untrained camera head a plausible field of view; returns the note for the metadata.

    The head's last layer outputs a delta per refinement iteration and the encoding's field of view
    goes through a ReLU, so random weights give fov 0 (infinite focal) about half the time. Setting
    the bias of the fov outputs to fov/iterations (square pixels: fov_h from fov_w and the aspect)
    makes the decoded camera plausible; the other weights stay random.
    """
    h, w = size_hw
    fov_w = math.radians(fov_w_deg)
    fov_h = 2 * math.atan(math.tan(fov_w / 2) * h / w)
    with torch.no_grad():
        bias = model.camera_head.pose_branch.fc2.bias
        bias[7] = fov_h / CAMERA_ITERATIONS
        bias[8] = fov_w / CAMERA_ITERATIONS
    return (
        f"random weights; camera head fc2 bias of fov_h/fov_w set to {math.degrees(fov_h):.1f}/{fov_w_deg:.1f} deg "
        f"over {CAMERA_ITERATIONS} iterations so the untrained head decodes to a plausible focal"
    )


def trace_context(upstream: Path | None):
    """VGGT's size-only tables: DINOv2's position table and the DPT heads' float64 sin-cos embedding."""
    dpt_mod = import_upstream("vggt.heads.dpt_head", upstream, family="vggt")

    @contextlib.contextmanager
    def context(module: torch.nn.Module):
        with frozen_position_embeddings(module), frozen_functions((dpt_mod, "position_grid_to_embed")):
            yield

    return context


def build(options: ModelExportOptions, size_hw: tuple[int, int]) -> ExportSpec:
    torch.manual_seed(options.seed)
    notes: list[str] = []
    if options.tiny:
        model = build_tiny(options.upstream, size_hw)
    else:
        vggt_mod = import_upstream("vggt.models.vggt", options.upstream, family="vggt")
        model = vggt_mod.VGGT(enable_track=False)  # the track head needs query points; ffrecon does not export it
        if options.checkpoint:
            load_into(
                model,
                load_state_dict(Path(options.checkpoint)),
                ignore_prefixes=("track_head.",),
                source=options.checkpoint,
            )
    model = model.eval().float()
    if options.checkpoint is None and not options.keep_untrained_heads:
        notes.append(plausible_fov(model, size_hw))
    elif options.checkpoint is None:
        notes.append("random weights; camera head left as initialised (its fov may decode to 0)")
    kind = "tiny configuration" if options.tiny else "VGGT-1B architecture"
    return ExportSpec(
        family="vggt",
        module=VGGTForOnnx(model).eval(),
        input_names=INPUT_NAMES,
        output_names=OUTPUT_NAMES,
        dynamic_axes={INPUT_NAMES[0]: {0: "S"}, **{k: {1: "S"} for k in OUTPUT_NAMES}},
        make_inputs=lambda n, rng: (random_images(n, size_hw, rng),),
        size_hw=size_hw,
        contract="multiview",
        description=f"VGGT ({kind}, weights: {options.weights}) exported by ffrecon export-model, "
        f"input {size_hw[1]}x{size_hw[0]}",
        notes=notes,
        trace_context=trace_context(options.upstream),
    )


def size_for_photo(height: int, width: int) -> tuple[int, int]:
    """The network input size the reference crop preprocessing gives a photo of this size."""
    return contract.network_size_hw(height, width, contract.PreprocessMode.CROP)
