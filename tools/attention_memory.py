"""Peak memory of one plain attention layer in onnxruntime (CPU) at VGGT-1B sizes.

Why the default chunk size is 8: a VGGT export with ordinary MatMul-Softmax-MatMul attention holds
a [heads, N, N] float32 score matrix in its global-attention layers, N = S x 1041 tokens for
518 x 392 inputs (1036 patches + 5 special tokens) and 16 heads. This prints the measured peak
for S frames next to the size of that matrix, so the arithmetic behind the default can be checked:

    python tools/attention_memory.py 2 4 8

Measured on the development machine: S=2 0.38 GB, S=4 1.26 GB, S=8 4.74 GB (matrix 4.44 GB), so
~69 MB x S^2, plus ~5 GB of fp32 weights: 8 frames ~ 10 GB, 16 frames ~ 23 GB (too much for 24 GB).
"""

from __future__ import annotations

import resource
import sys

import numpy as np
import onnxruntime as ort
from onnx import TensorProto, helper

TOKENS_PER_FRAME, HEADS, HEAD_DIM = 1041, 16, 64


def attention_model(num_tokens: int) -> bytes:
    inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, [HEADS, num_tokens, HEAD_DIM]) for n in "qkv"]
    nodes = [
        helper.make_node("Transpose", ["k"], ["kt"], perm=[0, 2, 1]),
        helper.make_node("MatMul", ["q", "kt"], ["scores"]),
        helper.make_node("Softmax", ["scores"], ["p"], axis=-1),
        helper.make_node("MatMul", ["p", "v"], ["out"]),
    ]
    out = [helper.make_tensor_value_info("out", TensorProto.FLOAT, [HEADS, num_tokens, HEAD_DIM])]
    model = helper.make_model(
        helper.make_graph(nodes, "attention", inputs, out), opset_imports=[helper.make_opsetid("", 17)]
    )
    model.ir_version = 8
    return model.SerializeToString()


def main(frame_counts: list[int]) -> None:
    for frames in frame_counts:  # peak RSS only grows, so run the counts in increasing order
        n = frames * TOKENS_PER_FRAME
        session = ort.InferenceSession(attention_model(n), providers=["CPUExecutionProvider"])
        x = np.random.default_rng(0).random((HEADS, n, HEAD_DIM), dtype=np.float32) * 0.1
        session.run(None, {"q": x, "k": x, "v": x})
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
        print(
            f"S={frames:3d}  tokens={n:6d}  peak RSS {peak:6.2f} GB   "
            f"one [H,N,N] fp32 matrix {HEADS * n * n * 4 / 1e9:6.2f} GB"
        )


if __name__ == "__main__":
    main(sorted(int(a) for a in sys.argv[1:]) or [2, 4, 8])
