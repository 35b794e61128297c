"""What every family's export shares: options, the traced module's description, export and verification.

A family module (``ffrecon/models/exporting/<family>.py``) builds an :class:`ExportSpec` (the
upstream model wrapped so that it takes and returns plain tensors with ffrecon's contract names);
:func:`export_spec` traces it with the TorchScript exporter under :func:`patches.export_rewrites`,
attaches the metadata ffrecon detects families by, optionally converts to fp16, saves (external
data beyond protobuf's 2 GB) and checks onnxruntime against PyTorch at a second frame/pair count.
"""

from __future__ import annotations

import contextlib
import logging
import resource
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ffrecon.errors import FFReconError, ModelError
from ffrecon.models.exporting.patches import export_rewrites, frozen_position_embeddings

log = logging.getLogger("ffrecon.export_model")

PROTOBUF_LIMIT = 2**31 - 2**24  # bytes; larger models keep their weights in an external NAME.onnx.data
FP32_TOLERANCE = 1e-3  # worst relative difference onnxruntime vs PyTorch accepted by the CLI
FP16_TOLERANCE = 5e-2


@dataclass(frozen=True, kw_only=True)
class ModelExportOptions:
    """What ``ffrecon export-model`` was asked for."""

    family: str
    out: Path
    checkpoint: str | None = None  # file or folder users download (or a Hugging Face id where upstream takes one)
    upstream: Path | None = None  # root of the upstream clone (None: an installed package)
    size_hw: tuple[int, int] | None = None  # network input size (None: from the photos, else the family's default)
    photos: Path | None = None  # a photo or folder the model will be used on: fixes size_hw
    fp16: bool = False
    fused_attention: bool = False  # onnxruntime's MultiHeadAttention op (CUDA: memory linear in frames)
    random_init: bool = False  # the real full-size architecture with random weights
    tiny: bool = False  # the same upstream classes at a small configuration (tests)
    variant: str | None = None  # which upstream configuration to build, for families with several (da3, monodepth)
    keep_untrained_heads: bool = False  # random weights: leave heads that decode to invalid cameras as they are (tests)
    opset: int = 17
    count: int = 2  # frames (or pairs) in the traced example; verification uses count + 1
    verify: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        if self.checkpoint is None and not (self.random_init or self.tiny):
            raise FFReconError(
                "no weights given",
                "pass --checkpoint FILE_OR_FOLDER, or --random-init / --tiny to check the export path without weights",
            )
        if self.checkpoint is not None and (self.random_init or self.tiny):
            raise FFReconError("--checkpoint cannot be combined with --random-init or --tiny", "drop one of them")
        if self.opset < 15:
            raise FFReconError(f"opset {self.opset} is too old", "use --opset 17 (the default) or newer")
        if self.count < 1:
            raise FFReconError(
                f"the traced example needs at least one frame or pair, got {self.count}", "use --frames 2"
            )

    @property
    def weights(self) -> str:
        return self.checkpoint or ("random (tiny configuration)" if self.tiny else "random (full size)")


@dataclass
class ExportSpec:
    """A traceable model and how to feed it.

    ``module(*inputs)`` returns a tuple of tensors in ``output_names`` order. ``make_inputs(n, rng)``
    returns numpy inputs for ``n`` frames (multi-view) or pairs (pairwise), in ``input_names`` order.
    """

    family: str
    module: torch.nn.Module
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    dynamic_axes: dict[str, dict[int, str]]
    make_inputs: Callable[[int, np.random.Generator], tuple[np.ndarray, ...]]
    size_hw: tuple[int, int]
    contract: str  # value of the ffrecon.contract metadata (the runner's family key)
    description: str
    notes: list[str] = field(default_factory=list)  # what was changed from upstream's output, for the metadata
    extra_metadata: dict[str, str] = field(default_factory=dict)
    # Extra rewrites for the trace (entered after the model ran once at the export size, outside it).
    trace_context: Callable[[torch.nn.Module], contextlib.AbstractContextManager] | None = frozen_position_embeddings


@dataclass(frozen=True)
class ExportReport:
    files: tuple[Path, ...]
    worst_difference: float | None  # None when not verified
    differences: dict[str, float]
    verify_count: int
    export_seconds: float
    verify_seconds: float
    peak_rss_gb: float
    parameters: int

    def summary(self) -> str:
        lines = [f"wrote {p} ({p.stat().st_size / 2**20:.1f} MiB)" for p in self.files]
        lines.append(
            f"{self.parameters / 1e6:.1f} M parameters; export {self.export_seconds:.0f} s, "
            f"verification {self.verify_seconds:.0f} s, peak memory {self.peak_rss_gb:.1f} GB"
        )
        if self.worst_difference is not None:
            per = ", ".join(f"{k} {v:.1e}" for k, v in self.differences.items())
            lines.append(
                f"onnxruntime vs PyTorch at {self.verify_count} frames/pairs: "
                f"worst relative difference {self.worst_difference:.2e} ({per})"
            )
        return "\n".join(lines)


