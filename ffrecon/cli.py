"""Command line: thin; parses options and calls the pipeline."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import os
import shlex
import signal
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from ffrecon import __version__
from ffrecon.concurrency import interrupts_deferred
from ffrecon.errors import FFReconError, InputError, Interrupted

log = logging.getLogger("ffrecon")

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")  # ffrecon.capture.images.VIDEO_EXTENSIONS

SEED_MAX = 2**32 - 1  # seeds are 0 to 2^32 - 1 (what numpy's and torch's generators all take)
# The demo scene's frames: a side from capture's smallest cap (ffrecon.capture.MIN_IMAGE_SIZE, below which SIFT
# and the models find next to nothing) to DEMO_MAX_SIDE; from DEMO_MIN_FRAMES to DEMO_MAX_FRAMES of them.
DEMO_MIN_SIDE, DEMO_MAX_SIDE = 64, 4096
DEMO_MIN_FRAMES, DEMO_MAX_FRAMES = 8, 1000  # 8: the demo's model makes frame 7 badly wrong (DemoOptions)
# export-model's opsets: ModelExportOptions refuses older ones; torch.onnx.export with dynamo=False (the export's)
# writes up to torch.onnx._constants.ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET (20 in torch 2.13)
MIN_OPSET, TORCHSCRIPT_MAX_OPSET = 15, 20


def _setup_logging(verbose: int) -> None:
    level = logging.DEBUG if verbose > 1 else logging.INFO if verbose >= 0 else logging.WARNING
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("[%(levelname)s] %(message)s" if level == logging.DEBUG else "%(message)s"))
    root = logging.getLogger("ffrecon")
    root.handlers[:] = [handler]
    root.setLevel(level)


def _log_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` while a command runs: a Python warning (numpy's RuntimeWarning, a library's
    UserWarning) as one logged line without the source path and code line that Python prints."""
    log.warning("%s: %s", category.__name__, " ".join(str(message).split()))


# Argument types: every value is checked as the command line is read, before any work. A value an options
# class holds is checked by that class (its __post_init__: the CLI and the Python API say the same); the
# InputError goes through argparse untouched (argparse catches only ValueError, TypeError and its own) to
# main, which prints it in one line with the fix (exit 2).


def _as_number(text: str, integer: bool) -> int | float | str:
    """The text as a number where it reads as one (an int first where a whole number is wanted, so the check
    shows it as given; else a float), else the text itself (the check names it)."""
    for convert in (int, float) if integer else (float,):
        try:
            return convert(text)
        except ValueError:
            pass
    return text


def _number(check, *, integer: bool = True):
    """An argparse ``type``: the text as a number that ``check(value)`` accepts (it raises InputError; for a
    value an options class holds, ``check`` builds that class with it)."""

    def parse(text: str) -> int | float:
        value = _as_number(text, integer)
        check(value)
        return int(value) if integer else float(value)

    return parse


def _in_range(name: str, flag: str, *, low: float, high: float | None = None, integer: bool = True, note: str = ""):
    """A number no options class checks: ``low`` to ``high`` (``note`` ends the fix)."""

    def check(value) -> None:
        from ffrecon.checks import check_number  # numpy: loaded by main once signals are held

        try:
            check_number(name, value, low=low, high=high, integer=integer, flag=flag)
        except InputError as err:
            raise InputError(err.problem, err.fix + note) from None

    return _number(check, integer=integer)


def _seed(flag: str):
    return _in_range("seed", flag, low=0, high=SEED_MAX)


def _text(flag: str):
    """A non-empty string."""

    def parse(text: str) -> str:
        if not text.strip():
            raise InputError(f"{flag} is empty", f"pass {flag} with a value")
        return text

    return parse


def _path(flag: str):
    """A non-empty path (``Path("")`` would be the current folder)."""
    text = _text(flag)
    return lambda value: Path(text(value))


def _model_file(flag: str, usage: str):
    """A model path that is not a folder (the runner says when the file is missing or unreadable); ``usage``
    starts the example the fix gives (``--model``, ``ffrecon inspect-model``)."""
    path = _path(flag)

    def parse(text: str) -> Path:
        model = path(text)
        if model.is_dir():
            inside = sorted(model.glob("*.onnx"))
            example = f", e.g. {usage} {inside[0]}" if inside else " (docs/models.md says how to make one)"
            raise InputError(f"{flag} {model} is a folder, not a model file", f"pass the .onnx file itself{example}")
        return model

    return parse


class _Parser(argparse.ArgumentParser):
    """argparse's own refusals (an unknown option, a missing argument, a choice not offered) as ffrecon's: an
    InputError, which main prints in one line with the fix (exit 2), instead of the usage text."""

    def error(self, message: str):
        raise InputError(message, f"see `{self.prog} --help`")


