"""DUSt3R (naver/dust3r) and MASt3R (naver/mast3r) to ONNX with the pairwise contract
(docs/contracts.md, "Pairwise models").

Inputs ``view1``, ``view2``: ``[B, 3, H, W]`` float32 RGB normalised to [-1, 1] (``(x / 255 - 0.5) / 0.5``),
preprocessed by :func:`ffrecon.models.pairwise.preprocess_pairwise` (upstream's ``load_images``).
Outputs, all ``[B, H, W, ...]`` float32 at the input resolution:

- ``pts3d [B, H, W, 3]``: view1's points in view1's camera frame (OpenCV axes, arbitrary scale);
- ``conf [B, H, W]``: their confidence, ``1 + exp(x)`` (>= 1);
- ``pts3d_in_other_view [B, H, W, 3]``: view2's points, also in view1's camera frame;
- ``conf_in_other_view [B, H, W]``: their confidence (>= 1).

MASt3R adds its local descriptors (for matching; ffrecon's runtime checks and ignores them so far):

- ``desc [B, H, W, 24]``: view1's descriptor at each view1 pixel, unit L2 norm;
- ``desc_conf [B, H, W]``: its confidence (``exp(x)`` for the published checkpoint, so >= 0, not >= 1);
- ``desc_in_other_view [B, H, W, 24]``, ``desc_conf_in_other_view [B, H, W]``: view2's descriptors at
  view2's pixels (the name mirrors ``conf_in_other_view``: the second head's output; descriptors have
  no frame). Matching is mutual nearest neighbours between ``desc[b]`` and ``desc_in_other_view[b]``
  (upstream ``mast3r.fast_nn.fast_reciprocal_NNs``), weighted by the two ``desc_conf``.

B is dynamic; H and W are fixed per file (rotary tables and head shapes are frozen at the export size).

Export rewrites, each computing upstream's numbers (applied in memory, only for the trace):

- the prediction heads are called with the export's (H, W) instead of reading it from ``true_shape``
  (upstream's ``landscape_only=False`` path does ``H, W = true_shape[0].tolist()``: the same values);
- the views carry distinct ``instance`` names, so upstream's ``is_symmetrized`` takes the plain path
  (each pair encoded as given; the symmetric shortcut only saves work, it gives the same values);
- a compiled ``curope`` RoPE (a CUDA extension ONNX cannot record) is replaced by croco's own PyTorch
  ``RoPE2D``; ``int(positions.max())`` and the cos/sin tables are frozen at the export size, and
  ``expm1``/``cartesian_prod`` are rewritten by :func:`ffrecon.models.exporting.patches.export_rewrites`.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import importlib.util
import io
import logging
import sys
from pathlib import Path

import torch

from ffrecon.errors import InputError
from ffrecon.models import pairwise as contract
from ffrecon.models.exporting.common import ExportSpec, ModelExportOptions, random_images
from ffrecon.models.exporting.upstream import import_upstream
from ffrecon.models.exporting.weights import WEIGHT_SUFFIXES, find_weights, load_into, load_state_dict

log = logging.getLogger("ffrecon.export_model")

INF = float("inf")
DEFAULT_SIZE_HW = (384, 512)  # 4:3 landscape photos at upstream's long side 512
PATCH_SIZE = contract.PATCH_SIZE
INPUT_NAMES = contract.INPUT_NAMES
OUTPUT_NAMES = contract.OUTPUT_NAMES
DESCRIPTOR_NAMES = contract.DESCRIPTOR_NAMES
DESC_DIM = 24

CLASSES = {"dust3r": "AsymmetricCroCo3DStereo", "mast3r": "AsymmetricMASt3R"}
MODULES = {"dust3r": "dust3r.model", "mast3r": "mast3r.model"}
# The published 512 checkpoints' architectures (their training commands in the upstream READMEs, with
# upstream load_model's changes: PatchEmbedDust3R for ManyAR_PatchEmbed, landscape_only=False):
# DUSt3R_ViTLarge_BaseDecoder_512_dpt and MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.
_VIT_LARGE = dict(
    pos_embed="RoPE100",
    patch_embed_cls="PatchEmbedDust3R",
    img_size=(512, 512),
    depth_mode=("exp", -INF, INF),
    conf_mode=("exp", 1, INF),
    enc_embed_dim=1024,
    enc_depth=24,
    enc_num_heads=16,
    dec_embed_dim=768,
    dec_depth=12,
    dec_num_heads=12,
    landscape_only=False,
)
PUBLISHED = {
    "dust3r": dict(_VIT_LARGE, head_type="dpt", output_mode="pts3d"),
    "mast3r": dict(
        _VIT_LARGE,
        head_type="catmlp+dpt",
        output_mode=f"pts3d+desc{DESC_DIM}",
        two_confs=True,
        desc_conf_mode=("exp", 0, INF),
    ),
}
# Tiny: the same classes and heads; dec_depth 10 is the least the DPT head takes (its hooks are
# [0, d/2, 3d/4, d]); the DPT widths are narrowed after construction (see _narrow_dpt).
TINY = dict(enc_embed_dim=64, enc_depth=2, enc_num_heads=2, dec_embed_dim=48, dec_depth=10, dec_num_heads=2)
TINY_DPT = dict(layer_dims=[16, 32, 64, 64], feature_dim=32, last_dim=16)


class PairwiseForOnnx(torch.nn.Module):
    """``view1, view2 [B, 3, H, W]`` in [-1, 1] to the contract outputs (plus descriptors for MASt3R).

    ``desc_dim`` is the descriptor size (None: no descriptors). The outputs are reshaped to their
    known sizes (``[-1, H, W, 3]`` etc.; values unchanged) so that the ONNX file declares them.
    """

    def __init__(self, model: torch.nn.Module, size_hw: tuple[int, int], *, desc_dim: int | None) -> None:
        super().__init__()
        self.model = model
        self.size_hw = size_hw
        self.desc_dim = desc_dim

    def forward(self, view1: torch.Tensor, view2: torch.Tensor) -> tuple[torch.Tensor, ...]:
        b = view1.shape[0]
        # Distinct instance names: upstream's is_symmetrized() is False, every pair is encoded as given.
        # true_shape is left out: upstream then uses the image's own shape, as load_images records it.
        res1, res2 = self.model(
            {"img": view1, "instance": [f"view1_{k}" for k in range(b)]},
            {"img": view2, "instance": [f"view2_{k}" for k in range(b)]},
        )
        h, w = self.size_hw
        points, maps = (-1, h, w, 3), (-1, h, w)
        outputs = (
            res1["pts3d"].reshape(points),
            res1["conf"].reshape(maps),
            res2["pts3d_in_other_view"].reshape(points),
            res2["conf"].reshape(maps),
        )
        if self.desc_dim is not None:
            desc = (-1, h, w, self.desc_dim)
            outputs += (
                res1["desc"].reshape(desc),
                res1["desc_conf"].reshape(maps),
                res2["desc"].reshape(desc),
                res2["desc_conf"].reshape(maps),
            )
        return outputs


def parse_model_string(text: str) -> tuple[str, dict]:
    """``"AsymmetricCroCo3DStereo(pos_embed='RoPE100', depth_mode=('exp', -inf, inf), ...)"`` (the
    ``args.model`` that upstream checkpoints store and upstream evaluates) read without evaluating
    code: literals, tuples, lists and ``inf`` only.

    >>> parse_model_string("AsymmetricMASt3R(img_size=(512, 512), depth_mode=('exp', -inf, inf))")
    ('AsymmetricMASt3R', {'img_size': (512, 512), 'depth_mode': ('exp', -inf, inf)})
    """

    def value(node: ast.AST):
        if isinstance(node, ast.Constant):
            return node.value
        if isinstance(node, (ast.Tuple, ast.List)):
            items = [value(n) for n in node.elts]
            return tuple(items) if isinstance(node, ast.Tuple) else items
        if isinstance(node, ast.Name) and node.id == "inf":
            return INF
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return -value(node.operand)
        raise ValueError(ast.dump(node))

    try:
        call = ast.parse(text.strip(), mode="eval").body
        if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Name) and not call.args):
            raise ValueError("not a call with keyword arguments")
        return call.func.id, {k.arg: value(k.value) for k in call.keywords}
    except (SyntaxError, ValueError) as exc:
        raise InputError(
            f"cannot read the checkpoint's model description {text[:120]!r} ({exc})",
            "pass a checkpoint published by naver (its 'args.model' is a constructor call with literal arguments)",
        ) from exc


def _read_pth(file: Path) -> dict:
    """A training checkpoint (``{'args': Namespace, 'model': state dict, ...}``) read with ``weights_only``."""
    try:
        with torch.serialization.safe_globals([argparse.Namespace]):
            return torch.load(file, map_location="cpu", weights_only=True)
    except Exception as exc:  # unpickling raises several types
        raise InputError(
            f"cannot read checkpoint {file}: {str(exc).splitlines()[0]}",
            "pass the .pth file naver publishes (or a state dict of tensors); download it again if it is truncated",
        ) from exc


def _narrow_dpt(model: torch.nn.Module, upstream: Path | None, family: str) -> None:
    """Replace each head's DPT adapter (upstream's ``DPTOutputAdapter_fix``) by the same class at
    :data:`TINY_DPT` widths: the published heads fix 256 features, which would make "tiny" 40 M parameters."""
    dpt_mod = import_upstream("dust3r.heads.dpt_head", upstream, family=family)
    for head in (model.downstream_head1, model.downstream_head2):
        old = head.dpt
        new = dpt_mod.DPTOutputAdapter_fix(
            num_channels=old.num_channels, hooks=old.hooks, head_type="regression", **TINY_DPT
        )
        new.init(dim_tokens_enc=old.dim_tokens_enc)
        head.dpt = new


def landscape_heads_off(model: torch.nn.Module, upstream: Path | None, family: str) -> None:
    """Wrap the heads as upstream's ``landscape_only=False`` does (load_model forces it for checkpoints:
    with PatchEmbedDust3R a portrait input must not be transposed back)."""
    misc = import_upstream("dust3r.utils.misc", upstream, family=family)
    model.head1 = misc.transpose_to_landscape(model.downstream_head1, activate=False)
    model.head2 = misc.transpose_to_landscape(model.downstream_head2, activate=False)


def pytorch_rope(model: torch.nn.Module) -> str | None:
    """Swap a compiled ``cuRoPE2D`` (CUDA extension; not traceable) for croco's PyTorch ``RoPE2D``.

    croco defines the PyTorch class only when ``models.curope`` fails to import, so its
    ``pos_embed.py`` is loaded once more with that extension hidden: upstream's own class, not a copy.
    Returns a note for the metadata, or None when nothing was swapped.
    """
    compiled = [
        (parent, name)
        for parent in model.modules()
        for name, child in parent.named_children()
        if type(child).__name__ == "cuRoPE2D"
    ]
    if not compiled:
        return None
    rope = getattr(compiled[0][0], compiled[0][1])
    source = Path(sys.modules["models.pos_embed"].__file__)
    hidden = {
        k: sys.modules.pop(k) for k in list(sys.modules) if k == "models.curope" or k.startswith("models.curope.")
    }
    sys.modules["models.curope"] = None  # makes `from models.curope import cuRoPE2D` raise ImportError
    try:
        spec = importlib.util.spec_from_file_location("ffrecon_croco_pos_embed_pytorch", source)
        module = importlib.util.module_from_spec(spec)
        with contextlib.redirect_stdout(io.StringIO()):  # upstream prints a warning about the missing extension
            spec.loader.exec_module(module)
    finally:
        del sys.modules["models.curope"]
        sys.modules.update(hidden)
    replacement = module.RoPE2D(freq=rope.base, F0=rope.F0)
    for parent, name in compiled:
        setattr(parent, name, replacement)
    return f"compiled cuRoPE2D replaced by croco's PyTorch RoPE2D (freq {rope.base:g}) for the export"


def model_class(family: str, upstream: Path | None) -> type:
    """Upstream's ``AsymmetricCroCo3DStereo`` (dust3r) or ``AsymmetricMASt3R`` (mast3r)."""
    return getattr(import_upstream(MODULES[family], upstream, family=family), CLASSES[family])


