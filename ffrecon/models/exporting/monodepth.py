"""Monocular depth (Depth Anything V1/V2, DPT via ``transformers``) to ONNX with the ``monodepth`` contract.

Input ``pixel_values [B, 3, H, W]`` float32 RGB in [0, 1] (the wrapper applies the checkpoint's
mean/std normalisation, ImageNet for Depth Anything); output ``predicted_depth [B, H, W]``: relative
inverse depth (disparity-like, Depth Anything's relative checkpoints and DPT) or metric depth in
metres (Depth Anything's metric checkpoints: sigmoid x ``max_depth``), recorded in the metadata as
``ffrecon.depth_kind`` = ``relative_inverse`` or ``metric``. B is dynamic; H and W are fixed per file.

Checkpoints are downloaded Hugging Face folders (``config.json`` plus weights), loaded with
``AutoModelForDepthEstimation.from_pretrained(folder)``; ``--tiny`` and ``--random-init`` build the
same ``transformers`` classes from a config with random weights.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import torch

from ffrecon.errors import FFReconError, InputError
from ffrecon.models import monodepth as contract
from ffrecon.models.exporting.common import ExportSpec, ModelExportOptions, random_images

log = logging.getLogger("ffrecon.export_model")

INPUT_NAMES = (contract.INPUT_NAME,)
OUTPUT_NAMES = contract.OUTPUT_NAMES
PATCH_SIZE = contract.PATCH_SIZE
DEFAULT_SIZE_HW = (518, 686)  # a 4:3 landscape photo under Depth Anything's processor (518, keep aspect, x14)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
SUPPORTED = ("DepthAnythingForDepthEstimation", "DPTForDepthEstimation")
# Depth Anything V2 sizes (the -hf configs): DINOv2 width, heads, layers, taken layers, neck, fusion, head.
VARIANTS = {
    "small": dict(hidden=384, heads=6, layers=12, out=[3, 6, 9, 12], neck=[48, 96, 192, 384], fusion=64, head=32),
    "base": dict(hidden=768, heads=12, layers=12, out=[3, 6, 9, 12], neck=[96, 192, 384, 768], fusion=128, head=32),
    "large": dict(
        hidden=1024, heads=16, layers=24, out=[5, 12, 18, 24], neck=[256, 512, 1024, 1024], fusion=256, head=32
    ),
    "tiny": dict(hidden=32, heads=2, layers=4, out=[1, 2, 3, 4], neck=[8, 16, 32, 32], fusion=16, head=8),
}
# Random weights drawn with std 0.02 (transformers' default) leave the tiny head's output near 1e-7;
# 0.1 gives outputs of order 0.01, so that comparisons against PyTorch measure something.
TINY_INITIALIZER_RANGE = 0.1
RANDOM_INIT_VARIANT = "large"  # Depth-Anything-V2-Large (335 M parameters)
METRIC_MAX_DEPTH = 20  # the indoor (Hypersim) metric models' max_depth; outdoor (VKITTI) ones use 80


class MonoDepthForOnnx(torch.nn.Module):
    """``pixel_values [B, 3, H, W]`` in [0, 1] to ``predicted_depth [B, H, W]``."""

    def __init__(self, model: torch.nn.Module, mean: tuple[float, ...], std: tuple[float, ...]) -> None:
        super().__init__()
        self.model = model
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1), persistent=False)

    def forward(self, pixel_values: torch.Tensor) -> tuple[torch.Tensor]:
        depth = self.model(pixel_values=(pixel_values - self.mean) / self.std).predicted_depth
        return (depth if depth.dim() == 3 else depth[:, 0],)  # DPT heads may keep the channel axis


def config_for(variant: str, metric: bool = False):
    """A ``DepthAnythingConfig`` of one of :data:`VARIANTS` (Depth Anything V2 layout)."""
    from transformers import DepthAnythingConfig, Dinov2Config

    v = VARIANTS[variant]
    init = dict(initializer_range=TINY_INITIALIZER_RANGE) if variant == "tiny" else {}
    backbone = Dinov2Config(
        image_size=518,
        patch_size=PATCH_SIZE,
        hidden_size=v["hidden"],
        num_attention_heads=v["heads"],
        num_hidden_layers=v["layers"],
        out_indices=v["out"],
        reshape_hidden_states=False,
        **init,
    )
    kind = (
        dict(depth_estimation_type="metric", max_depth=METRIC_MAX_DEPTH)
        if metric
        else dict(depth_estimation_type="relative")
    )
    return DepthAnythingConfig(
        backbone_config=backbone,
        reassemble_hidden_size=v["hidden"],
        neck_hidden_sizes=v["neck"],
        fusion_hidden_size=v["fusion"],
        head_hidden_size=v["head"],
        **kind,
        **init,
    )


def _variant(options: ModelExportOptions) -> tuple[str, bool]:
    """``(size, metric)`` from ``options.variant`` (proposed option), e.g. ``"large"`` or ``"small-metric"``.

    ``--tiny`` always builds the tiny size; a ``-metric`` variant still picks the metric head.
    """
    name = getattr(options, "variant", None) or RANDOM_INIT_VARIANT
    size, _, kind = name.partition("-")
    if size not in VARIANTS or kind not in ("", "metric"):
        raise InputError(
            f"unknown monocular depth variant '{name}'", f"use one of {', '.join(VARIANTS)}, optionally with '-metric'"
        )
    return ("tiny" if options.tiny else size), kind == "metric"


def load_checkpoint(folder: Path) -> tuple[torch.nn.Module, dict]:
    """A downloaded Hugging Face folder: the model (``from_pretrained``) and its preprocessor settings."""
    folder = Path(folder).expanduser()
    if not (folder / "config.json").is_file():
        raise InputError(
            f"{folder} is not a downloaded Hugging Face model folder (no config.json)",
            "download the whole model folder, "
            "e.g. `hf download depth-anything/Depth-Anything-V2-Small-hf --local-dir DA2S`",
        )
    architectures = json.loads((folder / "config.json").read_text()).get("architectures") or []
    if not set(architectures) & set(SUPPORTED):
        raise InputError(
            f"{folder} holds a {architectures or 'model of unknown architecture'}",
            f"ffrecon exports {', '.join(SUPPORTED)} checkpoints",
        )
    from transformers import AutoModelForDepthEstimation

    log.info("loading %s (%s) with transformers", folder, ", ".join(architectures))
    try:
        model = AutoModelForDepthEstimation.from_pretrained(str(folder), local_files_only=True)
    except (OSError, ValueError) as exc:
        raise InputError(
            f"transformers cannot load {folder}: {str(exc).splitlines()[0]}",
            "download the checkpoint folder again (config.json and model.safetensors)",
        ) from exc
    processor = folder / "preprocessor_config.json"
    settings = json.loads(processor.read_text()) if processor.is_file() else {}
    return model, settings


def depth_kind(config) -> str:
    """``metric`` for Depth Anything metric heads, else ``relative_inverse`` (relative Depth Anything, DPT)."""
    return "metric" if getattr(config, "depth_estimation_type", "relative") == "metric" else "relative_inverse"


def build(options: ModelExportOptions, size_hw: tuple[int, int]) -> ExportSpec:
    torch.manual_seed(options.seed)
    settings: dict = {}
    if options.checkpoint:
        model, settings = load_checkpoint(Path(options.checkpoint))
        name = Path(options.checkpoint).name
    else:
        from transformers import DepthAnythingForDepthEstimation

        size, metric = _variant(options)
        model = DepthAnythingForDepthEstimation(config_for(size, metric))
        name = f"Depth Anything V2 {size}{' metric' if metric else ''} layout"
    model = model.eval().float()
    patch = getattr(model.config, "patch_size", PATCH_SIZE)
    if size_hw[0] % patch or size_hw[1] % patch:
        raise FFReconError(
            f"input size {size_hw[1]}x{size_hw[0]} is not a multiple of this model's patch size {patch}",
            f"use --height and --width that are multiples of {patch}",
        )
    mean = tuple(settings.get("image_mean", IMAGENET_MEAN))
    std = tuple(settings.get("image_std", IMAGENET_STD))
    kind = depth_kind(model.config)
    metadata = {
        "ffrecon.depth_kind": kind,
        "ffrecon.monodepth.architecture": type(model).__name__,
        "ffrecon.monodepth.processor": json.dumps(
            {k: settings[k] for k in ("size", "keep_aspect_ratio", "ensure_multiple_of", "resample") if k in settings}
        ),
    }
    if kind == "metric":
        metadata["ffrecon.max_depth"] = str(model.config.max_depth)
    h, w = size_hw
    return ExportSpec(
        family="monodepth",
        module=MonoDepthForOnnx(model, mean, std).eval(),
        input_names=INPUT_NAMES,
        output_names=OUTPUT_NAMES,
        dynamic_axes={INPUT_NAMES[0]: {0: "B"}, OUTPUT_NAMES[0]: {0: "B"}},
        make_inputs=lambda n, rng: (random_images(n, size_hw, rng),),
        size_hw=size_hw,
        contract="monodepth",
        description=f"monocular depth ({name}, {kind}, weights: {options.weights}) exported by ffrecon export-model, "
        f"input {w}x{h}",
        notes=[f"normalisation mean {mean} std {std} inside the file; output {kind.replace('_', ' ')} depth"],
        extra_metadata=metadata,
    )


def size_for_photo(height: int, width: int) -> tuple[int, int]:
    """The network input size Depth Anything's image processor gives a photo (518, keep aspect, x14).

    >>> size_for_photo(480, 640), size_for_photo(1080, 1920)
    ((518, 686), (518, 924))
    """
    return contract.network_size_hw(height, width)
