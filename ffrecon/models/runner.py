"""onnxruntime sessions and model-family detection from declared inputs and outputs."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from ffrecon.errors import InputError, ModelError
from ffrecon.types import ModelFamily, ModelInfo

log = logging.getLogger("ffrecon.models")

# Declared names that identify each family (CONTRACTS.md sections 1 and 2).
MULTIVIEW_INPUT = "input_images"
MULTIVIEW_OUTPUTS = ("pose_enc", "depth", "depth_conf")
PAIRWISE_INPUTS = ("view1", "view2")
PAIRWISE_OUTPUTS = ("pts3d", "conf", "pts3d_in_other_view", "conf_in_other_view")
# Families that share the idea but not the contract: named so the error can say what was found.
KNOWN_UNSUPPORTED = {
    "camera_poses": "a Pi3/MapAnything-style model (camera_poses are world_from_cam)",
    "extrinsics": "a Depth-Anything-3-style model (extrinsics are cam_from_world, 504 px)",  # onnx name
}


@dataclass(frozen=True)
class TensorSpec:
    name: str
    shape: tuple[int | str | None, ...]
    dtype: str

    def __str__(self) -> str:
        dims = ", ".join("?" if d is None else str(d) for d in self.shape)
        return f"{self.name} [{dims}] {self.dtype}"


class OnnxModel:
    """An onnxruntime session with the model's declared I/O and detected family.

    Uses the CUDA provider when onnxruntime offers it, else the CPU with ``threads`` threads.
    """

    def __init__(self, path: Path | str, *, threads: int = 0, use_cuda: bool = True) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"model file not found: {self.path}", "pass the path of an .onnx file (see docs/exporting_models.md to make one)")
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads or (os.cpu_count() or 1)
        options.log_severity_level = 3
        providers = ["CPUExecutionProvider"]
        if use_cuda and "CUDAExecutionProvider" in ort.get_available_providers():
            providers.insert(0, "CUDAExecutionProvider")
        try:
            self.session = ort.InferenceSession(str(self.path), options, providers=providers)
        except Exception as exc:  # onnxruntime raises several unrelated types for unreadable files
            raise ModelError(f"onnxruntime cannot load {self.path}: {str(exc).splitlines()[0]}", "check that the file is a complete ONNX model (re-export or re-download it)") from exc
        self.providers = tuple(self.session.get_providers())
        self.inputs = tuple(TensorSpec(i.name, tuple(i.shape), i.type) for i in self.session.get_inputs())
        self.outputs = tuple(TensorSpec(o.name, tuple(o.shape), o.type) for o in self.session.get_outputs())
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        self.family = detect_family(self.inputs, self.outputs, self.path)
        log.debug("loaded %s (%s) on %s", self.path.name, self.family.value, self.providers)

    @property
    def simulated(self) -> bool:
        return self.metadata.get("ffrecon.simulated", "").lower() == "true"

    def fixed_size_hw(self, input_name: str) -> tuple[int, int] | None:
        """``(H, W)`` if the export fixed the spatial size of ``input_name``, else None."""
        spec = next((i for i in self.inputs if i.name == input_name), None)
        if spec is None or len(spec.shape) < 2:
            return None
        h, w = spec.shape[-2:]
        return (h, w) if isinstance(h, int) and isinstance(w, int) else None

    def info(self) -> ModelInfo:
        desc = self.metadata.get("ffrecon.description", "")
        return ModelInfo(str(self.path), self.family, self.simulated, desc)

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Run the model; returns all declared outputs by name."""
        names = [o.name for o in self.outputs]
        try:
            values = self.session.run(names, feeds)
        except Exception as exc:
            shapes = {k: v.shape for k, v in feeds.items()}
            raise ModelError(f"{self.path.name} failed on inputs {shapes}: {str(exc).splitlines()[0]}", "check the input sizes the model accepts with `ffrecon inspect-model`") from exc
        return dict(zip(names, values))


def detect_family(inputs: tuple[TensorSpec, ...], outputs: tuple[TensorSpec, ...], path: Path | str = "model") -> ModelFamily:
    """Model family from declared names; a readable :class:`ModelError` when nothing matches."""
    in_names = {i.name for i in inputs}
    out_names = {o.name for o in outputs}
    if MULTIVIEW_INPUT in in_names and set(MULTIVIEW_OUTPUTS) <= out_names:
        return ModelFamily.MULTIVIEW
    if set(PAIRWISE_INPUTS) <= in_names and set(PAIRWISE_OUTPUTS) <= out_names:
        return ModelFamily.PAIRWISE
    found = ", ".join(str(s) for s in inputs) + " -> " + ", ".join(str(s) for s in outputs)
    hint = next((v for k, v in KNOWN_UNSUPPORTED.items() if k in out_names), None)
    raise ModelError(
        f"{Path(path).name} matches no supported model contract. Found: {found}."
        + (f" It looks like {hint}, which ffrecon does not support yet." if hint else ""),
        f"expected either a VGGT-style model (input '{MULTIVIEW_INPUT}' [S,3,H,W]; outputs {', '.join(MULTIVIEW_OUTPUTS)}) "
        f"or a DUSt3R-style pairwise model (inputs {', '.join(PAIRWISE_INPUTS)}; outputs {', '.join(PAIRWISE_OUTPUTS)}); "
        "export with tools/export_vggt_onnx.py or tools/export_dust3r_onnx.py (docs/exporting_models.md)",
    )
