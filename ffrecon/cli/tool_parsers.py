"""The parsers of ``view``, ``render`` and ``export-model`` (``run`` and ``demo``: :mod:`ffrecon.cli.parser`)."""

from __future__ import annotations

import argparse

from ffrecon.cli.argtypes import SEED_MAX, field_default, in_range, keyword_default, path_arg, seed_arg, text_arg

# export-model's opsets: ModelExportOptions refuses older ones; torch.onnx.export with dynamo=False (the export's)
# writes up to torch.onnx._constants.ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET (20 in torch 2.13)
MIN_OPSET, TORCHSCRIPT_MAX_OPSET = 15, 20

# Each subcommand's line in `ffrecon --help`, in its order (the parser lists them all, and fills in the options of
# the one given alone: :func:`ffrecon.cli.parser.build_parser`).
COMMAND_HELP = {
    "run": "reconstruct a folder of photos or a video",
    "demo": "synthetic scene + simulated model through every stage (no downloads)",
    "inspect-model": "show a model's family, inputs, outputs and preprocessing",
    "export-model": "turn an upstream checkpoint into an ONNX model file ffrecon runs",
    "view": "open an output folder's cameras, points and splat in the browser",
    "render": "render an output folder's splat along a camera path (camera_path.json)",
}


def add_render_parser(sub) -> None:
    """``render``: a run's splat along a nerfstudio camera path (:mod:`ffrecon.render_path`)."""
    render = sub.add_parser("render", help=COMMAND_HELP["render"])
    render.add_argument("out", type=path_arg("the output folder"), help="an output folder of `ffrecon run -o OUT`")
    render.add_argument(
        "--camera-path",
        type=path_arg("--camera-path"),
        required=True,
        help="nerfstudio camera_path.json in the run's world (OUT/camera_path.json is the fly-through's)",
    )
    render.add_argument("-o", "--output", type=path_arg("--output"), required=True, help="the video to write (.mp4)")
    render.add_argument("--overwrite", action="store_true", help="replace the video if it exists")
    render.add_argument(
        "--device",
        choices=["auto", "cpu", "cuda"],
        default=None,
        help="auto: gsplat on CUDA when available, else ffrecon's CPU renderer (the splat stage's default)",
    )
    render.add_argument("-v", "--verbose", action="count", default=0)
    render.add_argument("-q", "--quiet", action="store_true")


def add_view_parser(sub) -> None:
    """``view``: the caps' defaults are :class:`~ffrecon.view.ViewOptions`'s (at least 1, as it checks), the
    address's :func:`~ffrecon.view.start_viewer`'s."""
    from ffrecon.view import ViewOptions, start_viewer

    view = sub.add_parser("view", help=COMMAND_HELP["view"])
    view.add_argument("out", type=path_arg("the output folder"), help="an output folder of `ffrecon run -o OUT`")
    view.add_argument(
        "--host",
        type=text_arg("--host"),
        default=None,
        help=f"address to listen on (default {keyword_default(start_viewer, 'host')}, this machine)",
    )
    view.add_argument(
        "--port",
        type=in_range("viewer port", "--port", low=0, high=65535, note=" (0: any free port)"),
        default=None,
        help=f"port to listen on, 0 to 65535; 0: any free port (default {keyword_default(start_viewer, 'port')})",
    )
    view.add_argument(
        "--max-points",
        type=in_range("ViewOptions.max_points", "--max-points", low=1),
        default=None,
        help=f"points drawn at most (default {field_default(ViewOptions, 'max_points')}; the rest subsampled)",
    )
    view.add_argument(
        "--max-gaussians",
        type=in_range("ViewOptions.max_gaussians", "--max-gaussians", low=1),
        default=None,
        help=f"Gaussians drawn at most, most opaque first (default {field_default(ViewOptions, 'max_gaussians')})",
    )
    view.add_argument("-v", "--verbose", action="count", default=0)


