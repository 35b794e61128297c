"""Options that act only together with another (:data:`OPTION_NEEDS`), checked as the command line is read."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import NamedTuple

from ffrecon.errors import InputError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")  # ffrecon.capture.images.VIDEO_EXTENSIONS


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