def load_checkpoint(options: ModelExportOptions) -> torch.nn.Module:
    """The model a checkpoint describes.

    - a ``.pth`` training checkpoint with ``args`` (what naver publishes for download): the
      architecture from ``args.model`` (read, not evaluated), then the weights (``dec_blocks2``
      copied from ``dec_blocks`` when absent, by upstream's ``load_state_dict``);
    - a plain state dict (``.pth``/``.safetensors``): the published 512 architecture of the family;
    - a folder with ``config.json`` or a Hugging Face id: upstream's ``from_pretrained``.
    """
    cls = model_class(options.family, options.upstream)
    path = Path(options.checkpoint).expanduser()
    if not path.exists() and (path.suffix in WEIGHT_SUFFIXES or str(options.checkpoint).startswith((".", "/", "~"))):
        raise InputError(
            f"no checkpoint at {path}",
            "pass the .pth file you downloaded (see docs/models.md), "
            "or a Hugging Face id such as naver/DUSt3R_ViTLarge_BaseDecoder_512_dpt",
        )
    if (path.is_dir() and (path / "config.json").is_file()) or not path.exists():
        log.info("loading %s with upstream from_pretrained(%s)", options.family, options.checkpoint)
        try:
            return cls.from_pretrained(str(path) if path.exists() else options.checkpoint)
        except Exception as exc:  # huggingface_hub and torch raise many types
            raise InputError(
                f"upstream from_pretrained cannot load {options.checkpoint}: {str(exc).splitlines()[0]}",
                "pass the .pth file you downloaded, or a folder with config.json and model.safetensors",
            ) from exc
    file = find_weights(path)
    if file.suffix == ".safetensors":
        state, arch = load_state_dict(file), None
    else:
        stored = _read_pth(file)
        arch = getattr(stored.get("args"), "model", None) if isinstance(stored, dict) else None
        state = stored.get("model", stored) if isinstance(stored, dict) else stored
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise InputError(
            f"{file} holds no state dict of tensors",
            "pass the checkpoint .pth naver publishes (keys 'args' and 'model') or a state dict",
        )
    if arch is None:
        model = cls(**PUBLISHED[options.family])
    else:
        name, kwargs = parse_model_string(arch)
        if name != cls.__name__:
            other = next((f for f, c in CLASSES.items() if c == name), None)
            raise InputError(
                f"{file.name} holds a {name} model, not {cls.__name__}",
                f"use `ffrecon export-model {other}`" if other else "pass a DUSt3R or MASt3R checkpoint",
            )
        model = cls(**kwargs)
    load_into(model, state, source=str(file))
    return model


