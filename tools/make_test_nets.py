"""Build the tiny, UNTRAINED ONNX fixtures in models/ (random weights, meaningless geometry).

They exist so that contract tests (names, shapes, ranges, dynamic sizes) run without real weights:

- ``tiny_vggt.onnx``: the VGGT contract (docs/contracts.md, "Multi-view models"), dynamic S, H, W (multiples of 14);
- ``tiny_dust3r.onnx``: ffrecon's pairwise contract (section 2), dynamic B, H, W (multiples of 16).

Usage: ``python tools/make_test_nets.py [--out models] [--seed 0]``. The same seed writes the same bytes.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import onnx

from ffrecon.synthetic.onnx_graph import GraphBuilder, quat_product_basis

log = logging.getLogger("ffrecon.tools.make_test_nets")

VGGT_PATCH = 14
DUST3R_PATCH = 16
WIDTH = 16  # feature channels
_DOC = (
    "UNTRAINED FIXTURE with random weights (seed {seed}) built by tools/make_test_nets.py: "
    "right names, shapes and ranges, meaningless geometry. For contract tests only."
)


def _conv_weight(rng: np.random.Generator, out_ch: int, in_ch: int, k: int) -> np.ndarray:
    """He-initialised ``[out, in, k, k]`` float32 weights."""
    return (rng.normal(size=(out_ch, in_ch, k, k)) * np.sqrt(2.0 / (in_ch * k * k))).astype(np.float32)


def _conv(
    g: GraphBuilder,
    rng: np.random.Generator,
    x: str,
    in_ch: int,
    out_ch: int,
    k: int,
    *,
    stride: int = 1,
    relu: bool = True,
) -> str:
    pad = (k - 1) // 2 if stride == 1 else 0
    bias = (0.1 * rng.normal(size=out_ch)).astype(np.float32)
    y = g.op(
        "Conv",
        [x, g.const(_conv_weight(rng, out_ch, in_ch, k), "w"), g.const(bias, "b")],
        kernel_shape=[k, k],
        strides=[stride, stride],
        pads=[pad] * 4,
    )
    return g.op("Relu", [y]) if relu else y


def _upsample(g: GraphBuilder, x: str, factor: int) -> str:
    """Bilinear upsampling by an integer factor (pixel-centre aligned)."""
    scales = g.const(np.array([1, 1, factor, factor], np.float32), "scales")
    return g.op("Resize", [x, "", scales], mode="linear", coordinate_transformation_mode="half_pixel")


def _at_least_one(g: GraphBuilder, x: str) -> str:
    """``1 + softplus(x)``: a confidence >= 1."""
    return g.op("Add", [g.op("Softplus", [x]), g.const(np.float32(1.0))])


def _positive(g: GraphBuilder, x: str) -> str:
    """``0.1 + softplus(x)``: a depth > 0."""
    return g.op("Add", [g.op("Softplus", [x]), g.const(np.float32(0.1))])


def _channels_last(g: GraphBuilder, x: str) -> str:
    """``[N, C, H, W]`` to ``[N, H, W, C]``."""
    return g.op("Transpose", [x], perm=[0, 2, 3, 1])


def _split_channels(g: GraphBuilder, x: str, sizes: list[int]) -> list[str]:
    return g.op("Split", [x, g.const(np.array(sizes, np.int64), "split")], axis=1, n_out=len(sizes))


def _pixel_rays(g: GraphBuilder, image: str) -> str:
    """``[1, 2, H, W]`` (x / z, y / z) of pixel-centre rays for a 60 degree horizontal field of view."""
    shape = g.op("Cast", [g.op("Shape", [image])], to=onnx.TensorProto.FLOAT)
    height = g.op("Gather", [shape, g.const(np.array(2, np.int64))], axis=0)
    width = g.op("Gather", [shape, g.const(np.array(3, np.int64))], axis=0)
    half, one = g.const(np.float32(0.5)), g.const(np.float32(1.0))
    focal = g.op("Div", [g.op("Mul", [width, half]), g.const(np.float32(np.tan(np.pi / 6)))])
    axes = []
    for size, shape_out in ((width, [1, 1, 1, -1]), (height, [1, 1, -1, 1])):
        centres = g.op("Range", [half, size, one])  # pixel centres, COLMAP rule
        ray = g.op("Div", [g.op("Sub", [centres, g.op("Mul", [size, half])]), focal])
        axes.append(g.op("Reshape", [ray, g.const(np.array(shape_out, np.int64))]))
    ray_x, ray_y = axes
    zeros = g.op("Mul", [g.op("Add", [ray_x, ray_y]), g.const(np.float32(0.0))])  # [1, 1, H, W]
    return g.op("Concat", [g.op("Add", [ray_x, zeros]), g.op("Add", [ray_y, zeros])], axis=1)


def build_tiny_vggt(seed: int = 0) -> onnx.ModelProto:
    """VGGT contract: ``input_images [S, 3, H, W]`` -> pose_enc, depth, depth_conf, world_points,
    world_points_conf, images."""
    rng = np.random.default_rng(seed)
    g = GraphBuilder("tiny_vggt")
    x = g.input("input_images", ["S", 3, "H", "W"])
    feat = _conv(g, rng, x, 3, WIDTH, VGGT_PATCH, stride=VGGT_PATCH)  # one token per 14x14 patch
    feat = _conv(g, rng, feat, WIDTH, WIDTH, 3)
    dense = _upsample(g, _conv(g, rng, feat, WIDTH, 6, 1, relu=False), VGGT_PATCH)  # [S, 6, H, W]
    depth_raw, dconf_raw, pts_raw, pconf_raw = _split_channels(g, dense, [1, 1, 3, 1])
    axis0, axis1 = g.const(np.array([0], np.int64)), g.const(np.array([1], np.int64))

    def per_pixel(value: str) -> str:  # [S, 1, H, W] -> [1, S, H, W]
        return g.op("Unsqueeze", [g.op("Squeeze", [value, axis1]), axis0])

    g.output(g.op("Unsqueeze", [_channels_last(g, _positive(g, depth_raw)), axis0]), "depth", [1, "S", "H", "W", 1])
    g.output(per_pixel(_at_least_one(g, dconf_raw)), "depth_conf", [1, "S", "H", "W"])
    g.output(g.op("Unsqueeze", [_channels_last(g, pts_raw), axis0]), "world_points", [1, "S", "H", "W", 3])
    g.output(per_pixel(_at_least_one(g, pconf_raw)), "world_points_conf", [1, "S", "H", "W"])

    # Camera head: pooled features -> translation, quaternion, horizontal field of view.
    pooled = g.op("Flatten", [g.op("GlobalAveragePool", [feat])], axis=1)  # [S, WIDTH]
    head = g.op(
        "Add",
        [
            g.op("MatMul", [pooled, g.const((0.3 * rng.normal(size=(WIDTH, 8))).astype(np.float32), "w")]),
            g.const(np.array([0, 0, 0, 0, 0, 0, 2.0, 0], np.float32), "b"),
        ],
    )  # bias towards w = 1
    t_raw, q_raw, fov_raw = _split_channels(g, head, [3, 4, 1])
    zero = g.const(np.array(0, np.int64))
    # The first frame is the world: subtract its translation, compose quaternions with its inverse.
    t = g.op("Sub", [t_raw, g.op("Gather", [t_raw, zero], axis=0)])
    norm = g.op("Sqrt", [g.op("ReduceSum", [g.op("Mul", [q_raw, q_raw]), axis1], keepdims=1)])
    q = g.op("Div", [q_raw, g.op("Add", [norm, g.const(np.float32(1e-6))])])
    q0_conj = g.op(
        "Mul", [g.op("Gather", [q, axis0], axis=0), g.const(np.array([-1, -1, -1, 1], np.float32))]
    )  # [1, 4]
    basis = g.const(quat_product_basis().reshape(4, 16).astype(np.float32), "quat_basis")
    q_rel = g.op(
        "MatMul", [q, g.op("Reshape", [g.op("MatMul", [q0_conj, basis]), g.const(np.array([4, 4], np.int64))])]
    )
    # fov_w in (0.5, 1.7) rad; fov_h from the aspect ratio, so the decoded pixels are square.
    fov_w = g.op("Add", [g.op("Mul", [g.op("Sigmoid", [fov_raw]), g.const(np.float32(1.2))]), g.const(np.float32(0.5))])
    shape = g.op("Cast", [g.op("Shape", [x])], to=onnx.TensorProto.FLOAT)
    aspect = g.op(
        "Div",
        [
            g.op("Gather", [shape, g.const(np.array(2, np.int64))], axis=0),
            g.op("Gather", [shape, g.const(np.array(3, np.int64))], axis=0),
        ],
    )
    half_w = g.op("Mul", [fov_w, g.const(np.float32(0.5))])
    fov_h = g.op("Mul", [g.op("Atan", [g.op("Mul", [g.op("Tan", [half_w]), aspect])]), g.const(np.float32(2.0))])
    pose_enc = g.op("Concat", [t, q_rel, fov_h, fov_w], axis=1)
    g.output(g.op("Unsqueeze", [pose_enc, axis0]), "pose_enc", [1, "S", 9])
    g.output(g.op("Unsqueeze", [x, axis0]), "images", [1, "S", 3, "H", "W"])
    model = g.model(opset=17)
    model.doc_string = _DOC.format(seed=seed)
    return model


def build_tiny_dust3r(seed: int = 0) -> onnx.ModelProto:
    """Pairwise contract: ``view1, view2 [B, 3, H, W]`` in [-1, 1] -> pts3d, conf, pts3d_in_other_view,
    conf_in_other_view."""
    rng = np.random.default_rng(seed + 1)
    g = GraphBuilder("tiny_dust3r")
    views = [g.input(name, ["B", 3, "H", "W"]) for name in ("view1", "view2")]
    w_enc = g.const(_conv_weight(rng, WIDTH, 3, DUST3R_PATCH), "w_enc")  # shared encoder
    b_enc = g.const((0.1 * rng.normal(size=WIDTH)).astype(np.float32), "b_enc")
    feats = [
        g.op("Relu", [g.op("Conv", [v, w_enc, b_enc], kernel_shape=[DUST3R_PATCH] * 2, strides=[DUST3R_PATCH] * 2)])
        for v in views
    ]
    w_mix = g.const(_conv_weight(rng, WIDTH, 2 * WIDTH, 3), "w_mix")  # shared decoder: own + other view
    b_mix = g.const((0.1 * rng.normal(size=WIDTH)).astype(np.float32), "b_mix")
    w_head = g.const(_conv_weight(rng, 4, WIDTH, 1), "w_head")
    b_head = g.const(np.array([0, 0, 1.0, 0], np.float32), "b_head")
    axis1 = g.const(np.array([1], np.int64))
    rays = _pixel_rays(g, views[0])
    for own, other, suffix in ((feats[0], feats[1], ""), (feats[1], feats[0], "_in_other_view")):
        mixed = g.op(
            "Relu",
            [
                g.op(
                    "Conv", [g.op("Concat", [own, other], axis=1), w_mix, b_mix], kernel_shape=[3, 3], pads=[1, 1, 1, 1]
                )
            ],
        )
        dense = _upsample(g, g.op("Conv", [mixed, w_head, b_head], kernel_shape=[1, 1]), DUST3R_PATCH)  # [B, 4, H, W]
        xy, z_raw, conf_raw = _split_channels(g, dense, [2, 1, 1])
        z = _positive(g, z_raw)
        # Points along each pixel's ray (60 degree field of view) with a small random sideways offset,
        # so that a focal length fitted to them is positive (the rest is still meaningless).
        xy = g.op("Add", [rays, g.op("Mul", [xy, g.const(np.float32(0.05))])])
        pts = g.op("Concat", [g.op("Mul", [xy, z]), z], axis=1)
        g.output(_channels_last(g, pts), "pts3d" + suffix, ["B", "H", "W", 3])
        g.output(g.op("Squeeze", [_at_least_one(g, conf_raw), axis1]), "conf" + suffix, ["B", "H", "W"])
    model = g.model(opset=17)
    model.doc_string = _DOC.format(seed=seed)
    return model


def write_test_nets(out_dir: Path, seed: int = 0) -> tuple[Path, Path]:
    """Write ``tiny_vggt.onnx`` and ``tiny_dust3r.onnx`` into ``out_dir``; returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = (out_dir / "tiny_vggt.onnx", out_dir / "tiny_dust3r.onnx")
    for path, model in zip(paths, (build_tiny_vggt(seed), build_tiny_dust3r(seed))):
        entry = model.metadata_props.add()
        entry.key, entry.value = (
            "ffrecon.description",
            f"untrained fixture (random weights, seed {seed}); meaningless geometry",
        )
        onnx.checker.check_model(model)
        onnx.save_model(model, str(path))
        log.info("wrote %s (%d bytes)", path, path.stat().st_size)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "models")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    write_test_nets(args.out, args.seed)


if __name__ == "__main__":
    main()
