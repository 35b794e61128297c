"""The command line's parser: ``run`` and ``demo`` here, the other subcommands in :mod:`ffrecon.cli.tool_parsers`.

Defaults live in the options classes alone (and a function's keywords where no class holds them): a flag that sets
one defaults to None and its help text reads the value from there (tests/test_cli_defaults.py checks each).
"""

from __future__ import annotations

import argparse
import sys

from ffrecon import __version__
from ffrecon.cli.argtypes import (
    SEED_MAX,
    CropBoxAction,
    Later,
    Parser,
    field_default,
    in_range,
    model_file_arg,
    number_arg,
    path_arg,
    text_arg,
)
from ffrecon.cli.needs import check_partners
from ffrecon.cli.tool_parsers import COMMAND_HELP, add_export_parser, add_render_parser, add_view_parser

# The demo scene's frames: a side from capture's smallest cap (ffrecon.capture.MIN_IMAGE_SIZE, below which SIFT
# and the models find next to nothing) to DEMO_MAX_SIDE; from DEMO_MIN_FRAMES to DEMO_MAX_FRAMES of them.
DEMO_MIN_SIDE, DEMO_MAX_SIDE = 64, 4096
DEMO_MIN_FRAMES, DEMO_MAX_FRAMES = 8, 1000  # 8: the demo's model makes frame 7 badly wrong (DemoOptions)


# The option classes whose modules load torch, open3d or numba, imported when a value given or a help text shown
# needs them (their help texts are made then: :class:`~ffrecon.cli.argtypes.Later`).
def _multiview_options():
    from ffrecon.models.multiview import MultiviewOptions

    return MultiviewOptions


def _feedforward_options():
    from ffrecon.models.stage import FeedForwardOptions

    return FeedForwardOptions


def _ray_options():
    from ffrecon.models.distributed import RayOptions

    return RayOptions


def _optimize_options():
    from ffrecon.splat.optimize import OptimizeOptions

    return OptimizeOptions


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line, every value and every option's partner checked (an InputError else)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), "")  # no option before it takes a value
    args = build_parser(command).parse_args(argv)
    check_partners(args)
    return args


def _add_output_folder_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "-o", "--out", type=path_arg("--out"), required=True, help="output folder (see the README for its layout)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace results already in the output folder")
    p.add_argument(
        "--resume",
        action="store_true",
        help="reuse the stages OUT (or an interrupted run into OUT) finished, where inputs and options are unchanged",
    )
    p.add_argument("--fresh", action="store_true", help="recompute every stage, even those an interrupted run finished")


def _add_extra_output_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--compare-seeds",
        action="store_true",
        help="with a model, also train the splat from COLMAP's points under the same budget, and compare",
    )
    p.add_argument(
        "--mesh",
        nargs="?",
        const="tsdf",
        choices=("tsdf", "poisson"),
        help="also write a mesh (mesh.ply, mesh.glb): TSDF fusion of the depth maps (plain --mesh) or Poisson",
    )
    p.add_argument(
        "--sog",
        action="store_true",
        help="also write splat.sog (PlayCanvas) with splat-transform (`make clients`); minutes for 10k+ Gaussians",
    )
    p.add_argument(
        "--reference",
        type=path_arg("--reference"),
        default=None,
        help="a reference COLMAP model to score the cameras against",
    )


def _add_model_call_options(p: argparse.ArgumentParser) -> None:
    """Options of ``run`` and ``demo`` for the model's calls (defaults: MultiviewOptions' and
    FeedForwardOptions')."""
    from ffrecon.models.memory import MEMORY_FRACTION

    p.add_argument(
        "--chunk-size",
        type=number_arg(lambda v: _multiview_options()(chunk_size=v, chunk_overlap=1)),
        default=None,
        help=f"frames per model call (default: as many as fit in {MEMORY_FRACTION * 100:g}%% of the free memory; "
        "docs/benchmarks.md)",
    )
    p.add_argument(
        "--chunk-overlap",
        type=number_arg(lambda v: _multiview_options()(chunk_overlap=v)),
        default=None,
        help=Later(
            lambda: (
                "frames shared by consecutive chunks, at least 1 and less than the chunk size "
                f"(default {field_default(_multiview_options(), 'chunk_overlap')})"
            )
        ),
    )
    p.add_argument(
        "--preprocess",
        choices=["crop", "pad", "resize"],
        default=None,
        help="preprocessing mode (default: the model family's reference; VGGT: crop or pad, DA3: resize or crop)",
    )
    p.add_argument(
        "--no-loop-chunks",
        action="store_true",
        help="no loop calls where a long path revisits a place (default: found from the chunks, and a pose graph "
        "spreads the drift; report.json feedforward.chunks.loops)",
    )
    p.add_argument(
        "--threads",
        type=number_arg(lambda v: _feedforward_options()(threads=v)),
        default=None,
        help="CPU threads for inference, >= 1 (default: all)",
    )
    _add_ray_options(p)


