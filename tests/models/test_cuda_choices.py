"""What the model stage decides for onnxruntime's CUDA provider, checked without a GPU.

The provider itself ran on an H100 (docs/benchmarks.md); here: the chunk size follows the GPU's free
memory and the file's attention kind, and a CUDA provider that is offered but does not load is said,
not silently replaced by the CPU.
"""

import logging
from pathlib import Path

import pytest

from ffrecon.models import memory, runner
from ffrecon.models.memory import default_chunk_size
from ffrecon.models.runner import OnnxModel

TINY_VGGT = Path(__file__).resolve().parents[2] / "models" / "tiny_vggt.onnx"
GB = 2**30


def _file(tmp_path: Path, gigabytes: float) -> Path:
    path = tmp_path / "m.onnx"
    with open(path, "wb") as f:  # sparse: only the size matters to the memory model
        f.truncate(int(gigabytes * GB))
    return path


@pytest.mark.parametrize(
    "attention,on_cuda,want",
    [
        # VGGT-1B fp32 at 518 x 392 with 40 GB free (budget 28 GB; weights 5.2 GB):
        ("math", False, 12),  # CPU fit of docs/benchmarks.md: 0.18 GB a frame + 0.143 GB x S^2
        ("fused", False, 12),  # the CPU kernel of MultiHeadAttention still holds the scores
        ("math", True, 9),  # CUDA: its 1.21 GB a frame, plus the scores
        ("fused", True, 18),  # CUDA, no scores: linear only
    ],
)
def test_chunk_size_follows_the_provider_and_the_attention(tmp_path, attention, on_cuda, want):
    path = _file(tmp_path, 4.54)
    metadata = {"ffrecon.attention_heads": "16", "ffrecon.attention": attention, "ffrecon.description": "x, fp32"}
    assert default_chunk_size(path, (392, 518), metadata, available=40 * GB, on_cuda=on_cuda) == want


def test_chunk_size_on_cuda_reads_the_gpu_not_the_host(tmp_path, monkeypatch):
    path = _file(tmp_path, 2.27)
    monkeypatch.setattr(memory, "cuda_free_memory_bytes", lambda: 79 * GB)
    monkeypatch.setattr(memory, "available_memory_bytes", lambda: 8 * GB)
    metadata = {"ffrecon.attention": "fused", "ffrecon.description": "VGGT-1B, fp16"}
    on_gpu = default_chunk_size(path, (392, 518), metadata, on_cuda=True)
    on_host = default_chunk_size(path, (392, 518), metadata, on_cuda=False)
    assert on_gpu > 60 and on_host < on_gpu  # 0.7 x 79 GB at 0.65 GB a fp16 frame -> the 64-frame cap


def test_offered_cuda_that_does_not_load_is_said(monkeypatch, caplog):
    """onnxruntime lists CUDA but the session comes up on the CPU (missing CUDA/cuDNN): a warning with the fix."""
    offered = [*runner.ort.get_available_providers(), "CUDAExecutionProvider"]
    monkeypatch.setattr(runner.ort, "get_available_providers", lambda: offered)
    with caplog.at_level(logging.WARNING, logger="ffrecon.models"):
        model = OnnxModel(TINY_VGGT)
    assert not model.on_cuda and model.providers == ("CPUExecutionProvider",)
    assert "runs on the CPU" in caplog.text and "onnxruntime-gpu" in caplog.text
