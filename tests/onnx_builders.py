"""Small hand-built ONNX graphs for bad-model tests (a NaN-emitting VGGT, a model with unknown names)."""

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


def _const(name, value):
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(np.asarray(value), name))


def vggt_like(path: Path, *, fill: float = 1.0, input_name: str = "input_images") -> Path:
    """A VGGT-contract graph whose depth is ``fill`` everywhere (use NaN for a broken export).

    pose_enc is identity pose with 60 degree fields of view; confidences are 2.
    """
    nodes = [
        _const("axes0", np.array([0], np.int64)),
        _const("axes_last", np.array([-1], np.int64)),
        _const("c_starts", np.array([0], np.int64)),
        _const("c_ends", np.array([1], np.int64)),
        _const("c_axes", np.array([1], np.int64)),
        _const("zero", np.array(0.0, np.float32)),
        _const("fill", np.array(fill, np.float32)),
        _const("two", np.array(2.0, np.float32)),
        _const("pose_row", np.array([0, 0, 0, 0, 0, 0, 1, 1.0472, 1.0472], np.float32)),
        helper.make_node("Slice", [input_name, "c_starts", "c_ends", "c_axes"], ["chan0"]),  # [S,1,H,W]
        helper.make_node("Mul", ["chan0", "zero"], ["zeros"]),
        helper.make_node("Squeeze", ["zeros", "c_axes"], ["zeros_shw"]),  # [S,H,W]
        helper.make_node("Add", ["zeros_shw", "fill"], ["depth_shw"]),
        helper.make_node("Unsqueeze", ["depth_shw", "axes_last"], ["depth_shw1"]),
        helper.make_node("Unsqueeze", ["depth_shw1", "axes0"], ["depth"]),
        helper.make_node("Add", ["zeros_shw", "two"], ["conf_shw"]),
        helper.make_node("Unsqueeze", ["conf_shw", "axes0"], ["depth_conf"]),
        helper.make_node("ReduceMean", ["zeros_shw"], ["per_frame"], axes=[1, 2], keepdims=1),  # [S,1]
        helper.make_node("Add", ["per_frame", "pose_row"], ["pose_s9"]),  # [S,9]
        helper.make_node("Unsqueeze", ["pose_s9", "axes0"], ["pose_enc"]),
    ]
    graph = helper.make_graph(
        nodes,
        "vggt_like",
        [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, ["S", 3, "H", "W"])],
        [
            helper.make_tensor_value_info("pose_enc", TensorProto.FLOAT, [1, "S", 9]),
            helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, "S", "H", "W", 1]),
            helper.make_tensor_value_info("depth_conf", TensorProto.FLOAT, [1, "S", "H", "W"]),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path
