#!/usr/bin/env python
"""Export VGGT (facebookresearch/vggt) to ONNX with ffrecon's multi-view contract (CONTRACTS.md section 1).

Input ``input_images [S, 3, H, W]`` float32 RGB in [0, 1]; outputs ``pose_enc [1, S, 9]``,
``depth [1, S, H, W, 1]``, ``depth_conf [1, S, H, W]``, ``world_points [1, S, H, W, 3]``,
``world_points_conf [1, S, H, W]``, ``images [1, S, 3, H, W]``. S is dynamic; H and W are fixed per
file (VGGT's rotary position tables are computed in Python and frozen at export), so export one
file per input size you need. The export is checked with onnxruntime against PyTorch on random
frames, at another S than the one traced.

Needs the upstream package (not an ffrecon dependency) and its weights, e.g.::

    pip install git+https://github.com/facebookresearch/vggt
    python tools/export_vggt_onnx.py --checkpoint facebook/VGGT-1B --out models/vggt_1b_518x392.onnx

See docs/exporting_models.md for memory needs and fp16 notes.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch
from onnx_export_common import add_export_options, check_input_size, export_onnx, verify_onnx

log = logging.getLogger("export_vggt_onnx")

INPUT_NAME = "input_images"
OUTPUT_NAMES = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf", "images")
PATCH_SIZE = 14


class VGGTForOnnx(torch.nn.Module):
    """``input_images [S, 3, H, W]`` in [0, 1] to the six contract outputs (leading batch axis of 1)."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, input_images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        predictions = self.model(input_images)  # VGGT adds the batch axis to [S, 3, H, W] itself
        missing = [k for k in OUTPUT_NAMES if k not in predictions]
        if missing:
            raise RuntimeError(f"this VGGT version does not return {missing}; got {sorted(predictions)}")
        return tuple(predictions[k] for k in OUTPUT_NAMES)


def load_vggt(checkpoint: str) -> torch.nn.Module:
    """A Hugging Face repo id or local directory (``from_pretrained``), or a ``model.pt`` state dict."""
    try:
        from vggt.models.vggt import VGGT
    except ImportError as exc:
        raise SystemExit(
            "error: the upstream `vggt` package is not installed (it is not an ffrecon dependency).\n"
            "  fix: pip install git+https://github.com/facebookresearch/vggt  (ideally in a separate environment)"
        ) from exc
    path = Path(checkpoint)
    if path.is_file():
        model = VGGT()
        model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    else:
        model = VGGT.from_pretrained(checkpoint)  # downloads on first use (about 5 GB)
    return model.eval().float()


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default="facebook/VGGT-1B", help="Hugging Face repo id, local directory, or model.pt state dict (default: %(default)s)")
    parser.add_argument("--out", type=Path, help="output .onnx (default: models/vggt_<W>x<H>.onnx)")
    parser.add_argument("--height", type=int, default=392, help="input height, multiple of 14 (default: %(default)s, 4:3 photos in VGGT's crop mode)")
    parser.add_argument("--width", type=int, default=518, help="input width, multiple of 14 (default: %(default)s)")
    parser.add_argument("--frames", type=int, default=2, help="frames in the traced example (S stays dynamic; default: %(default)s)")
    add_export_options(parser)
    args = parser.parse_args(argv)
    check_input_size(parser, args, PATCH_SIZE)
    if args.out is None:
        args.out = Path("models") / f"vggt_{args.width}x{args.height}{'_fp16' if args.fp16 else ''}.onnx"
    return args


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args = parse_args(argv)
    start = time.time()
    log.info("loading VGGT from %s", args.checkpoint)
    module = VGGTForOnnx(load_vggt(args.checkpoint)).eval()
    rng = np.random.default_rng(0)
    example = torch.from_numpy(rng.random((args.frames, 3, args.height, args.width), dtype=np.float32))
    log.info("exporting with the %s exporter at S=%d, %dx%d (this takes minutes and several GB of memory)", args.exporter, args.frames, args.width, args.height)
    metadata = {
        "ffrecon.description": f"VGGT ({args.checkpoint}) exported by tools/export_vggt_onnx.py, {'fp16' if args.fp16 else 'fp32'}, input {args.width}x{args.height}",
        "ffrecon.contract": "multiview",
    }
    dynamic_axes = {INPUT_NAME: {0: "S"}, **{k: {1: "S"} for k in OUTPUT_NAMES}}
    written = export_onnx(module, (example,), [INPUT_NAME], list(OUTPUT_NAMES), dynamic_axes, args.out, opset=args.opset, exporter=args.exporter, metadata=metadata, fp16=args.fp16)
    if not args.skip_verify:
        frames = args.frames + 1  # another S than the traced one: checks that S really is dynamic
        check = rng.random((frames, 3, args.height, args.width), dtype=np.float32)
        log.info("verifying with onnxruntime against PyTorch at S=%d", frames)
        with torch.no_grad():
            reference = dict(zip(OUTPUT_NAMES, (t.float().numpy() for t in module(torch.from_numpy(check)))))
        worst = verify_onnx(args.out, {INPUT_NAME: check}, reference, rtol=3e-2 if args.fp16 else 1e-3)
        log.info("verified: worst relative difference %.2e", worst)
    for path in written:
        print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB)")
    print(f"input  {INPUT_NAME} [S, 3, {args.height}, {args.width}] float32 RGB in [0, 1]")
    print(f"outputs {', '.join(OUTPUT_NAMES)}; {time.time() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