def plain_patch_embed(model: torch.nn.Module, upstream: Path | None, family: str) -> None:
    """Use ``PatchEmbedDust3R`` where a model was built with ``ManyAR_PatchEmbed`` (the training
    class, which transposes portrait inputs), with the same weights: upstream ``load_model``'s rule."""
    old = model.patch_embed
    if type(old).__name__ != "ManyAR_PatchEmbed":
        return
    patch_mod = import_upstream("dust3r.patch_embed", upstream, family=family)
    new = patch_mod.get_patch_embed("PatchEmbedDust3R", old.img_size, old.patch_size, old.proj.out_channels)
    new.load_state_dict(old.state_dict())
    model.patch_embed = new


def build_model(options: ModelExportOptions) -> tuple[torch.nn.Module, list[str]]:
    """The upstream model for ``options`` (eval mode, float32) and notes for the metadata."""
    notes: list[str] = []
    if options.checkpoint:
        model = load_checkpoint(options)
    else:
        kwargs = dict(PUBLISHED[options.family], **(TINY if options.tiny else {}))
        model = model_class(options.family, options.upstream)(**kwargs)
        if options.tiny:
            _narrow_dpt(model, options.upstream, options.family)
            notes.append(f"tiny configuration {TINY}, DPT widths {TINY_DPT}")
    plain_patch_embed(model, options.upstream, options.family)
    landscape_heads_off(model, options.upstream, options.family)
    note = pytorch_rope(model)
    if note:
        notes.append(note)
    notes.append(
        "heads called at the export's HxW (upstream's landscape_only=False path); "
        "rotary tables and int(positions.max()) frozen at HxW; expm1 as exp - 1"
    )
    return model.eval().float(), notes


