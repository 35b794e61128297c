"""Rewrites that let the TorchScript ONNX exporter take upstream code as shipped.

Each rewrite computes the same numbers as the code it stands in for, and applies only inside
:func:`export_rewrites` (the upstream files are never edited; PyTorch runs outside the context are
untouched, so the verification compares the export against the original code):

- ``torch.cartesian_prod`` (VGGT's, Pi3's and Depth Anything 3's rotary position grids) has no ONNX
  symbolic: replaced by the identical ``meshgrid`` + ``stack`` form.
- ``aten::expm1`` (VGGT's and DA3's depth/point activations, DUSt3R's ``exp`` head) has no symbolic
  at opset 17: exported as ``Exp(x) - 1``. For the |x| < 1e-3 where the two differ in the last
  bits, the absolute difference is below 1e-7, far under the outputs' scale.
- ``int(positions.max())`` in the rotary embeddings is data-dependent; under tracing it is read once
  and frozen, which is right because positions depend only on the fixed input size (H, W).
  Exports therefore fix H and W and keep the frame (or pair) count dynamic.

- ``F.scaled_dot_product_attention`` (fused attention) is written out as MatMul-Softmax-MatMul with a
  constant scale (code that imported the function by name keeps the fused op, which exports too).
  With ``fused=True`` it becomes onnxruntime's ``com.microsoft.MultiHeadAttention`` contrib op instead:
  on the CUDA provider that runs flash or memory-efficient kernels, so no ``[heads, N, N]`` score
  matrix is held and memory grows linearly with the frames (the CPU provider computes it as before).

Family-specific rewrites live with their family's exporter.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

_OPSET_FOR_SYMBOLICS = 15  # CastLike needs 15; registered for this opset and every later one
_registered = False


def _cartesian_prod(*tensors: torch.Tensor) -> torch.Tensor:
    """``torch.cartesian_prod`` for 1-D tensors, built from ONNX-exportable ops (same values, same order)."""
    if len(tensors) == 1:
        return tensors[0]
    grids = torch.meshgrid(*tensors, indexing="ij")
    return torch.stack([g.reshape(-1) for g in grids], dim=-1)


def _expm1_symbolic(g, x):  # noqa: ANN001 - torch.onnx symbolic signature
    one = g.op("Constant", value_t=torch.tensor(1.0))
    one = g.op("CastLike", one, x)
    return g.op("Sub", g.op("Exp", x), one)


def register_symbolics() -> None:
    """Register the ONNX symbolics ffrecon adds (idempotent)."""
    global _registered
    if not _registered:
        torch.onnx.register_custom_op_symbolic("aten::expm1", _expm1_symbolic, _OPSET_FOR_SYMBOLICS)
        _registered = True


def _attention(
    query: torch.Tensor,
    key: torch.Tensor,
    value: torch.Tensor,
    attn_mask: torch.Tensor | None = None,
    dropout_p: float = 0.0,
    is_causal: bool = False,
    scale: float | None = None,
    **_: object,
) -> torch.Tensor:
    """``F.scaled_dot_product_attention`` (inference) as MatMul-Softmax-MatMul with a constant scale.

    The fused op's ONNX symbolic computes its scale from the runtime shape through float32 Cast
    nodes, which fp16 conversion cannot retype (the file then fails to load); the head width is
    fixed, so the scale is a constant here. Same arithmetic as PyTorch's math backend.
    """
    if is_causal or dropout_p:
        raise RuntimeError("ffrecon's attention rewrite covers inference without causal masks only")
    factor = float(scale) if scale is not None else float(query.shape[-1]) ** -0.5
    scores = torch.matmul(query * factor, key.transpose(-2, -1))
    if attn_mask is not None:
        scores = scores.masked_fill(~attn_mask, float("-inf")) if attn_mask.dtype == torch.bool else scores + attn_mask
    return torch.matmul(torch.softmax(scores, dim=-1), value)


class _MultiHeadAttention(torch.autograd.Function):
    """Attention that PyTorch computes as :func:`_attention` and the exporter writes as one contrib op.

    ``MultiHeadAttention`` takes ``[batch, tokens, heads * width]`` queries, keys and values, so the
    symbolic moves the heads axis in and out around it (two Transposes and Reshapes per tensor).
    """

    @staticmethod
    def forward(ctx, query, key, value, scale: float, heads: int):  # noqa: ANN001, ARG004
        return _attention(query, key, value, scale=scale)

    @staticmethod
    def symbolic(g, query, key, value, scale: float, heads: int):  # noqa: ANN001
        def tokens(x):  # [B, heads, N, width] -> [B, N, heads * width]
            x = g.op("Transpose", x, perm_i=[0, 2, 1, 3])
            return g.op("Reshape", x, g.op("Constant", value_t=torch.tensor([0, 0, -1])))

        out = g.op(
            "com.microsoft::MultiHeadAttention",
            tokens(query),
            tokens(key),
            tokens(value),
            num_heads_i=heads,
            scale_f=scale,
        )
        out = g.op("Reshape", out, g.op("Constant", value_t=torch.tensor([0, 0, heads, -1])))
        out = g.op("Transpose", out, perm_i=[0, 2, 1, 3])
        out.setType(query.type())
        return out


def _fused_attention(
    query: torch.Tensor,
    key: torch.Tensor,
    value: torch.Tensor,
    attn_mask: torch.Tensor | None = None,
    dropout_p: float = 0.0,
    is_causal: bool = False,
    scale: float | None = None,
    **_: object,
) -> torch.Tensor:
    """``F.scaled_dot_product_attention`` exported as ``com.microsoft.MultiHeadAttention`` (see the module doc)."""
    if is_causal or dropout_p or attn_mask is not None or query.dim() != 4:
        raise RuntimeError("ffrecon's fused attention export covers unmasked 4-D inference attention only")
    factor = float(scale) if scale is not None else float(query.shape[-1]) ** -0.5
    heads = int(query.shape[1])  # fixed by the architecture: a constant in the graph
    return _MultiHeadAttention.apply(query, key, value, factor, heads)


@contextlib.contextmanager
def export_rewrites(*, fused_attention: bool = False) -> Iterator[None]:
    """Apply the rewrites above for the duration of one export."""
    register_symbolics()
    originals = (torch.cartesian_prod, torch.nn.functional.scaled_dot_product_attention)
    torch.cartesian_prod = _cartesian_prod
    torch.nn.functional.scaled_dot_product_attention = _fused_attention if fused_attention else _attention
    try:
        yield
    finally:
        torch.cartesian_prod, torch.nn.functional.scaled_dot_product_attention = originals


def _cache_key(args: tuple, kwargs: dict) -> tuple:
    """Arguments reduced to what size-only tables depend on: tensors by shape and dtype, the rest by value."""

    def reduce(a):
        if isinstance(a, torch.Tensor) and a.ndim == 0 and not a.is_floating_point():
            return int(a)  # a size read under tracing
        if isinstance(a, torch.Tensor):
            return ("tensor", tuple(int(s) for s in a.shape), a.dtype)
        return a

    return tuple(reduce(a) for a in args) + tuple((k, reduce(v)) for k, v in sorted(kwargs.items()))


def _filled_outside_trace(original, label: str):
    """``original`` behind a cache keyed by its arguments' shapes and values: filled by the original
    code when called outside a trace, served as a constant inside one (missing there is an error)."""
    cache: dict[tuple, object] = {}

    def cached(*args, **kwargs):
        key = _cache_key(args, kwargs)
        if key not in cache:
            if torch.jit.is_tracing():
                raise RuntimeError(f"{label}{key} was not precomputed before tracing")
            value = original(*args, **kwargs)
            cache[key] = value.detach() if isinstance(value, torch.Tensor) else value
        return cache[key]

    return cached


@contextlib.contextmanager
def frozen_position_embeddings(model: torch.nn.Module) -> Iterator[int]:
    """Serve every DINOv2-style ``interpolate_pos_encoding`` from a cache filled by the original code.

    DINOv2 (VGGT's, Pi3's and DA3's encoders) resizes its learnt position table with antialiased
    bicubic interpolation, which ONNX cannot express. The table depends only on the input size,
    which every export fixes: run the model once at that size outside the trace (the original code
    fills the cache, so the values are exactly upstream's) and the trace then records the table as a
    constant. Yields the number of modules wrapped; the originals are restored on exit.
    """
    wrapped = []
    for sub in model.modules():
        original = getattr(sub, "interpolate_pos_encoding", None)
        if callable(original):
            sub.interpolate_pos_encoding = _filled_outside_trace(original, "interpolate_pos_encoding")
            wrapped.append(sub)
    try:
        yield len(wrapped)
    finally:
        for sub in wrapped:
            del sub.interpolate_pos_encoding  # the instance attribute; the class method shows again


@contextlib.contextmanager
def frozen_functions(*targets: tuple[object, str]) -> Iterator[None]:
    """Serve module-level functions that build size-only tables from a cache filled outside the trace.

    For tables computed in float64 (VGGT's DPT position embedding: ONNX Einsum cannot mix float32
    positions with float64 frequencies) or with other non-exportable ops whose inputs depend only on
    the input size. ``targets`` are ``(module, function_name)``; the same input shapes must always mean
    the same values, which holds within one export (fixed H and W).
    """
    saved = [(owner, name, getattr(owner, name)) for owner, name in targets]
    for owner, name, original in saved:
        setattr(owner, name, _filled_outside_trace(original, name))
    try:
        yield
    finally:
        for owner, name, original in saved:
            setattr(owner, name, original)