def add_export_parser(sub) -> None:
    from ffrecon.models.exporting import FAMILIES

    families = "\n".join(f"  {name:<10} {entry.summary}" for name, entry in FAMILIES.items())
    export = sub.add_parser(
        "export-model",
        help=COMMAND_HELP["export-model"],
        description=(
            "Export a public model to ONNX with ffrecon's contract names, then check onnxruntime against PyTorch."
            f"\n\nfamilies:\n{families}\n\n"
            "See docs/models.md for where checkpoints are published and their licenses."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    export.add_argument("family", choices=list(FAMILIES), help="model family")
    _add_export_arguments(export)


def _add_export_arguments(export: argparse.ArgumentParser) -> None:
    """The options of ``export-model``: what to export from and to (the rest: :func:`_add_export_build_options`)."""

    export.add_argument(
        "-o",
        "--out",
        type=path_arg("--out"),
        required=True,
        help="output .onnx file (weights over 2 GB go to OUT.onnx.data beside it)",
    )
    weights = export.add_mutually_exclusive_group(required=True)
    weights.add_argument(
        "--checkpoint", type=text_arg("--checkpoint"), help="the checkpoint file or folder you downloaded"
    )
    weights.add_argument(
        "--random-init",
        action="store_true",
        help="the real full-size architecture with random weights (checks the export path without weights)",
    )
    weights.add_argument(
        "--tiny", action="store_true", help="the same upstream classes at a small configuration, random weights (tests)"
    )
    export.add_argument(
        "--upstream",
        type=path_arg("--upstream"),
        default=None,
        help="root of the upstream code clone, when it is not an installed package",
    )
    export.add_argument(
        "--height",
        type=in_range("export height", "--height", low=1),
        default=None,
        help="network input height, a multiple of the family's patch size (default: from --photos, else the "
        "family's default)",
    )
    export.add_argument(
        "--width", type=in_range("export width", "--width", low=1), default=None, help="network input width"
    )
    export.add_argument(
        "--photos",
        type=path_arg("--photos"),
        default=None,
        help="a photo or folder the model will be used on: sets --height/--width by the family's preprocessing",
    )
    _add_export_build_options(export)


def _add_export_build_options(export: argparse.ArgumentParser) -> None:
    """How ``export-model`` builds, traces and checks the model; the defaults of --frames, --opset and --seed are
    :class:`~ffrecon.models.exporting.ModelExportOptions`'s."""
    from ffrecon.models.exporting import ModelExportOptions

    export.add_argument(
        "--fp16", action="store_true", help="fp16 weights and compute, float32 inputs/outputs (GPU; half the size)"
    )
    export.add_argument(
        "--fused-attention",
        action="store_true",
        help="attention as onnxruntime's MultiHeadAttention op: on CUDA, flash/memory-efficient kernels whose "
        "memory grows linearly with the frames (GPU; the CPU provider runs it too)",
    )
    export.add_argument(
        "--frames",
        type=in_range("ModelExportOptions.count", "--frames", low=1),
        default=None,
        help="frames (pairs for pairwise models) in the traced example, >= 1; the check runs one more "
        f"(default {field_default(ModelExportOptions, 'count')})",
    )
    export.add_argument(
        "--opset",
        type=in_range("ModelExportOptions.opset", "--opset", low=MIN_OPSET, high=TORCHSCRIPT_MAX_OPSET),
        default=None,
        help=f"ONNX opset, {MIN_OPSET} to {TORCHSCRIPT_MAX_OPSET} "
        f"(default {field_default(ModelExportOptions, 'opset')})",
    )
    export.add_argument("--skip-verify", action="store_true", help="do not compare onnxruntime with PyTorch")
    export.add_argument(
        "--keep-untrained-heads",
        action="store_true",
        help="with random weights, leave heads that decode to invalid cameras as initialised (tests ffrecon's checks)",
    )
    export.add_argument(
        "--variant",
        type=text_arg("--variant"),
        default=None,
        help="upstream configuration to build with --random-init "
        "(da3: da3-small|base|large|giant; monodepth: small|base|large, optionally -metric)",
    )
    export.add_argument(
        "--seed",
        type=seed_arg("--seed"),
        default=None,
        help=f"seed of the random weights and of the traced example's inputs, 0 to {SEED_MAX} "
        f"(default {field_default(ModelExportOptions, 'seed')})",
    )
    export.add_argument("-v", "--verbose", action="count", default=0)
    export.add_argument("-q", "--quiet", action="store_true")