def _static_head(
    head: torch.nn.Module, size_hw: tuple[int, int], decout: list[torch.Tensor], true_shape: torch.Tensor
) -> dict:
    return head(decout, size_hw)  # upstream's wrapper_no, with (H, W) known instead of read from true_shape


def trace_context(size_hw: tuple[int, int]):
    """Heads called at the fixed export size (see the module docstring); restored on exit."""

    @contextlib.contextmanager
    def context(wrapper: torch.nn.Module):
        model = wrapper.model
        saved = model.head1, model.head2
        model.head1 = lambda decout, true_shape: _static_head(model.downstream_head1, size_hw, decout, true_shape)
        model.head2 = lambda decout, true_shape: _static_head(model.downstream_head2, size_hw, decout, true_shape)
        try:
            yield
        finally:
            model.head1, model.head2 = saved

    return context


def build(options: ModelExportOptions, size_hw: tuple[int, int]) -> ExportSpec:
    torch.manual_seed(options.seed)
    model, notes = build_model(options)
    descriptors = options.family == "mast3r"
    desc_dim = int(model.downstream_head1.local_feat_dim) if descriptors else None
    names = OUTPUT_NAMES + (DESCRIPTOR_NAMES if descriptors else ())
    kind = (
        "tiny configuration"
        if options.tiny
        else "published 512 architecture"
        if options.checkpoint is None
        else "checkpoint"
    )
    label = "MASt3R" if descriptors else "DUSt3R"
    return ExportSpec(
        family=options.family,
        module=PairwiseForOnnx(model, size_hw, desc_dim=desc_dim).eval(),
        input_names=INPUT_NAMES,
        output_names=names,
        dynamic_axes={k: {0: "B"} for k in INPUT_NAMES + names},
        make_inputs=lambda n, rng: (
            random_images(n, size_hw, rng, low=-1.0, high=1.0),
            random_images(n, size_hw, rng, low=-1.0, high=1.0),
        ),
        size_hw=size_hw,
        contract="pairwise",
        description=f"{label} ({kind}, weights: {options.weights}) exported by ffrecon export-model, "
        f"input {size_hw[1]}x{size_hw[0]}",
        notes=notes,
        extra_metadata={"ffrecon.descriptor_dim": str(desc_dim)} if descriptors else {},
        trace_context=trace_context(size_hw),
    )


def size_for_photo(height: int, width: int) -> tuple[int, int]:
    """The network input size upstream's ``load_images(size=512)`` gives a photo of this size."""
    return contract.network_size_hw(height, width, contract.LONG_SIDE)