def peak_rss_gb() -> float:
    """This process's peak resident memory so far, in GB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def torch_outputs(spec: ExportSpec, inputs: tuple[np.ndarray, ...]) -> dict[str, np.ndarray]:
    """Run the wrapped PyTorch module (no export rewrites) and return float32 numpy outputs by name."""
    with torch.no_grad():
        values = spec.module(*(torch.from_numpy(x) for x in inputs))
    return {name: v.detach().float().numpy() for name, v in zip(spec.output_names, values)}


def relative_difference(have: np.ndarray, want: np.ndarray) -> float:
    """``max |have - want| / max |want|`` (inf for shape mismatches or non-finite values).

    >>> relative_difference(np.array([1.0, 2.0]), np.array([1.0, 2.002]))
    0.000999...
    """
    if have.shape != want.shape or not np.isfinite(have).all():
        return float("inf")
    return float(np.abs(have.astype(np.float64) - want).max() / (np.abs(want).max() + 1e-12))


def export_spec(spec: ExportSpec, options: ModelExportOptions) -> ExportReport:
    """Trace, save and verify one :class:`ExportSpec` to ``options.out``."""
    import onnx

    out = Path(options.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(options.seed)
    example = tuple(torch.from_numpy(x) for x in spec.make_inputs(options.count, rng))
    params = sum(p.numel() for p in spec.module.parameters())
    log.info(
        "exporting %s (%.1f M parameters) at %d frames/pairs, %dx%d, opset %d",
        spec.family,
        params / 1e6,
        options.count,
        spec.size_hw[1],
        spec.size_hw[0],
        options.opset,
    )
    start = time.perf_counter()
    model, warm = _trace(spec, example, options, out.parent)
    _declare_output_shapes(model, warm, spec.dynamic_axes)
    if options.fp16:
        try:
            from onnxconverter_common import float16
        except ImportError as exc:
            raise FFReconError("--fp16 needs onnxconverter-common", "pip install 'ffrecon[export]'") from exc
        model = _to_fp16(model, float16)
    onnx.helper.set_model_props(model, _metadata(spec, options, params))
    files = _save(model, out)
    del model  # the proto holds a copy of every weight: free it before the verification runs the model twice
    export_seconds = time.perf_counter() - start
    differences: dict[str, float] = {}
    verify_seconds = 0.0
    count = options.count + 1  # another count than the traced one: checks that it really is dynamic
    if options.verify:
        start = time.perf_counter()
        differences = verify(spec, out, spec.make_inputs(count, rng))
        verify_seconds = time.perf_counter() - start
        _require_within_tolerance(differences, count, options.fp16)
    return ExportReport(
        tuple(files),
        max(differences.values()) if differences else None,
        differences,
        count,
        export_seconds,
        verify_seconds,
        peak_rss_gb(),
        params,
    )


def _trace(spec: ExportSpec, example: tuple[torch.Tensor, ...], options: ModelExportOptions, tmp_parent: Path):
    """Trace ``spec.module`` on ``example`` into an ONNX proto; also return PyTorch's outputs on it.

    The module runs once before the trace: that fills the size-dependent caches (see ``patches``).
    The exporter writes to a temporary folder under ``tmp_parent`` (it may write external weight
    files next to the graph), which is loaded back and removed.
    """
    import onnx

    with tempfile.TemporaryDirectory(dir=tmp_parent, prefix=".export-") as tmp:
        raw = Path(tmp) / "raw.onnx"
        context = spec.trace_context(spec.module) if spec.trace_context else contextlib.nullcontext()
        with torch.no_grad(), context:
            warm = torch_outputs(spec, tuple(x.numpy() for x in example))
            try:
                with export_rewrites(fused_attention=options.fused_attention):
                    torch.onnx.export(
                        spec.module,
                        example,
                        str(raw),
                        input_names=list(spec.input_names),
                        output_names=list(spec.output_names),
                        dynamic_axes=spec.dynamic_axes,
                        opset_version=options.opset,
                        custom_opsets={"com.microsoft": 1} if options.fused_attention else None,
                        dynamo=False,
                    )
            except Exception as exc:  # the exporter raises many types; all mean "this graph did not export"
                raise ModelError(
                    f"the ONNX exporter failed on {spec.family}: {str(exc).splitlines()[0]}",
                    "this upstream version uses an operator ffrecon does not rewrite yet; "
                    "report it with the upstream commit",
                ) from exc
        model = onnx.load(str(raw))  # also reads external weight files the exporter wrote
    return model, warm


def _metadata(spec: ExportSpec, options: ModelExportOptions, params: int) -> dict[str, str]:
    """The ``ffrecon.*`` metadata properties the runner detects families by and inspect-model shows."""
    return {
        "ffrecon.contract": spec.contract,
        "ffrecon.family": spec.family,
        "ffrecon.description": spec.description + (", fp16" if options.fp16 else ", fp32"),
        "ffrecon.input_size_hw": f"{spec.size_hw[0]},{spec.size_hw[1]}",
        "ffrecon.weights": options.weights,
        "ffrecon.notes": " | ".join(spec.notes),
        "ffrecon.torch": torch.__version__,
        # For ffrecon.models.memory: "fused" (onnxruntime's MultiHeadAttention) holds no score matrix on CUDA.
        "ffrecon.attention": "fused" if options.fused_attention else "math",
        # For ffrecon.models.memory: the widest attention's head count sizes the frames-squared score matrices.
        "ffrecon.attention_heads": str(
            max((int(getattr(m, "num_heads", 0) or 0) for m in spec.module.modules()), default=0)
        ),
        "ffrecon.parameters": str(params),
        **spec.extra_metadata,
    }


def _require_within_tolerance(differences: dict[str, float], count: int, fp16: bool) -> None:
    """Raise :class:`ModelError` if onnxruntime and PyTorch differ by more than the precision allows."""
    worst = max(differences.values())
    tolerance = FP16_TOLERANCE if fp16 else FP32_TOLERANCE
    if not worst <= tolerance:
        raise ModelError(
            f"onnxruntime and PyTorch differ by up to {worst:.2e} at {count} frames/pairs "
            f"(tolerance {tolerance:.0e}): {differences}",
            "the traced graph does not generalise; export with --frames equal to the chunk size you will run, "
            "and report the upstream commit",
        )


def verify(spec: ExportSpec, path: Path, inputs: tuple[np.ndarray, ...]) -> dict[str, float]:
    """Worst relative difference per output between onnxruntime (CPU) and PyTorch on ``inputs``."""
    import onnxruntime as ort

    reference = torch_outputs(spec, inputs)
    options = ort.SessionOptions()
    options.log_severity_level = 3
    try:
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises several types; all mean the same here
        raise ModelError(
            f"onnxruntime cannot load {path}: {str(exc).splitlines()[0]}",
            "fp16 files may need onnxruntime-gpu; verify there, or pass --skip-verify",
        ) from exc
    got = session.run(list(spec.output_names), dict(zip(spec.input_names, inputs)))
    return {name: relative_difference(have, reference[name]) for name, have in zip(spec.output_names, got)}


def _to_fp16(model, float16):
    """fp16 weights and compute, float32 inputs and outputs (so that ffrecon feeds and reads float32).

    onnxconverter-common retypes tensors and initialisers but leaves the exporter's own
    ``Cast(to=float32)`` nodes (the ``.to(dtype)`` and ``.float()`` calls in upstream code), which then
    feed float32 into fp16 arithmetic and the file fails to load. Those casts are retyped to fp16
    here; the casts the converter adds itself (at the inputs and outputs) are left alone.
    """
    import onnx

    exporter_casts = {n.name for n in model.graph.node if n.op_type == "Cast"}
    model = float16.convert_float_to_float16(model, keep_io_types=True, disable_shape_infer=True)
    outputs = {o.name for o in model.graph.output}
    for node in model.graph.node:
        if node.op_type == "Cast" and node.name in exporter_casts and not set(node.output) & outputs:
            for attr in node.attribute:
                if attr.name == "to" and attr.i == onnx.TensorProto.FLOAT:
                    attr.i = onnx.TensorProto.FLOAT16
    return model


def _declare_output_shapes(model, outputs: dict[str, np.ndarray], dynamic_axes: dict[str, dict[int, str]]) -> None:
    """Name the dynamic axes and fix the others in the declared output shapes (the tracer leaves
    names like ``Concatlocal_points_dim_0``), so ``ffrecon inspect-model`` shows the contract."""
    for output in model.graph.output:
        if output.name not in outputs:
            continue
        dims = output.type.tensor_type.shape.dim
        shape = outputs[output.name].shape
        if len(dims) != len(shape):
            continue
        for axis, dim in enumerate(dims):
            name = dynamic_axes.get(output.name, {}).get(axis)
            if name:
                dim.dim_param = name
            else:
                dim.dim_value = int(shape[axis])


def _save(model, out: Path) -> list[Path]:
    import onnx

    data = out.with_name(out.name + ".data")
    for stale in (out, data):
        stale.unlink(missing_ok=True)
    # Sum the weights rather than call ByteSize(): protobuf cannot even measure a message over 2 GB.
    weight_bytes = sum(len(t.raw_data) or t.ByteSize() for t in model.graph.initializer)
    if weight_bytes < PROTOBUF_LIMIT - 2**26:
        onnx.save_model(model, str(out))
        return [out]
    onnx.save_model(
        model,
        str(out),
        save_as_external_data=True,
        all_tensors_to_one_file=True,
        location=data.name,
        size_threshold=1024,
    )
    return [out, data]


def random_images(
    count: int,
    size_hw: tuple[int, int],
    rng: np.random.Generator,
    *,
    low: float = 0.0,
    high: float = 1.0,
    batch_axis: bool = False,
) -> np.ndarray:
    """``[count, 3, H, W]`` (or ``[1, count, 3, H, W]``) float32 uniform in [low, high]: example inputs."""
    x = rng.uniform(low, high, (count, 3, *size_hw)).astype(np.float32)
    return x[None] if batch_axis else x