class _CropBox(argparse.Action):
    """``--crop-box x0 y0 z0 x1 y1 z1`` or ``--crop-box BOX.json``: read and checked as the command line is
    read (:func:`~ffrecon.splat.clean.crop_box_from_args`; an InputError, exit 2)."""

    def __call__(self, parser, namespace, values, option_string=None):
        from ffrecon.splat.clean import crop_box_from_args

        setattr(namespace, self.dest, crop_box_from_args(values, option_string or "--crop-box"))


class _Partner(NamedTuple):
    """What an option acts with: ``label`` in the message, ``how`` to get it in the fix, ``met(args)``."""

    label: str
    how: str
    met: Callable[[argparse.Namespace], bool]


def _flag(flag: str, metavar: str = "") -> _Partner:
    dest = flag.lstrip("-").replace("-", "_")
    return _Partner(flag, f"add {flag} {metavar}".strip(), lambda a: getattr(a, dest) is not None)


_MODEL = _Partner("--model", "add --model MODEL.onnx", lambda a: a.command == "demo" or a.model is not None)
_SPLAT = _Partner("the splat", "leave out --no-splat", lambda a: not a.no_splat)
_COLMAP = _Partner(
    "the COLMAP cross-check", "leave out --no-colmap and --quick", lambda a: not (a.no_colmap or a.quick)
)
_VIDEO = _Partner(
    "a video input",
    f"pass a video file ({', '.join(VIDEO_SUFFIXES)})",
    lambda a: a.input.suffix.lower() in VIDEO_SUFFIXES and not a.input.is_dir(),
)
_RUN_DEMO = ("run", "demo")


class _Needs(NamedTuple):
    commands: tuple[str, ...]
    option: str  # as the message names it
    partner: _Partner
    given: Callable[[argparse.Namespace], bool] | None = None  # None: the option is on the command line


# Every option that acts only together with another, in one table and under one rule: given without its
# partner it is refused as the command line is read, "OPTION needs PARTNER" (exit 2), never silently ignored.
# (--quick without a model is refused by ffrecon.pipeline.check_run_options, before any work, for the Python API
# too.)
OPTION_NEEDS = (
    _Needs(_RUN_DEMO, "--intrinsics-prior", _flag("--intrinsics", "FILE")),
    _Needs(_RUN_DEMO, "--poses-prior", _flag("--poses", "MODEL_OR_JSON")),
    _Needs(_RUN_DEMO, "--ray-workers", _flag("--ray")),
    _Needs(_RUN_DEMO, "--ray-gpus", _flag("--ray")),
    _Needs(("run",), "--video-frames", _VIDEO),
    _Needs(("run",), "--compare-seeds", _MODEL),
    _Needs(("run",), "--pairing model", _MODEL, lambda a: a.pairing == "model"),
    _Needs(_RUN_DEMO, "--pairing vocab_tree", _flag("--vocab-tree", "FILE"), lambda a: a.pairing == "vocab_tree"),
    _Needs(_RUN_DEMO, "--compare-seeds", _COLMAP),  # it trains the splat from COLMAP's points
    _Needs(_RUN_DEMO, "--compare-seeds", _SPLAT),
    _Needs(_RUN_DEMO, "--pairing", _COLMAP),
    _Needs(_RUN_DEMO, "--vocab-tree", _COLMAP),
    _Needs(_RUN_DEMO, "--min-registration", _COLMAP),  # the registration gate is COLMAP's
    _Needs(_RUN_DEMO, "--sog", _SPLAT),
    _Needs(_RUN_DEMO, "--crop-box", _SPLAT),
    _Needs(_RUN_DEMO, "--splat-seconds", _SPLAT),
    _Needs(("export-model",), "--height", _flag("--width", "W")),
    _Needs(("export-model",), "--width", _flag("--height", "H")),
    _Needs(
        ("export-model",),
        "--keep-untrained-heads",
        _Partner("random weights", "add --random-init or --tiny", lambda a: a.random_init or a.tiny),
    ),
)


def _given_option(args: argparse.Namespace, option: str) -> bool:
    value = getattr(args, option.lstrip("-").replace("-", "_"))
    return value is not None and value is not False


def check_partners(args: argparse.Namespace) -> None:
    """Raise :class:`InputError` for the first option of :data:`OPTION_NEEDS` given without its partner."""
    for rule in OPTION_NEEDS:
        if args.command not in rule.commands:
            continue
        given = rule.given(args) if rule.given else _given_option(args, rule.option)
        if given and not rule.partner.met(args):
            name = rule.option.split()[0]
            raise InputError(f"{rule.option} needs {rule.partner.label}", f"{rule.partner.how}, or leave out {name}")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line, every value and every option's partner checked (an InputError else)."""
    args = build_parser().parse_args(argv)
    check_partners(args)
    return args


