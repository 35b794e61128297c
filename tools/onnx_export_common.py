"""Export helpers shared by tools/export_vggt_onnx.py and tools/export_dust3r_onnx.py.

The scripts run from tools/ (``python tools/export_vggt_onnx.py``), so Python finds this module
beside them without any path manipulation.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger("onnx_export")
PROTOBUF_LIMIT = 2**31 - 2**24  # bytes; larger models keep their weights in an external .data file


def export_onnx(module: torch.nn.Module, inputs: tuple[torch.Tensor, ...], input_names: list[str], output_names: list[str], dynamic_axes: dict, out: Path, *, opset: int, exporter: str, metadata: dict[str, str], fp16: bool) -> list[Path]:
    """Export, attach metadata, optionally convert to fp16, save (external data when large). Returns the files written."""
    import onnx

    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        raw = Path(tmp) / "raw.onnx"
        with torch.no_grad():
            torch.onnx.export(module, inputs, str(raw), input_names=input_names, output_names=output_names, dynamic_axes=dynamic_axes, opset_version=opset, dynamo=exporter == "dynamo")
        model = onnx.load(str(raw))  # also reads any external weight files the exporter wrote
    if fp16:
        try:
            from onnxconverter_common import float16
        except ImportError as exc:
            raise SystemExit("error: --fp16 needs onnxconverter-common.\n  fix: pip install onnxconverter-common") from exc
        # Inputs and outputs stay float32 so that callers (ffrecon) feed and read float32.
        model = float16.convert_float_to_float16(model, keep_io_types=True, disable_shape_infer=True)
    onnx.helper.set_model_props(model, metadata)
    data = out.with_name(out.name + ".data")
    for stale in (out, data):
        stale.unlink(missing_ok=True)
    if model.ByteSize() < PROTOBUF_LIMIT:
        onnx.save_model(model, str(out))
        return [out]
    onnx.save_model(model, str(out), save_as_external_data=True, all_tensors_to_one_file=True, location=data.name, size_threshold=1024)
    return [out, data]


def verify_onnx(path: Path, feeds: dict[str, np.ndarray], reference: dict[str, np.ndarray], *, rtol: float) -> float:
    """Run the file with onnxruntime and compare with PyTorch; returns the worst relative error."""
    import onnxruntime as ort

    providers = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in ort.get_available_providers()]
    try:
        session = ort.InferenceSession(str(path), providers=providers)
    except Exception as exc:  # onnxruntime raises several types; all mean the same here
        raise SystemExit(f"error: onnxruntime cannot load {path}: {str(exc).splitlines()[0]}\n"
                         "  fix: fp16 files often need onnxruntime-gpu (CUDA); verify there, or pass --skip-verify") from exc
    names = [o.name for o in session.get_outputs()]
    got = dict(zip(names, session.run(names, feeds)))
    worst = 0.0
    for name, want in reference.items():
        have = got[name]
        if have.shape != want.shape or not np.isfinite(have).all():
            raise SystemExit(f"error: output '{name}' is {have.shape} with {int((~np.isfinite(have)).sum())} non-finite values; PyTorch gave {want.shape}")
        err = float(np.abs(have - want).max() / (np.abs(want).max() + 1e-6))
        log.info("  %-20s %-22s max relative difference %.2e", name, str(list(have.shape)), err)
        worst = max(worst, err)
    if worst > rtol:
        raise SystemExit(f"error: onnxruntime and PyTorch differ by up to {worst:.2e} (tolerance {rtol:.0e}); the export is not usable at these sizes")
    return worst


def add_export_options(parser: argparse.ArgumentParser) -> None:
    """The options both export scripts share (exporter, opset, precision, verification)."""
    parser.add_argument("--opset", type=int, default=17)
    parser.add_argument("--exporter", choices=("torchscript", "dynamo"), default="torchscript", help="torch.onnx exporter (dynamo needs onnxscript; default: %(default)s)")
    parser.add_argument("--fp16", action="store_true", help="store weights and compute in fp16 (half the size; may overflow, see the docs)")
    parser.add_argument("--skip-verify", action="store_true", help="do not compare onnxruntime with PyTorch")


def check_input_size(parser: argparse.ArgumentParser, args: argparse.Namespace, patch_size: int) -> None:
    """Exports fix H and W; both must be multiples of the model's patch size."""
    if args.height % patch_size or args.width % patch_size:
        parser.error(f"--height and --width must be multiples of {patch_size}")
