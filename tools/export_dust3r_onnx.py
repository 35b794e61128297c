#!/usr/bin/env python
"""Export DUSt3R (naver/dust3r) or MASt3R (naver/mast3r) to ONNX with ffrecon's pairwise names (CONTRACTS.md section 2).

Inputs ``view1``, ``view2`` ``[B, 3, H, W]`` float32 RGB normalised to [-1, 1]; outputs ``pts3d``
``[B, H, W, 3]`` (view1's points in view1's camera frame), ``conf`` ``[B, H, W]`` (>= 1),
``pts3d_in_other_view`` ``[B, H, W, 3]`` (view2's points, also in view1's frame) and
``conf_in_other_view`` ``[B, H, W]`` (>= 1). B is dynamic; H and W are fixed per file (the rotary
position tables are computed in Python and frozen at export), so export one file per input size
(ffrecon's pairwise path then uses that size: ``PairwiseOptions(size_hw=...)``). The export is
checked with onnxruntime against PyTorch on random pairs, at another B than the one traced.

Needs the upstream package (not an ffrecon dependency) and its weights, e.g.::

    git clone --recursive https://github.com/naver/dust3r && pip install -r dust3r/requirements.txt
    PYTHONPATH=dust3r python tools/export_dust3r_onnx.py --out models/dust3r_512x384.onnx

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

log = logging.getLogger("export_dust3r_onnx")

INPUT_NAMES = ("view1", "view2")
OUTPUT_NAMES = ("pts3d", "conf", "pts3d_in_other_view", "conf_in_other_view")
PATCH_SIZE = 16
DEFAULT_CHECKPOINTS = {"dust3r": "naver/DUSt3R_ViTLarge_BaseDecoder_512_dpt", "mast3r": "naver/MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric"}


class PairwiseForOnnx(torch.nn.Module):
    """Two image batches to the four contract outputs; hides the upstream dict-of-views interface."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, view1: torch.Tensor, view2: torch.Tensor) -> tuple[torch.Tensor, ...]:
        b, _, h, w = view1.shape
        true_shape = torch.tensor([[h, w]], dtype=torch.int64).expand(b, 2)
        # `instance` tells upstream whether the batch is (a, b), (b, a) interleaved; ours is not.
        res1, res2 = self.model(
            {"img": view1, "true_shape": true_shape, "instance": [f"view1_{k}" for k in range(b)]},
            {"img": view2, "true_shape": true_shape, "instance": [f"view2_{k}" for k in range(b)]},
        )
        return res1["pts3d"], res1["conf"], res2["pts3d_in_other_view"], res2["conf"]


def load_model(family: str, checkpoint: str) -> torch.nn.Module:
    """A Hugging Face repo id or local directory (``from_pretrained``), or a local ``.pth`` checkpoint."""
    try:
        if family == "mast3r":
            from mast3r.model import AsymmetricMASt3R as Model
        else:
            from dust3r.model import AsymmetricCroCo3DStereo as Model
    except ImportError as exc:
        raise SystemExit(
            f"error: the upstream `{family}` package is not importable (it is not an ffrecon dependency).\n"
            f"  fix: git clone --recursive https://github.com/naver/{family}, install its requirements, and put the clone on PYTHONPATH"
        ) from exc
    return Model.from_pretrained(checkpoint).eval().float()  # upstream accepts hub ids and .pth files


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--family", choices=tuple(DEFAULT_CHECKPOINTS), default="dust3r", help="upstream model class (default: %(default)s)")
    parser.add_argument("--checkpoint", help="Hugging Face repo id, local directory or .pth file (default: the family's 512 px ViT-Large model)")
    parser.add_argument("--out", type=Path, help="output .onnx (default: models/<family>_<W>x<H>.onnx)")
    parser.add_argument("--height", type=int, default=384, help="input height, multiple of 16 (default: %(default)s, 4:3 landscape at long side 512)")
    parser.add_argument("--width", type=int, default=512, help="input width, multiple of 16 (default: %(default)s; 224x224 for *_224_* checkpoints)")
    parser.add_argument("--batch", type=int, default=2, help="pairs in the traced example (B stays dynamic; default: %(default)s)")
    add_export_options(parser)
    args = parser.parse_args(argv)
    check_input_size(parser, args, PATCH_SIZE)
    args.checkpoint = args.checkpoint or DEFAULT_CHECKPOINTS[args.family]
    if args.out is None:
        args.out = Path("models") / f"{args.family}_{args.width}x{args.height}{'_fp16' if args.fp16 else ''}.onnx"
    return args


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args = parse_args(argv)
    start = time.time()
    log.info("loading %s from %s", args.family, args.checkpoint)
    module = PairwiseForOnnx(load_model(args.family, args.checkpoint)).eval()
    rng = np.random.default_rng(0)

    def pairs(b: int) -> tuple[np.ndarray, np.ndarray]:
        return tuple(rng.uniform(-1, 1, (b, 3, args.height, args.width)).astype(np.float32) for _ in range(2))

    example = tuple(torch.from_numpy(v) for v in pairs(args.batch))
    log.info("exporting with the %s exporter at B=%d, %dx%d (this takes minutes and several GB of memory)", args.exporter, args.batch, args.width, args.height)
    metadata = {
        "ffrecon.description": f"{args.family} ({args.checkpoint}) exported by tools/export_dust3r_onnx.py, {'fp16' if args.fp16 else 'fp32'}, input {args.width}x{args.height}",
        "ffrecon.contract": "pairwise",
    }
    dynamic_axes = {k: {0: "B"} for k in INPUT_NAMES + OUTPUT_NAMES}
    written = export_onnx(module, example, list(INPUT_NAMES), list(OUTPUT_NAMES), dynamic_axes, args.out, opset=args.opset, exporter=args.exporter, metadata=metadata, fp16=args.fp16)
    if not args.skip_verify:
        batch = args.batch + 1  # another B than the traced one: checks that B really is dynamic
        view1, view2 = pairs(batch)
        log.info("verifying with onnxruntime against PyTorch at B=%d", batch)
        with torch.no_grad():
            reference = dict(zip(OUTPUT_NAMES, (t.float().numpy() for t in module(torch.from_numpy(view1), torch.from_numpy(view2)))))
        worst = verify_onnx(args.out, {"view1": view1, "view2": view2}, reference, rtol=3e-2 if args.fp16 else 1e-3)
        log.info("verified: worst relative difference %.2e", worst)
    for path in written:
        print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB)")
    print(f"inputs {', '.join(INPUT_NAMES)} [B, 3, {args.height}, {args.width}] float32 RGB in [-1, 1]")
    print(f"outputs {', '.join(OUTPUT_NAMES)}; {time.time() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