def _add_ray_options(p: argparse.ArgumentParser) -> None:
    """The model's chunks on Ray (defaults: RayOptions')."""

    p.add_argument(
        "--ray",
        nargs="?",
        const="",
        default=None,
        metavar="ADDRESS",
        help="run the model's chunks on Ray workers (pip install 'ffrecon[distributed]'): alone, a local Ray "
        "instance; with an address ('auto', 'ray://HEAD:10001'), that cluster (docs/pipeline.md)",
    )
    p.add_argument(
        "--ray-workers",
        type=number_arg(lambda v: _ray_options()(workers=v)),
        default=None,
        help="with --ray: model sessions (default: as many as the cluster's CPUs allow, one per chunk at most)",
    )
    p.add_argument(
        "--ray-gpus",
        type=number_arg(lambda v: _ray_options()(gpus_per_worker=v), integer=False),
        default=None,
        help="with --ray: GPUs per model session (1 on a GPU cluster: onnxruntime runs on CUDA there; "
        "default: none, the CPU)",
    )


def _add_known_input_options(p: argparse.ArgumentParser) -> None:
    """What the user knows about the capture: intrinsics, poses, masks."""
    p.add_argument(
        "--intrinsics",
        type=path_arg("--intrinsics"),
        default=None,
        metavar="FILE",
        help="known intrinsics in COLMAP's cameras.txt form (one camera for all photos, or a line per photo with "
        "its name in place of the id): they replace the model's (reported beside them), seed COLMAP's focal "
        "and stay fixed in the bundle adjustment",
    )
    p.add_argument(
        "--poses",
        type=path_arg("--poses"),
        default=None,
        metavar="MODEL_OR_JSON",
        help="known poses: a COLMAP model folder or a nerfstudio transforms.json, by photo name (three or more); "
        "they replace the model's (reported beside them) and stay fixed in the bundle adjustment",
    )
    p.add_argument(
        "--poses-prior",
        action="store_true",
        help="with --poses: priors the bundle adjustment keeps the camera centres near, not fixed poses",
    )
    p.add_argument(
        "--masks",
        type=path_arg("--masks"),
        default=None,
        metavar="FOLDER",
        help="a PNG per photo (<stem>.png or <name>.png, nerfstudio's and COLMAP's convention), 0 where the photo "
        "is to be ignored (moving objects, people): no features, fused points or splat loss there",
    )
    p.add_argument(
        "--intrinsics-prior",
        action="store_true",
        help="with --intrinsics: starting values the bundle adjustment refines, not fixed ones",
    )


def _add_pairing_options(p: argparse.ArgumentParser) -> None:
    """Which pairs COLMAP's cross-check matches (defaults: ColmapOptions')."""
    from ffrecon.sfm.crosscheck.options import ColmapOptions, PairingMode

    p.add_argument(
        "--pairing",
        choices=[m.value for m in PairingMode],
        default=None,
        help="pairs the COLMAP cross-check matches: exhaustive, sequential (video order, frames 2^k apart; loop "
        "closure with --vocab-tree), spatial (GPS), vocab_tree (retrieval), model (the pairs the model's cameras "
        "and depth say overlap, loop candidates included; COLMAP still verifies and maps on its own); "
        f"default {field_default(ColmapOptions, 'pairing').value}: exhaustive up to "
        f"{field_default(ColmapOptions, 'exhaustive_max_images')} photos, then model with a model, else sequential",
    )
    p.add_argument(
        "--vocab-tree",
        type=path_arg("--vocab-tree"),
        default=None,
        metavar="FILE",
        help="a COLMAP vocabulary tree (from colmap.github.io) for vocab_tree pairing and sequential loop closure",
    )


