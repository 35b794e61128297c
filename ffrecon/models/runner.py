"""onnxruntime sessions and model-family detection from declared inputs and outputs."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from ffrecon.concurrency import available_cores
from ffrecon.errors import InputError, ModelError
from ffrecon.types import ModelFamily, ModelInfo

log = logging.getLogger("ffrecon.models")

# Declared names that identify each family (docs/models.md): (inputs, outputs) each family's files
# must declare. Exports from ``ffrecon export-model`` also carry ``ffrecon.contract`` metadata.
MULTIVIEW_INPUT = "input_images"
MULTIVIEW_OUTPUTS = ("pose_enc", "depth", "depth_conf")
PAIRWISE_INPUTS = ("view1", "view2")
PAIRWISE_OUTPUTS = ("pts3d", "conf", "pts3d_in_other_view", "conf_in_other_view")
SIGNATURES: dict[ModelFamily, tuple[tuple[str, ...], tuple[str, ...]]] = {
    ModelFamily.MULTIVIEW: ((MULTIVIEW_INPUT,), MULTIVIEW_OUTPUTS),
    ModelFamily.DA3: (("images",), ("depth", "depth_conf", "extrinsics", "intrinsics")),
    ModelFamily.PI3: (("images",), ("local_points", "conf", "camera_poses")),
    ModelFamily.MAPANYTHING: (("images",), ("ray_directions", "depth_along_ray", "cam_trans", "cam_quats", "conf")),
    ModelFamily.MONODEPTH: (("pixel_values",), ("predicted_depth",)),
    ModelFamily.PAIRWISE: (PAIRWISE_INPUTS, PAIRWISE_OUTPUTS),
}
FAMILY_NAMES = {
    ModelFamily.MULTIVIEW: "VGGT",
    ModelFamily.DA3: "Depth Anything 3",
    ModelFamily.PI3: "Pi3",
    ModelFamily.MAPANYTHING: "MapAnything",
    ModelFamily.MONODEPTH: "monocular depth (Depth Anything V2 / DPT)",
    ModelFamily.PAIRWISE: "DUSt3R / MASt3R (pairwise)",
}


@dataclass(frozen=True)
class TensorSpec:
    name: str
    shape: tuple[int | str | None, ...]
    dtype: str

    def __str__(self) -> str:
        dims = ", ".join("?" if d is None else str(d) for d in self.shape)
        return f"{self.name} [{dims}] {self.dtype}"


# The arena grows by what a call asks for instead of to the next power of two (a 20 GB call of a large
# model would otherwise reserve 32 GB of the GPU).
CUDA_PROVIDER_OPTIONS = {"arena_extend_strategy": "kSameAsRequested"}


def _cuda_offered() -> bool:
    """Whether this onnxruntime build has the CUDA provider; loads the CUDA/cuDNN libraries of NVIDIA's pip
    wheels first (``onnxruntime.preload_dlls``, onnxruntime >= 1.21), which the provider does not find itself."""
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        return False
    preload = getattr(ort, "preload_dlls", None)
    if preload is not None:
        try:
            preload(cuda=True, cudnn=True, msvc=False)
        except Exception as exc:  # libraries found elsewhere (system CUDA) still work: the session decides
            log.debug("onnxruntime.preload_dlls: %s", exc)
    return True


def cpu_threads(threads: int = 0, *, use_cuda: bool = True) -> int:
    """CPU threads an :class:`OnnxModel` made with these arguments keeps busy: its intra-op threads on the
    CPU (``threads``, 0: the cores this process may run on, :func:`~ffrecon.concurrency.available_cores`), one
    (the Python side of the stage) when the model runs on CUDA."""
    if use_cuda and "CUDAExecutionProvider" in ort.get_available_providers():
        return 1
    return threads or available_cores()


class OnnxModel:
    """An onnxruntime session with the model's declared I/O and detected family.

    Uses the CUDA provider when onnxruntime offers it, else the CPU with ``threads`` threads. ``while_running``
    is entered around every run of the session (e.g. a :meth:`ffrecon.concurrency.CoreShare.claim` of the
    cores it keeps busy).
    """

    def __init__(
        self,
        path: Path | str,
        *,
        threads: int = 0,
        use_cuda: bool = True,
        while_running: Callable[[], AbstractContextManager] = contextlib.nullcontext,
    ) -> None:
        self.path = Path(path)
        self.while_running = while_running
        if not self.path.is_file():
            raise InputError(
                f"model file not found: {self.path}", "pass the path of an .onnx file (see docs/models.md to make one)"
            )
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads or available_cores()  # taskset/cpuset: not the machine's count
        options.log_severity_level = 3
        providers: list = ["CPUExecutionProvider"]
        cuda = use_cuda and _cuda_offered()
        if cuda:
            providers.insert(0, ("CUDAExecutionProvider", CUDA_PROVIDER_OPTIONS))
        try:
            self.session = ort.InferenceSession(str(self.path), options, providers=providers)
        except Exception as exc:  # onnxruntime raises several unrelated types for unreadable files
            raise ModelError(
                f"onnxruntime cannot load {self.path}: {str(exc).splitlines()[0]}",
                "check that the file is a complete ONNX model (re-export or re-download it)",
            ) from exc
        self.providers = tuple(self.session.get_providers())
        if cuda and not self.on_cuda:
            log.warning(
                "onnxruntime offers CUDA but its provider did not load (CUDA or cuDNN libraries it was built for "
                "are missing): %s runs on the CPU. Fix: pip install 'onnxruntime-gpu[cuda,cudnn]' or the matching "
                "CUDA/cuDNN",
                self.path.name,
            )
        self.inputs = tuple(TensorSpec(i.name, tuple(i.shape), i.type) for i in self.session.get_inputs())
        self.outputs = tuple(TensorSpec(o.name, tuple(o.shape), o.type) for o in self.session.get_outputs())
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        self.family = detect_family(self.inputs, self.outputs, self.path, self.metadata)
        log.debug("loaded %s (%s) on %s", self.path.name, self.family.value, self.providers)

    @property
    def on_cuda(self) -> bool:
        """Whether the session runs on onnxruntime's CUDA provider (else the CPU)."""
        return "CUDAExecutionProvider" in self.providers

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
        return ModelInfo(str(self.path), self.family, self.simulated, desc, metadata=dict(self.metadata))

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Run the model; returns all declared outputs by name."""
        names = [o.name for o in self.outputs]
        try:
            with self.while_running():
                values = self.session.run(names, feeds)
        except Exception as exc:
            shapes = {k: v.shape for k, v in feeds.items()}
            raise ModelError(
                f"{self.path.name} failed on inputs {shapes}: {str(exc).splitlines()[0]}",
                "check the input sizes the model accepts with `ffrecon inspect-model`",
            ) from exc
        return dict(zip(names, values))

    def run_checked(self, image_input: str, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """:meth:`run`, first checking the batch against sizes the export baked in (a clearer error than
        onnxruntime's)."""
        fixed = self.fixed_size_hw(image_input)
        got = tuple(feeds[image_input].shape[-2:])
        if fixed is not None and got != fixed:
            raise ModelError(
                f"{self.path.name} was exported for {fixed[1]}x{fixed[0]} inputs, "
                f"but these photos preprocess to {got[1]}x{got[0]}",
                "re-export the model for these photos (`ffrecon export-model ... --photos DIR`, or "
                f"--height {got[0]} --width {got[1]}), or use photos of the aspect ratio it was exported for",
            )
        return self.run(feeds)


def _matches(family: ModelFamily, in_names: set[str], out_names: set[str]) -> bool:
    inputs, outputs = SIGNATURES[family]
    return set(inputs) <= in_names and set(outputs) <= out_names


def detect_family(
    inputs: tuple[TensorSpec, ...],
    outputs: tuple[TensorSpec, ...],
    path: Path | str = "model",
    metadata: dict[str, str] | None = None,
) -> ModelFamily:
    """Model family from the ``ffrecon.contract`` metadata and the declared names.

    The metadata picks the family when present; the declared names must still match it (a file
    whose metadata and names disagree is rejected). Without metadata the names decide.
    Raises:
        ModelError: nothing matches; the message lists what was found and what each family expects.
    """
    in_names = {i.name for i in inputs}
    out_names = {o.name for o in outputs}
    found = ", ".join(str(s) for s in inputs) + " -> " + ", ".join(str(s) for s in outputs)
    claimed = (metadata or {}).get("ffrecon.contract")
    if claimed:
        family = next((f for f in ModelFamily if f.value == claimed), None)
        if family is None:
            raise ModelError(
                f"{Path(path).name} says it follows the '{claimed}' contract, which this ffrecon does not know. "
                f"Found: {found}.",
                f"supported contracts: {', '.join(f.value for f in ModelFamily)}; "
                "update ffrecon or re-export the model",
            )
        if _matches(family, in_names, out_names):
            return family
        want_in, want_out = SIGNATURES[family]
        raise ModelError(
            f"{Path(path).name} says it follows the {FAMILY_NAMES[family]} contract but declares other names. "
            f"Found: {found}.",
            f"{FAMILY_NAMES[family]} needs inputs {', '.join(want_in)} and outputs {', '.join(want_out)}; "
            "re-export with `ffrecon export-model`",
        )
    for family in SIGNATURES:
        if _matches(family, in_names, out_names):
            return family
    expected = "; ".join(
        f"{FAMILY_NAMES[f]}: inputs {', '.join(i)} -> outputs {', '.join(o)}" for f, (i, o) in SIGNATURES.items()
    )
    raise ModelError(
        f"{Path(path).name} matches no supported model contract. Found: {found}.",
        f"supported families and the names they declare: {expected}. "
        "Export models with `ffrecon export-model FAMILY` (docs/models.md)",
    )
