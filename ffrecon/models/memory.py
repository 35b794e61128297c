"""How many frames one multi-view model call can hold: the default chunk size, from available memory.

A multi-view transformer's "global" attention layers attend over all tokens of all S frames at once.
Exported to ONNX as MatMul-Softmax-MatMul, each such layer holds a ``[heads, S*T, S*T]`` float32
score matrix (T tokens per frame), and the softmax writes a second one beside it, so peak memory
grows with S squared; the weights and per-frame activations add a constant and a linear term.
Fitted to the full-size VGGT-1B export at 518 x 392 with ``tools/bench_models.py`` (2, 4, 8 frames:
5.98, 8.05, 15.63 GB; fit 5.05 + 0.178 S + 0.143 S^2 GB; docs/benchmarks.md):

    peak(S) ~ WEIGHT_FACTOR * file bytes + S * LINEAR_BYTES_PER_TOKEN * T + SCORE_COPIES * heads * 4 bytes * (S * T)^2

The default chunk size is the largest S whose peak stays under ``MEMORY_FRACTION`` of the memory
available now (``/proc/meminfo``), between ``MIN_CHUNK`` and ``MAX_CHUNK``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from ffrecon.machine import available_memory_bytes

log = logging.getLogger("ffrecon.models")

WEIGHT_FACTOR = 1.15  # onnxruntime's resident weights per file byte (fit: 5.05 GB for a 4.54 GB file)
LINEAR_BYTES_PER_TOKEN = 4 * 1024 * 45  # activations alive per token (fit: 0.178 GB per 1041-token frame)
SCORE_COPIES = 2  # scores and softmax output (fit: 0.143 GB x S^2 = 2 x 16 heads x 4 B x 1041^2)
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
    model_bytes: int, size_hw: tuple[int, int], *, heads: int = DEFAULT_HEADS, patch: int = 14
) -> CallMemory:
    """The memory model above for a model file of ``model_bytes`` at network input ``size_hw``."""
    tokens = (size_hw[0] // patch) * (size_hw[1] // patch) + SPECIAL_TOKENS
    return CallMemory(
        WEIGHT_FACTOR * model_bytes, LINEAR_BYTES_PER_TOKEN * tokens, SCORE_COPIES * 4.0 * max(heads, 1) * tokens**2
    )


def model_file_bytes(path: Path) -> int:
    """The model file plus its external weight file(s) (``NAME.onnx.data``)."""
    path = Path(path)
    return sum(p.stat().st_size for p in path.parent.glob(path.name + "*") if p.is_file())


def default_chunk_size(
    path: Path, size_hw: tuple[int, int], metadata: dict[str, str], *, available: int | None = None
) -> int:
    """Frames per call for the model at ``path`` so one call fits in the memory available now."""
    heads = int(metadata.get("ffrecon.attention_heads") or DEFAULT_HEADS) or DEFAULT_HEADS
    memory = call_memory(model_file_bytes(path), size_hw, heads=heads)
    budget = MEMORY_FRACTION * (available if available is not None else available_memory_bytes())
    frames = min(MAX_CHUNK, max(MIN_CHUNK, memory.max_frames(budget)))
    log.info(
        "chunk size %d frames per call (%.1f GB estimated peak of %.1f GB budget; --chunk-size overrides)",
        frames,
        memory.peak_bytes(frames) / 2**30,
        budget / 2**30,
    )
    return frames