def add_run_options(p: argparse.ArgumentParser) -> None:
    """Options of ``run`` and ``demo``; their defaults live in the stage options classes alone, and so do
    their checks (each class's ``__post_init__``: a bad value is an InputError naming the flag)."""
    from ffrecon.capture import CaptureOptions
    from ffrecon.sfm.crosscheck.gate_types import GateOptions

    _add_output_folder_options(p)
    _add_model_call_options(p)
    p.add_argument(
        "--max-image-size",
        type=number_arg(lambda v: CaptureOptions(max_image_size=v)),
        default=None,
        metavar="N",
        help="long side in pixels of the frames every stage works on; larger photos are downscaled at capture "
        f"(default {field_default(CaptureOptions, 'max_image_size')}, as 3DGS; 0 keeps full size, which costs "
        "memory and time: docs/benchmarks.md)",
    )
    _add_known_input_options(p)
    p.add_argument(
        "--quick",
        action="store_true",
        help="needs --model: no COLMAP reconstruction; the model's cameras refined by bundle adjustment on SIFT "
        "matches of the pairs they say overlap (faster; nothing independent checks the cameras)",
    )
    p.add_argument("--no-colmap", action="store_true", help="skip the COLMAP cross-check")
    _add_pairing_options(p)
    p.add_argument("--no-refine", action="store_true", help="skip the bundle-adjustment refinement")
    p.add_argument("--no-splat", action="store_true", help="skip the Gaussian splat")
    p.add_argument("--force", action="store_true", help="go on past failed verification gates")
    p.add_argument(
        "--min-registration",
        type=number_arg(lambda v: GateOptions(min_registration_ratio=v), integer=False),
        default=None,
        help="registration-ratio gate: the share of the images COLMAP must register, 0 to 1 "
        f"(default {field_default(GateOptions, 'min_registration_ratio')})",
    )
    p.add_argument(
        "--splat-seconds",
        type=number_arg(lambda v: _optimize_options().brief(max_seconds=v), integer=False),
        default=None,
        help=Later(
            lambda: (
                "the splat stage's budget in seconds, > 0: its optimisation, held-out scores, cleaning, pose "
                f"check, renders, video and SPZ together (default {field_default(_optimize_options(), 'max_seconds')})"
            )
        ),
    )
    p.add_argument(
        "--crop-box",
        nargs="+",
        action=CropBoxAction,
        type=text_arg("--crop-box"),
        default=None,
        metavar="BOX",
        help="six numbers x0 y0 z0 x1 y1 z1, or a box file (ffrecon view writes one; docs/camera_paths.md): keep only "
        "the Gaussians in this axis-aligned box of the final cameras' world (sparse/0, transforms.json) instead of "
        "the automatic box; splat.ply and splat.spz are cropped",
    )
    _add_extra_output_options(p)
    p.add_argument("-v", "--verbose", action="count", default=0)
    p.add_argument("-q", "--quiet", action="store_true")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every subcommand (None), or of ``command`` with its options and the others listed alone
    (``ffrecon --help``, ``--version`` and a misspelt command read only their names and lines): the subcommands'
    help texts read their defaults from option classes whose modules load torch, open3d and numba (1-2.5 s)."""
    parser = Parser(prog="ffrecon", description="Photos or a video in, a verified 3D reconstruction out.")
    parser.add_argument("--version", action="version", version=f"ffrecon {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    adders = {
        "run": _add_run_parser,
        "demo": add_demo_parser,
        "inspect-model": _add_inspect_parser,
        "export-model": add_export_parser,
        "view": add_view_parser,
        "render": add_render_parser,
    }
    for name, line in COMMAND_HELP.items():
        if command is None or command == name:
            adders[name](sub)
        else:
            sub.add_parser(name, help=line)
    return parser


def _add_run_parser(sub) -> None:
    from ffrecon.capture import CaptureOptions

    run = sub.add_parser("run", help=COMMAND_HELP["run"])
    run.add_argument(
        "input", type=path_arg("the input"), help="folder of images (jpg, png, tiff, webp, bmp) or a video file"
    )
    run.add_argument(
        "--model",
        type=model_file_arg("--model", "--model"),
        default=None,
        help="ONNX model (any family in docs/models.md; make one with `ffrecon export-model`); "
        "without one, COLMAP makes the cameras and the splat is seeded from its points",
    )
    run.add_argument(
        "--video-frames",
        type=number_arg(lambda v: CaptureOptions(video_frames=v)),
        default=None,
        help=f"frames to keep from a video (default {field_default(CaptureOptions, 'video_frames')})",
    )
    run.add_argument(
        "--skip-bad-images", action="store_true", help="leave out unreadable files and non-images instead of stopping"
    )
    add_run_options(run)


def _add_inspect_parser(sub) -> None:
    inspect = sub.add_parser("inspect-model", help=COMMAND_HELP["inspect-model"])
    inspect.add_argument("model", type=model_file_arg("the model", "ffrecon inspect-model"), help="an .onnx file")


# demo's flags for fields of ffrecon.synthetic.SceneOptions, which does not check them: (dest, field, help, low,
# high); the flag is --dest
DEMO_SCENE_FLAGS = (
    ("frames", "num_frames", "frames of the synthetic scene", DEMO_MIN_FRAMES, DEMO_MAX_FRAMES),
    ("width", "width", "frame width in pixels", DEMO_MIN_SIDE, DEMO_MAX_SIDE),
    ("height", "height", "frame height in pixels", DEMO_MIN_SIDE, DEMO_MAX_SIDE),
    ("seed", "seed", "seed of the scene's random textures and jitter", 0, SEED_MAX),
)


def add_demo_parser(sub) -> None:
    """``demo``: the synthetic scene's options (defaults: :class:`~ffrecon.synthetic.SceneOptions`'s), then
    those of ``run``."""
    from ffrecon.synthetic import SceneOptions

    demo = sub.add_parser("demo", help=COMMAND_HELP["demo"])
    for dest, name, what, low, high in DEMO_SCENE_FLAGS:
        default = field_default(SceneOptions, name)
        check = in_range(f"SceneOptions.{name}", f"--{dest}", low=low, high=high)
        demo.add_argument(f"--{dest}", type=check, default=None, help=f"{what}, {low} to {high} (default {default})")
    add_run_options(demo)