def _field_default(options_class, name: str):
    """The default of a field of an options dataclass, for help texts (the value lives in the class alone;
    tests/test_cli_defaults.py checks every help text's default against its field)."""
    return options_class.__dataclass_fields__[name].default


def _keyword_default(function, name: str):
    """The default of a function's keyword argument, for help texts (the value lives in the signature alone)."""
    import inspect

    return inspect.signature(function).parameters[name].default


def _add_output_folder_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "-o", "--out", type=_path("--out"), required=True, help="output folder (see the README for its layout)"
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
        type=_path("--reference"),
        default=None,
        help="a reference COLMAP model to score the cameras against",
    )


def _add_model_call_options(p: argparse.ArgumentParser) -> None:
    """Options of ``run`` and ``demo`` for the model's calls (defaults: MultiviewOptions' and
    FeedForwardOptions')."""
    from ffrecon.models.memory import MEMORY_FRACTION
    from ffrecon.models.multiview import MultiviewOptions
    from ffrecon.models.stage import FeedForwardOptions

    p.add_argument(
        "--chunk-size",
        type=_number(lambda v: MultiviewOptions(chunk_size=v, chunk_overlap=1)),
        default=None,
        help=f"frames per model call (default: as many as fit in {MEMORY_FRACTION * 100:g}%% of the free memory; "
        "docs/benchmarks.md)",
    )
    p.add_argument(
        "--chunk-overlap",
        type=_number(lambda v: MultiviewOptions(chunk_overlap=v)),
        default=None,
        help="frames shared by consecutive chunks, at least 1 and less than the chunk size "
        f"(default {_field_default(MultiviewOptions, 'chunk_overlap')})",
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
        type=_number(lambda v: FeedForwardOptions(threads=v)),
        default=None,
        help="CPU threads for inference, >= 1 (default: all)",
    )
    _add_ray_options(p)


def _add_ray_options(p: argparse.ArgumentParser) -> None:
    """The model's chunks on Ray (defaults: RayOptions')."""
    from ffrecon.models.distributed import RayOptions

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
        type=_number(lambda v: RayOptions(workers=v)),
        default=None,
        help="with --ray: model sessions (default: as many as the cluster's CPUs allow, one per chunk at most)",
    )
    p.add_argument(
        "--ray-gpus",
        type=_number(lambda v: RayOptions(gpus_per_worker=v), integer=False),
        default=None,
        help="with --ray: GPUs per model session (1 on a GPU cluster: onnxruntime runs on CUDA there; "
        "default: none, the CPU)",
    )


