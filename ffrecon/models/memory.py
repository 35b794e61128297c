"""How many frames one multi-view model call can hold: the default chunk size, from available memory.

A multi-view transformer's "global" attention layers attend over all tokens of all S frames at once.
Exported to ONNX as MatMul-Softmax-MatMul, each such layer holds a ``[heads, S*T, S*T]`` float32
score matrix (T tokens per frame), and the softmax writes a second one beside it, so peak memory
grows with S squared; the weights and per-frame activations add a constant and a linear term.
Fitted to the full-size VGGT-1B export at 518 x 392 with ``tools/bench_models.py`` (2, 4, 8 frames:
5.98, 8.05, 15.63 GB; fit 5.05 + 0.178 S + 0.143 S^2 GB; docs/benchmarks.md):

    peak(S) ~ WEIGHT_FACTOR * file bytes + S * LINEAR_BYTES_PER_TOKEN * T + SCORE_COPIES * heads * 4 bytes * (S * T)^2

The default chunk size is the largest S whose peak stays under ``MEMORY_FRACTION`` of the memory
available now (``/proc/meminfo``; the GPU's free memory when the model runs on onnxruntime's CUDA
provider), between ``MIN_CHUNK`` and ``MAX_CHUNK``. fp16 files hold activations and scores in 2 bytes.
Files exported with ``--fused-attention`` run onnxruntime's MultiHeadAttention, whose CUDA kernels
hold no score matrix: on CUDA their quadratic term is dropped (measured: memory grew linearly from 1 to
50 frames), and the CPU kernel still materialises the scores. The CUDA provider's per-token term is its
own measurement (``CUDA_LINEAR_BYTES_PER_TOKEN``, about 6x the CPU provider's).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from ffrecon.machine import available_memory_bytes, cuda_free_memory_bytes

log = logging.getLogger("ffrecon.models")

WEIGHT_FACTOR = 1.15  # onnxruntime's resident weights per file byte (fit: 5.05 GB for a 4.54 GB file)
LINEAR_BYTES_PER_TOKEN = 4 * 1024 * 45  # activations alive per token (fit: 0.178 GB per 1041-token frame)
SCORE_COPIES = 2  # scores and softmax output (fit: 0.143 GB x S^2 = 2 x 16 heads x 4 B x 1041^2)
# onnxruntime 1.31's CUDA provider, VGGT-1B fp32 with --fused-attention at 336 x 518 (893 tokens a frame) on an
# H100 (tools/bench_models.py): peak GPU memory 6.35, 15.72, 26.08, 57.24 GB at 1, 10, 20, 50 frames, i.e.
# 1.04 GB a frame and nothing quadratic (the scores alone would be 127 GB at 50 frames).
CUDA_LINEAR_BYTES_PER_TOKEN = 1.04 * 2**30 / 893
MEMORY_FRACTION = 0.7
MIN_CHUNK, MAX_CHUNK = 2, 64
DEFAULT_HEADS = 16  # VGGT-1B, Pi3 and DA3-large use 16-head global attention
SPECIAL_TOKENS = 5  # camera/register tokens per frame (VGGT, Pi3)


@dataclass(frozen=True)
class CallMemory:
    """Peak memory of one call of S frames: ``base + linear * S + quadratic * S^2`` bytes."""

    base: float
    linear: float
    quadratic: float

    def peak_bytes(self, frames: int) -> float:
        return self.base + self.linear * frames + self.quadratic * frames**2

    def max_frames(self, budget_bytes: float) -> int:
        """Largest S (>= 0) with ``peak_bytes(S) <= budget_bytes``.

        >>> CallMemory(1e9, 0.0, 1e9).max_frames(5e9)
        2
        >>> m = call_memory(int(4.54 * 2**30), (392, 518))  # VGGT-1B fp32: measured 15.63 GB at 8 frames
        >>> round(m.peak_bytes(8) / 2**30, 1), m.max_frames(16 * 2**30)
        (14.9, 8)
        """
        s = 0
        while s < 10_000 and self.peak_bytes(s + 1) <= budget_bytes:
            s += 1
        return s


def call_memory(
    model_bytes: int,
    size_hw: tuple[int, int],
    *,
    heads: int = DEFAULT_HEADS,
    patch: int = 14,
    value_bytes: int = 4,
    scores: bool = True,
    on_cuda: bool = False,
) -> CallMemory:
    """The memory model above for a model file of ``model_bytes`` at network input ``size_hw``.

    ``value_bytes``: 4 for fp32 files, 2 for fp16; ``scores``: False when attention holds no score
    matrix; ``on_cuda``: onnxruntime's CUDA provider, which keeps far more activations per token than
    the CPU one (``CUDA_LINEAR_BYTES_PER_TOKEN``).

    >>> m = call_memory(int(4.52 * 2**30), (336, 518), scores=False, on_cuda=True)  # H100, fused: 50 frames
    >>> m.quadratic, round(m.peak_bytes(50) / 2**30, 1)  # measured 57.24 GB
    (0.0, 57.2)
    """
    tokens = (size_hw[0] // patch) * (size_hw[1] // patch) + SPECIAL_TOKENS
    scale = value_bytes / 4
    linear = (CUDA_LINEAR_BYTES_PER_TOKEN if on_cuda else LINEAR_BYTES_PER_TOKEN) * tokens * scale
    quadratic = SCORE_COPIES * 4.0 * max(heads, 1) * tokens**2 * scale if scores else 0.0
    return CallMemory(WEIGHT_FACTOR * model_bytes, linear, quadratic)


def model_file_bytes(path: Path) -> int:
    """The model file plus its external weight file(s) (``NAME.onnx.data``)."""
    path = Path(path)
    return sum(p.stat().st_size for p in path.parent.glob(path.name + "*") if p.is_file())


def _available(on_cuda: bool) -> tuple[int, str]:
    if on_cuda:
        free = cuda_free_memory_bytes()
        if free is not None:
            return free, "GPU"
        log.warning("the model runs on CUDA but the GPU's free memory cannot be read: sizing chunks by host memory")
    return available_memory_bytes(), "host"


def default_chunk_size(
    path: Path,
    size_hw: tuple[int, int],
    metadata: dict[str, str],
    *,
    available: int | None = None,
    on_cuda: bool = False,
) -> int:
    """Frames per call for the model at ``path`` so one call fits in the memory available now (the GPU's
    when ``on_cuda``)."""
    heads = int(metadata.get("ffrecon.attention_heads") or DEFAULT_HEADS) or DEFAULT_HEADS
    fp16 = metadata.get("ffrecon.description", "").endswith("fp16")
    fused = metadata.get("ffrecon.attention") == "fused"
    memory = call_memory(
        model_file_bytes(path),
        size_hw,
        heads=heads,
        value_bytes=2 if fp16 else 4,
        scores=not (fused and on_cuda),
        on_cuda=on_cuda,
    )
    free, where = (available, "given") if available is not None else _available(on_cuda)
    budget = MEMORY_FRACTION * free
    frames = min(MAX_CHUNK, max(MIN_CHUNK, memory.max_frames(budget)))
    log.info(
        "chunk size %d frames per call (%.1f GB estimated peak of a %.1f GB budget, %s memory; --chunk-size overrides)",
        frames,
        memory.peak_bytes(frames) / 2**30,
        budget / 2**30,
        where,
    )
    return frames
