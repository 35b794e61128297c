"""A few lines of sugar over ``onnx.helper`` for graphs built from numpy constants.

Used by the simulated VGGT model and by ``tools/make_test_nets.py``.

>>> g = GraphBuilder("double")
>>> x = g.input("x", ["N"])
>>> g.output(g.op("Mul", [x, g.const(np.float32(2.0))]), "y", ["N"])
>>> len(g.model().graph.node)
2
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


class GraphBuilder:
    """Accumulates nodes, initializers, inputs and outputs; names are generated unless given."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._nodes: list[onnx.NodeProto] = []
        self._initializers: list[onnx.TensorProto] = []
        self._inputs: list[onnx.ValueInfoProto] = []
        self._outputs: list[onnx.ValueInfoProto] = []
        self._count = 0

    def _fresh(self, stem: str) -> str:
        self._count += 1
        return f"{stem}_{self._count}"

    def input(self, name: str, shape: list[int | str], dtype: int = TensorProto.FLOAT) -> str:
        """Declare a graph input; string dimensions are dynamic (named)."""
        self._inputs.append(helper.make_tensor_value_info(name, dtype, shape))
        return name

    def const(self, value: np.ndarray | np.generic, name: str | None = None) -> str:
        """Store a numpy array (dtype kept) as an initializer and return its name."""
        tensor_name = self._fresh(name or "const")
        self._initializers.append(numpy_helper.from_array(np.asarray(value), tensor_name))
        return tensor_name

    def op(self, op_type: str, inputs: list[str], *, n_out: int = 1, **attrs) -> str | list[str]:
        """Add a node; returns its output name, or a list of ``n_out`` names when ``n_out > 1``."""
        outputs = [self._fresh(op_type.lower()) for _ in range(n_out)]
        self._nodes.append(helper.make_node(op_type, inputs, outputs, name=self._fresh("node_" + op_type), **attrs))
        return outputs[0] if n_out == 1 else outputs

    def output(self, value: str, name: str, shape: list[int | str], dtype: int = TensorProto.FLOAT) -> None:
        """Expose ``value`` as graph output ``name``."""
        self._nodes.append(helper.make_node("Identity", [value], [name], name=self._fresh("node_output")))
        self._outputs.append(helper.make_tensor_value_info(name, dtype, shape))

    def model(self, opset: int = 17) -> onnx.ModelProto:
        """The finished model (IR version pinned so that older onnxruntime builds load it)."""
        graph = helper.make_graph(self._nodes, self.name, self._inputs, self._outputs, self._initializers)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], producer_name="ffrecon")
        model.ir_version = 8
        return model


def quat_product_basis() -> np.ndarray:
    """``[4, 4, 4]`` B with ``p (x) q = p @ sum_k q[k] B[k]`` for Hamilton quaternions in xyzw order.

    Lets a graph compose quaternions with two MatMuls: build ``M = q @ B.reshape(4, 16)`` as ``[4, 4]``,
    then ``p (x) q = p @ M``; ``R(p (x) q) = R(p) R(q)``.

    >>> B = quat_product_basis(); i, j = np.eye(4)[0], np.eye(4)[1]
    >>> (i @ np.tensordot(j, B, axes=1)).tolist()  # i * j = k
    [0.0, 0.0, 1.0, 0.0]
    """

    def product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.concatenate([a[3] * b[:3] + b[3] * a[:3] + np.cross(a[:3], b[:3]), [a[3] * b[3] - a[:3] @ b[:3]]])

    eye = np.eye(4)
    return np.array([[product(eye[j], eye[k]) for j in range(4)] for k in range(4)])