def _add_known_input_options(p: argparse.ArgumentParser) -> None:
    """What the user knows about the capture: intrinsics, poses, masks."""
    p.add_argument(
        "--intrinsics",
        type=_path("--intrinsics"),
        default=None,
        metavar="FILE",
        help="known intrinsics in COLMAP's cameras.txt form (one camera for all photos, or a line per photo with "
        "its name in place of the id): they replace the model's (reported beside them), seed COLMAP's focal "
        "and stay fixed in the bundle adjustment",
    )
    p.add_argument(
        "--poses",
        type=_path("--poses"),
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
        type=_path("--masks"),
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
    from ffrecon.sfm.colmap_options import ColmapOptions, PairingMode

    p.add_argument(
        "--pairing",
        choices=[m.value for m in PairingMode],
        default=None,
        help="pairs the COLMAP cross-check matches: exhaustive, sequential (video order, frames 2^k apart; loop "
        "closure with --vocab-tree), spatial (GPS), vocab_tree (retrieval), model (the pairs the model's cameras "
        "and depth say overlap, loop candidates included; COLMAP still verifies and maps on its own); "
        f"default {_field_default(ColmapOptions, 'pairing').value}: exhaustive up to "
        f"{_field_default(ColmapOptions, 'exhaustive_max_images')} photos, then model with a model, else sequential",
    )
    p.add_argument(
        "--vocab-tree",
        type=_path("--vocab-tree"),
        default=None,
        metavar="FILE",
        help="a COLMAP vocabulary tree (from colmap.github.io) for vocab_tree pairing and sequential loop closure",
    )


def _add_run_options(p: argparse.ArgumentParser) -> None:
    """Options of ``run`` and ``demo``; their defaults live in the stage options classes alone, and so do
    their checks (each class's ``__post_init__``: a bad value is an InputError naming the flag)."""
    from ffrecon.capture import CaptureOptions
    from ffrecon.sfm.gates import GateOptions
    from ffrecon.splat.optimize import OptimizeOptions

    _add_output_folder_options(p)
    _add_model_call_options(p)
    p.add_argument(
        "--max-image-size",
        type=_number(lambda v: CaptureOptions(max_image_size=v)),
        default=None,
        metavar="N",
        help="long side in pixels of the frames every stage works on; larger photos are downscaled at capture "
        f"(default {_field_default(CaptureOptions, 'max_image_size')}, as 3DGS; 0 keeps full size, which costs "
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
        type=_number(lambda v: GateOptions(min_registration_ratio=v), integer=False),
        default=None,
        help="registration-ratio gate: the share of the images COLMAP must register, 0 to 1 "
        f"(default {_field_default(GateOptions, 'min_registration_ratio')})",
    )
    p.add_argument(
        "--splat-seconds",
        type=_number(lambda v: OptimizeOptions.brief(max_seconds=v), integer=False),
        default=None,
        help="the splat stage's budget in seconds, > 0: its optimisation, held-out scores, cleaning, pose check, "
        f"renders, video and SPZ together (default {_field_default(OptimizeOptions, 'max_seconds')})",
    )
    p.add_argument(
        "--crop-box",
        nargs="+",
        action=_CropBox,
        type=_text("--crop-box"),
        default=None,
        metavar="BOX",
        help="six numbers x0 y0 z0 x1 y1 z1, or a box file (ffrecon view writes one; docs/camera_paths.md): keep only "
        "the Gaussians in this axis-aligned box of the final cameras' world (sparse/0, transforms.json) instead of "
        "the automatic box; splat.ply and splat.spz are cropped",
    )
    _add_extra_output_options(p)
    p.add_argument("-v", "--verbose", action="count", default=0)
    p.add_argument("-q", "--quiet", action="store_true")


def build_parser() -> argparse.ArgumentParser:
    from ffrecon.capture import CaptureOptions

    parser = _Parser(prog="ffrecon", description="Photos or a video in, a verified 3D reconstruction out.")
    parser.add_argument("--version", action="version", version=f"ffrecon {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="reconstruct a folder of photos or a video")
    run.add_argument(
        "input", type=_path("the input"), help="folder of images (jpg, png, tiff, webp, bmp) or a video file"
    )
    run.add_argument(
        "--model",
        type=_model_file("--model", "--model"),
        default=None,
        help="ONNX model (any family in docs/models.md; make one with `ffrecon export-model`); "
        "without one, COLMAP makes the cameras and the splat is seeded from its points",
    )
    run.add_argument(
        "--video-frames",
        type=_number(lambda v: CaptureOptions(video_frames=v)),
        default=None,
        help=f"frames to keep from a video (default {_field_default(CaptureOptions, 'video_frames')})",
    )
    run.add_argument(
        "--skip-bad-images", action="store_true", help="leave out unreadable files and non-images instead of stopping"
    )
    _add_run_options(run)
    _add_demo_parser(sub)
    inspect = sub.add_parser("inspect-model", help="show a model's family, inputs, outputs and preprocessing")
    inspect.add_argument("model", type=_model_file("the model", "ffrecon inspect-model"), help="an .onnx file")
    _add_export_parser(sub)
    _add_view_parser(sub)
    _add_render_parser(sub)
    return parser


def _add_render_parser(sub) -> None:
    """``render``: a run's splat along a nerfstudio camera path (:mod:`ffrecon.render_path`)."""
    render = sub.add_parser("render", help="render an output folder's splat along a camera path (camera_path.json)")
    render.add_argument("out", type=_path("the output folder"), help="an output folder of `ffrecon run -o OUT`")
    render.add_argument(
        "--camera-path",
        type=_path("--camera-path"),
        required=True,
        help="nerfstudio camera_path.json in the run's world (OUT/camera_path.json is the fly-through's)",
    )
    render.add_argument("-o", "--output", type=_path("--output"), required=True, help="the video to write (.mp4)")
    render.add_argument("--overwrite", action="store_true", help="replace the video if it exists")
    render.add_argument(
        "--device",
        choices=["auto", "cpu", "cuda"],
        default=None,
        help="auto: gsplat on CUDA when available, else ffrecon's CPU renderer (the splat stage's default)",
    )
    render.add_argument("-v", "--verbose", action="count", default=0)
    render.add_argument("-q", "--quiet", action="store_true")


def _render(args: argparse.Namespace) -> int:
    from ffrecon.render_path import render_path

    done = render_path(args.out, args.camera_path, args.output, overwrite=args.overwrite, device=args.device or "auto")
    if not args.quiet:
        print(done.summary())
    return 0


def _add_view_parser(sub) -> None:
    """``view``: the caps' defaults are :class:`~ffrecon.view.ViewOptions`'s (at least 1, as it checks), the
    address's :func:`~ffrecon.view.start_viewer`'s."""
    from ffrecon.view import ViewOptions, start_viewer

    view = sub.add_parser("view", help="open an output folder's cameras, points and splat in the browser")
    view.add_argument("out", type=_path("the output folder"), help="an output folder of `ffrecon run -o OUT`")
    view.add_argument(
        "--host",
        type=_text("--host"),
        default=None,
        help=f"address to listen on (default {_keyword_default(start_viewer, 'host')}, this machine)",
    )
    view.add_argument(
        "--port",
        type=_in_range("viewer port", "--port", low=0, high=65535, note=" (0: any free port)"),
        default=None,
        help=f"port to listen on, 0 to 65535; 0: any free port (default {_keyword_default(start_viewer, 'port')})",
    )
    view.add_argument(
        "--max-points",
        type=_in_range("ViewOptions.max_points", "--max-points", low=1),
        default=None,
        help=f"points drawn at most (default {_field_default(ViewOptions, 'max_points')}; the rest subsampled)",
    )
    view.add_argument(
        "--max-gaussians",
        type=_in_range("ViewOptions.max_gaussians", "--max-gaussians", low=1),
        default=None,
        help=f"Gaussians drawn at most, most opaque first (default {_field_default(ViewOptions, 'max_gaussians')})",
    )
    view.add_argument("-v", "--verbose", action="count", default=0)


# demo's flags for fields of ffrecon.synthetic.SceneOptions, which does not check them: (dest, field, help, low,
# high); the flag is --dest
_DEMO_SCENE_FLAGS = (
    ("frames", "num_frames", "frames of the synthetic scene", DEMO_MIN_FRAMES, DEMO_MAX_FRAMES),
    ("width", "width", "frame width in pixels", DEMO_MIN_SIDE, DEMO_MAX_SIDE),
    ("height", "height", "frame height in pixels", DEMO_MIN_SIDE, DEMO_MAX_SIDE),
    ("seed", "seed", "seed of the scene's random textures and jitter", 0, SEED_MAX),
)


def _add_demo_parser(sub) -> None:
    """``demo``: the synthetic scene's options (defaults: :class:`~ffrecon.synthetic.SceneOptions`'s), then
    those of ``run``."""
    from ffrecon.synthetic import SceneOptions

    demo = sub.add_parser("demo", help="synthetic scene + simulated model through every stage (no downloads)")
    for dest, name, what, low, high in _DEMO_SCENE_FLAGS:
        default = _field_default(SceneOptions, name)
        check = _in_range(f"SceneOptions.{name}", f"--{dest}", low=low, high=high)
        demo.add_argument(f"--{dest}", type=check, default=None, help=f"{what}, {low} to {high} (default {default})")
    _add_run_options(demo)


def _scene_options(args: argparse.Namespace):
    """The demo scene's :class:`~ffrecon.synthetic.SceneOptions`: the flags given, the class's defaults else."""
    from ffrecon.synthetic import SceneOptions

    return SceneOptions(**_given(**{name: getattr(args, dest) for dest, name, *_ in _DEMO_SCENE_FLAGS}))


def _add_export_parser(sub) -> None:
    from ffrecon.models.exporting import FAMILIES

    families = "\n".join(f"  {name:<10} {entry.summary}" for name, entry in FAMILIES.items())
    export = sub.add_parser(
        "export-model",
        help="turn an upstream checkpoint into an ONNX model file ffrecon runs",
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
    """The options of ``export-model``; the defaults of --frames, --opset and --seed are
    :class:`~ffrecon.models.exporting.ModelExportOptions`'s. Long because it is one declaration per option,
    a few lines each."""
    from ffrecon.models.exporting import ModelExportOptions

    export.add_argument(
        "-o",
        "--out",
        type=_path("--out"),
        required=True,
        help="output .onnx file (weights over 2 GB go to OUT.onnx.data beside it)",
    )
    weights = export.add_mutually_exclusive_group(required=True)
    weights.add_argument(
        "--checkpoint", type=_text("--checkpoint"), help="the checkpoint file or folder you downloaded"
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
        type=_path("--upstream"),
        default=None,
        help="root of the upstream code clone, when it is not an installed package",
    )
    export.add_argument(
        "--height",
        type=_in_range("export height", "--height", low=1),
        default=None,
        help="network input height, a multiple of the family's patch size (default: from --photos, else the "
        "family's default)",
    )
    export.add_argument(
        "--width", type=_in_range("export width", "--width", low=1), default=None, help="network input width"
    )
    export.add_argument(
        "--photos",
        type=_path("--photos"),
        default=None,
        help="a photo or folder the model will be used on: sets --height/--width by the family's preprocessing",
    )
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
        type=_in_range("ModelExportOptions.count", "--frames", low=1),
        default=None,
        help="frames (pairs for pairwise models) in the traced example, >= 1; the check runs one more "
        f"(default {_field_default(ModelExportOptions, 'count')})",
    )
    export.add_argument(
        "--opset",
        type=_in_range("ModelExportOptions.opset", "--opset", low=MIN_OPSET, high=TORCHSCRIPT_MAX_OPSET),
        default=None,
        help=f"ONNX opset, {MIN_OPSET} to {TORCHSCRIPT_MAX_OPSET} "
        f"(default {_field_default(ModelExportOptions, 'opset')})",
    )
    export.add_argument("--skip-verify", action="store_true", help="do not compare onnxruntime with PyTorch")
    export.add_argument(
        "--keep-untrained-heads",
        action="store_true",
        help="with random weights, leave heads that decode to invalid cameras as initialised (tests ffrecon's checks)",
    )
    export.add_argument(
        "--variant",
        type=_text("--variant"),
        default=None,
        help="upstream configuration to build with --random-init "
        "(da3: da3-small|base|large|giant; monodepth: small|base|large, optionally -metric)",
    )
    export.add_argument(
        "--seed",
        type=_seed("--seed"),
        default=None,
        help=f"seed of the random weights and of the traced example's inputs, 0 to {SEED_MAX} "
        f"(default {_field_default(ModelExportOptions, 'seed')})",
    )
    export.add_argument("-v", "--verbose", action="count", default=0)
    export.add_argument("-q", "--quiet", action="store_true")


def _export_options(args: argparse.Namespace):
    """``export-model``'s :class:`~ffrecon.models.exporting.ModelExportOptions`; the flags not given
    (None) leave the class's defaults."""
    from ffrecon.models.exporting import ModelExportOptions

    return ModelExportOptions(
        family=args.family,
        out=args.out,
        checkpoint=args.checkpoint,
        upstream=args.upstream,
        size_hw=(args.height, args.width) if args.height else None,
        photos=args.photos,
        fp16=args.fp16,
        fused_attention=args.fused_attention,
        random_init=args.random_init,
        tiny=args.tiny,
        keep_untrained_heads=args.keep_untrained_heads,
        verify=not args.skip_verify,
        variant=args.variant,
        **_given(opset=args.opset, count=args.frames, seed=args.seed),
    )


def _export(args: argparse.Namespace) -> None:
    import warnings

    from ffrecon.models.exporting import export_model

    options = _export_options(args)
    with warnings.catch_warnings():
        warnings.simplefilter(
            "ignore"
        )  # the tracer's warnings are about the Python-side size logic the export fixes on purpose
        report = export_model(options)
    print(report.summary())


def _given(**values) -> dict:
    """The options the user gave (None: not given, so the options class's default stands)."""
    return {k: v for k, v in values.items() if v is not None}


def _colmap_options(args: argparse.Namespace, preset):
    from ffrecon.sfm.colmap_options import PairingMode

    return dataclasses.replace(
        preset,
        enabled=preset.enabled and not args.no_colmap,
        **_given(
            pairing=None if args.pairing is None else PairingMode(args.pairing),
            vocab_tree_path=args.vocab_tree,
        ),
    )


def _ray_options(args: argparse.Namespace):
    from ffrecon.models.distributed import RayOptions

    if args.ray is None:  # --ray-workers and --ray-gpus need --ray (OPTION_NEEDS)
        return None
    return RayOptions(address=args.ray or None, **_given(workers=args.ray_workers, gpus_per_worker=args.ray_gpus))


def _run_options(args: argparse.Namespace, ground_truth: Path | None = None):
    from ffrecon.capture import CaptureOptions
    from ffrecon.export.stage import ExportOptions
    from ffrecon.models.adapters import PreprocessMode
    from ffrecon.models.multiview import MultiviewOptions
    from ffrecon.models.stage import FeedForwardOptions
    from ffrecon.pipeline import RunOptions
    from ffrecon.sfm.gates import GateOptions
    from ffrecon.splat.clean import CleanOptions
    from ffrecon.splat.optimize import OptimizeOptions
    from ffrecon.splat.stage import SplatOptions

    mode = PreprocessMode(args.preprocess) if args.preprocess else None
    multiview = MultiviewOptions(mode=mode, **_given(chunk_size=args.chunk_size, chunk_overlap=args.chunk_overlap))
    if getattr(args, "no_loop_chunks", False):
        multiview = dataclasses.replace(multiview, loops=dataclasses.replace(multiview.loops, enabled=False))
    capture = CaptureOptions(
        **_given(
            video_frames=getattr(args, "video_frames", None),
            skip_bad_images=getattr(args, "skip_bad_images", None),
            max_image_size=args.max_image_size,
            intrinsics=args.intrinsics,
            masks=args.masks,
            poses=args.poses,
        ),
        poses_prior=args.poses_prior,
        intrinsics_prior=args.intrinsics_prior,
    )
    splat = SplatOptions(
        enabled=not args.no_splat,
        compare_seeds=args.compare_seeds,
        sog=args.sog,
        optimize=OptimizeOptions.brief(**_given(max_seconds=args.splat_seconds)),
        **_given(clean=args.crop_box and CleanOptions(crop_box=args.crop_box)),
    )
    preset = RunOptions.quick() if args.quick else RunOptions()  # the flags below override the preset's fields
    return dataclasses.replace(
        preset,
        capture=capture,
        feedforward=FeedForwardOptions(multiview=multiview, ray=_ray_options(args), **_given(threads=args.threads)),
        colmap=_colmap_options(args, preset.colmap),
        gates=GateOptions(**_given(min_registration_ratio=args.min_registration)),
        refine=dataclasses.replace(preset.refine, enabled=not args.no_refine),
        splat=splat,
        exports=ExportOptions(mesh=args.mesh),
        overwrite=args.overwrite,
        resume=args.resume,
        fresh=args.fresh,
        force=args.force,
        ground_truth=ground_truth,
        reference=args.reference,
        command=shlex.join(["ffrecon", *sys.argv[1:]]),
    )


def _print_summary(results) -> None:
    """The end-of-run summary, from the same report data as report.html."""
    from ffrecon.report.build import build_report
    from ffrecon.report.html import summary_rows, wall_seconds

    report = build_report(results)
    verdict = report["verdict"]
    print(f"\nffrecon: {verdict['status'].upper()} - {verdict['message']}")
    for item, value in summary_rows(report):
        print(f"  {item:<28} {value}")
    for item in report["skipped_stages"]:
        print(f"  skipped {item['stage']}: {item['reason']}")
    print(f"  {'time':<28} {wall_seconds(report):.1f} s")
    print(f"  report: {results.out_dir / 'report.html'}")
    print(f"  look around in 3D: ffrecon view {results.out_dir}")


def _inspect(path: Path) -> None:
    from ffrecon.models.adapters import adapter_for
    from ffrecon.models.runner import FAMILY_NAMES, OnnxModel
    from ffrecon.types import ModelFamily

    model = OnnxModel(path)
    simulated = " (SIMULATED)" if model.simulated else ""
    print(f"{path.name}: {FAMILY_NAMES[model.family]} ({model.family.value}) model{simulated}")
    print("inputs:\n" + "\n".join(f"  {s}" for s in model.inputs))
    print("outputs:\n" + "\n".join(f"  {s}" for s in model.outputs))
    if model.family is ModelFamily.PAIRWISE:
        print(
            "preprocessing: RGB (x/255 - 0.5) / 0.5; long side 512 (224 checkpoints: short side 224, centre "
            "square), sides cropped to multiples of 16, square photos to 4:3; pairs from a pair graph, then "
            "global alignment"
        )
        if {"desc", "desc_conf"} <= {o.name for o in model.outputs}:
            print("MASt3R descriptors (desc, desc_conf per view) are checked but not used yet")
    else:
        adapter = adapter_for(model.family)
        print(f"contract: {adapter.description}")
        print(f"preprocessing modes: {', '.join(m.value for m in adapter.modes)}; world frame: {adapter.world_frame}")
    for k, v in model.metadata.items():
        print(f"  metadata {k}: {v[:200]}")


def _view_options(args: argparse.Namespace):
    """``view``'s :class:`~ffrecon.view.ViewOptions`: the caps given, the class's defaults else."""
    from ffrecon.view import ViewOptions

    return ViewOptions(**_given(max_points=args.max_points, max_gaussians=args.max_gaussians))


def _view(args: argparse.Namespace) -> int:
    """Serve the viewer until Ctrl-C (or SIGTERM), then stop it and say so in one line (exit 0)."""
    import time

    from ffrecon.view import load_scene, start_viewer

    started = time.perf_counter()
    scene = load_scene(args.out, _view_options(args))
    signal.signal(signal.SIGTERM, _terminate)  # pycolmap, imported by load_scene, installs its own handler
    viewer = start_viewer(scene, **_given(host=args.host, port=args.port))
    for what, why in scene.missing:
        log.info("not shown: %s (%s)", what, why)
    print(f"viewer: {viewer.url}  (ready in {time.perf_counter() - started:.1f} s; Ctrl-C stops it)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        stopped = viewer.stop()
        print("ffrecon: viewer stopped", file=sys.stderr)
        if not stopped:  # a connection held the server: leave without waiting for its threads at exit
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)
    return 0


def _leave_if_work_beside(exit_code: int) -> None:
    """After a second Ctrl-C the run stops without waiting for COLMAP's current step in the thread beside
    (ffrecon.concurrency); a process that finishes normally while pycolmap computes in another thread is
    aborted by the C++ runtime, so it leaves at once instead (the staging folder is already as it stays)."""
    from ffrecon.concurrency import work_beside_running

    if work_beside_running():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(exit_code)


def _parse_with_imports(argv: list[str] | None) -> argparse.Namespace:
    """Parse the command line and import what the command runs, with Ctrl-C and SIGTERM held until done.

    Held, because a KeyboardInterrupt inside a C extension's initialisation becomes an ImportError with a
    traceback (:func:`~ffrecon.concurrency.interrupts_deferred`); a signal is then taken once the imports
    end. pycolmap's logging library (glog) installs, when pycolmap is imported, a SIGTERM handler that
    prints a native stack trace and kills the process, so pycolmap is imported in a block of its own, whose
    end puts the held handlers back. numpy, OpenCV and Pillow load before it, in the order the package
    has always imported them: with pycolmap's bundled libraries loaded first, Pillow's PNG writer aborts in
    zlib's deflateEnd ("double free", reproduced with `ffrecon demo`).
    """
    with interrupts_deferred(), _blocked_in_the_kernel():
        import cv2  # noqa: F401
        import numpy  # noqa: F401
        import PIL.Image  # noqa: F401
        import pycolmap  # noqa: F401
    with interrupts_deferred():  # seconds of imports: the option classes, then the pipeline
        args = parse_args(argv)
        _setup_logging(-1 if getattr(args, "quiet", False) else getattr(args, "verbose", 0))
        if args.command in ("run", "demo"):
            import ffrecon.pipeline  # noqa: F401
    return args


@contextlib.contextmanager
def _blocked_in_the_kernel():
    """SIGINT and SIGTERM blocked by the kernel (left pending) while glog may own them: pycolmap's import
    installs glog's native handler part-way through its initialisation, and a signal arriving after that
    was handled by glog (a stack dump, the process killed: reproduced by SIGTERM 0.25 s after start on a
    loaded machine). Blocked before numpy and OpenCV load, because the threads they start (OpenBLAS's)
    inherit the mask: a signal that reached such a thread went to glog's handler too (seen once in 40
    tries). At the end Python's handlers are put back over glog's, then the main thread unblocks, so a
    pending signal reaches the Python handler in force (held by :func:`interrupts_deferred`)."""
    held = {signal.SIGINT, signal.SIGTERM}
    before = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        for sig in held:
            handler = signal.getsignal(sig)
            if handler is not None:
                signal.signal(sig, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _terminate(signum, frame) -> None:
    """SIGTERM ends the run like Ctrl-C: finished stages kept, one line said, no stack trace."""
    raise KeyboardInterrupt


def _run_command(args: argparse.Namespace):
    from ffrecon.pipeline import run

    if args.command == "demo":
        from ffrecon.demo import DemoOptions, prepare_demo

        options = _run_options(args)  # checked before the scene is rendered
        demo = prepare_demo(DemoOptions(scene=_scene_options(args)))
        return run(demo.images, args.out, demo.model, dataclasses.replace(options, ground_truth=demo.scene_dir))
    return run(args.input, args.out, args.model, _run_options(args))


def main(argv: list[str] | None = None) -> int:
    previous = signal.signal(signal.SIGTERM, _terminate)
    showwarning, warnings.showwarning = warnings.showwarning, _log_warning
    try:
        args = _parse_with_imports(argv)
        if args.command == "inspect-model":
            _inspect(args.model)
            return 0
        if args.command == "export-model":
            _export(args)
            return 0
        if args.command == "view":
            return _view(args)
        if args.command == "render":
            return _render(args)
        results = _run_command(args)
    except Interrupted as err:
        print(f"ffrecon: {err.problem}; {err.fix}", file=sys.stderr)
        _leave_if_work_beside(err.exit_code)
        return err.exit_code
    except FFReconError as err:
        print(f"ffrecon: error: {err.problem}", file=sys.stderr)
        if err.fix:
            print(f"  fix: {err.fix}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("ffrecon: interrupted; earlier results are untouched", file=sys.stderr)
        _leave_if_work_beside(Interrupted.exit_code)
        return Interrupted.exit_code
    finally:
        signal.signal(signal.SIGTERM, previous)
        warnings.showwarning = showwarning
    if not getattr(args, "quiet", False):
        _print_summary(results)
    return results.exit_code


def entry() -> int:
    """The ``ffrecon`` command (and ``python -m ffrecon``): :func:`main`, then SIGTERM ignored while the
    interpreter shuts down (torch, numba and open3d take a moment), so that a finished run's exit code
    is not turned into a kill."""
    code = main()
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return code
