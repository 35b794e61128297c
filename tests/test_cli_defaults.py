"""The command line's defaults and help texts come from the options dataclasses (issue 23), so they cannot drift:
every flag that sets a dataclass field defaults to None (the field's default stands), its help text shows that
field's default, and parsing no flags gives the dataclasses' defaults. A default written in the CLI is allowed
only where no options class holds the value (CLI_ONLY_DEFAULTS); a flag that sets a keyword argument of a function
takes that keyword's default (KEYWORD_DEFAULTS). The splat's budget has one default (issue 41)."""

import argparse
import dataclasses
import inspect
import logging
import re
from pathlib import Path

import pytest

from ffrecon import cli
from ffrecon.capture import CaptureOptions
from ffrecon.models.exporting import ModelExportOptions
from ffrecon.models.memory import MEMORY_FRACTION
from ffrecon.models.multiview import MultiviewOptions
from ffrecon.pipeline import RunOptions
from ffrecon.report import html
from ffrecon.sfm.crosscheck.gate_types import GateOptions
from ffrecon.splat import stage as splat_stage
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import SplatOptions
from ffrecon.synthetic import SceneOptions
from ffrecon.view import ViewOptions, start_viewer

_RUN_AND_DEMO = {
    "--chunk-overlap": (MultiviewOptions, "chunk_overlap"),
    "--max-image-size": (CaptureOptions, "max_image_size"),
    "--min-registration": (GateOptions, "min_registration_ratio"),
    "--splat-seconds": (OptimizeOptions, "max_seconds"),
}
# subcommand -> {flag: (options class, field)}: the flags that set a field of an options dataclass
FIELDS = {
    "run": {**_RUN_AND_DEMO, "--video-frames": (CaptureOptions, "video_frames")},
    "demo": {
        **_RUN_AND_DEMO,
        "--frames": (SceneOptions, "num_frames"),
        "--width": (SceneOptions, "width"),
        "--height": (SceneOptions, "height"),
        "--seed": (SceneOptions, "seed"),
    },
    "view": {"--max-points": (ViewOptions, "max_points"), "--max-gaussians": (ViewOptions, "max_gaussians")},
    "export-model": {
        "--frames": (ModelExportOptions, "count"),
        "--opset": (ModelExportOptions, "opset"),
        "--seed": (ModelExportOptions, "seed"),
    },
    "inspect-model": {},
    "render": {},
}
# Defaults written in the CLI because nothing else holds them: none left.
CLI_ONLY_DEFAULTS: set[tuple[str, str]] = set()
# (subcommand, flag) -> (function, keyword): flags passed to a function whose signature holds their default.
KEYWORD_DEFAULTS = {("view", "--host"): (start_viewer, "host"), ("view", "--port"): (start_viewer, "port")}
# The fewest arguments each subcommand parses with.
REQUIRED = {
    "run": ["photos", "-o", "out"],
    "demo": ["-o", "out"],
    "view": ["out"],
    "export-model": ["vggt", "-o", "model.onnx", "--tiny"],
    "inspect-model": ["model.onnx"],
    "render": ["out", "--camera-path", "camera_path.json", "-o", "video.mp4"],
}
EXPORT_DEFAULTS = ModelExportOptions(family="vggt", out=Path("model.onnx"), tiny=True)
# Flags whose value is a count, a switch or an action of argparse's own: no options class holds their default.
_ARGPARSE_DEFAULTS = (
    argparse._StoreTrueAction,
    argparse._CountAction,
    argparse._HelpAction,
    argparse._VersionAction,
)
_CASES = [(command, flag) for command, flags in FIELDS.items() for flag in flags]


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    (sub,) = [a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def _flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """The options of a subcommand by their long flag (positional arguments left out)."""
    return {a.option_strings[-1]: a for a in parser._actions if a.option_strings}


def _help(action: argparse.Action) -> str:
    """The help text as --help prints it (argparse's %-formatting, without the line wrapping)."""
    return (action.help or "") % {**vars(action), "prog": "ffrecon"}


def _options(command: str, argv: list[str]) -> dict:
    """The options objects a subcommand makes from its arguments, by options class."""
    args = cli.build_parser().parse_args([command, *REQUIRED[command], *argv])
    if command == "export-model":
        return {ModelExportOptions: cli._export_options(args)}
    if command == "view":
        return {ViewOptions: cli._view_options(args)}
    run = cli._run_options(args)
    made = {
        CaptureOptions: run.capture,
        MultiviewOptions: run.feedforward.multiview,
        GateOptions: run.gates,
        OptimizeOptions: run.splat.optimize,
    }
    if command == "demo":
        made[SceneOptions] = cli._scene_options(args)
    return made


def _field_default(options_class, name: str):
    """The field's default, read from the dataclass itself (not through the CLI's helper)."""
    (field,) = [f for f in dataclasses.fields(options_class) if f.name == name]
    assert field.default is not dataclasses.MISSING, f"{options_class.__name__}.{name} has no plain default"
    return field.default


def test_every_subcommand_is_listed():
    assert set(_subparsers()) == set(FIELDS) == set(REQUIRED)


@pytest.mark.parametrize(("command", "flag"), _CASES)
def test_help_shows_the_field_default(command, flag):
    options_class, name = FIELDS[command][flag]
    action = _flags(_subparsers()[command])[flag]
    default = _field_default(options_class, name)
    assert action.default is None, f"{command} {flag}: default {action.default!r} written in the CLI"
    shown = re.findall(r"\bdefault:? ([^\s,;)]+)", _help(action))
    assert shown == [str(default)], f"{command} {flag} help says default {shown}, {options_class.__name__}.{name}"


def test_no_other_default_is_written_in_the_cli():
    """A flag outside FIELDS has no default of its own (None: the options class decides) and its help names no
    number as its default, unless the CLI alone holds the value (CLI_ONLY_DEFAULTS)."""
    written = []
    for command, parser in _subparsers().items():
        for flag, action in _flags(parser).items():
            if flag in FIELDS[command] or (command, flag) in CLI_ONLY_DEFAULTS | set(KEYWORD_DEFAULTS):
                continue
            if not isinstance(action, _ARGPARSE_DEFAULTS) and action.default is not None:
                written.append(f"{command} {flag} default={action.default!r}")
            if re.search(r"\bdefault:? -?\d", _help(action)):
                written.append(f"{command} {flag} help: {_help(action)!r}")
    assert not written, "take these from an options class (and add them to FIELDS): " + "; ".join(written)


@pytest.mark.parametrize("command", ["run", "demo"])
def test_chunk_size_help_names_the_memory_fraction(command):
    text = _help(_flags(_subparsers()[command])["--chunk-size"])
    assert f"as many as fit in {MEMORY_FRACTION * 100:g}% of the free memory" in text


@pytest.mark.parametrize("command", ["run", "demo"])
def test_no_flags_give_the_run_defaults(command):
    args = cli.build_parser().parse_args([command, *REQUIRED[command]])
    assert dataclasses.replace(cli._run_options(args), command="") == RunOptions()
    if command == "demo":
        assert cli._scene_options(args) == SceneOptions()


def test_quick_gives_the_quick_preset():
    args = cli.build_parser().parse_args(["run", *REQUIRED["run"], "--quick"])
    assert dataclasses.replace(cli._run_options(args), command="") == RunOptions.quick()


def test_no_flags_give_the_view_and_export_defaults():
    assert _options("view", [])[ViewOptions] == ViewOptions()
    assert _options("export-model", [])[ModelExportOptions] == EXPORT_DEFAULTS


@pytest.mark.parametrize(("command", "flag"), _CASES)
def test_each_flag_sets_its_field(command, flag):
    """Without the flag the field keeps its default; with another value the flag sets that field."""
    options_class, name = FIELDS[command][flag]
    default = _field_default(options_class, name)
    assert getattr(_options(command, [])[options_class], name) == default
    other = default / 2 if isinstance(default, float) else default + 1
    assert getattr(_options(command, [flag, str(other)])[options_class], name) == other


@pytest.mark.parametrize(("command", "flag"), sorted(KEYWORD_DEFAULTS))
def test_help_shows_the_keyword_default(command, flag):
    function, name = KEYWORD_DEFAULTS[command, flag]
    action = _flags(_subparsers()[command])[flag]
    default = inspect.signature(function).parameters[name].default
    assert action.default is None, f"{command} {flag}: default {action.default!r} written in the CLI"
    shown = re.findall(r"\bdefault:? ([^\s,;)]+)", _help(action))
    assert shown == [str(default)], f"{command} {flag} help says default {shown}, {function.__name__}({name}=...)"


def test_the_splat_budget_has_one_default():
    """The run's splat budget is OptimizeOptions.max_seconds's default: the brief preset (what the splat stage
    trains with) does not write another."""
    budget = _field_default(OptimizeOptions, "max_seconds")
    assert SplatOptions().optimize.max_seconds == OptimizeOptions.brief().max_seconds == budget
    assert "max_seconds" not in inspect.getsource(OptimizeOptions.brief).split('"""')[-1]


def test_prose_names_the_options_defaults(monkeypatch, caplog):
    """The splat's memory warning and the report's held-out caption read their numbers from the options."""
    monkeypatch.setattr(CaptureOptions.__dataclass_fields__["max_image_size"], "default", 1234)
    monkeypatch.setattr(SplatOptions.__dataclass_fields__["holdout_every"], "default", 5)
    assert "every 5th frame by default" in html.curve_caption()
    monkeypatch.setattr(splat_stage, "training_side", lambda sizes, cap: 320)
    monkeypatch.setattr(splat_stage, "splat_peak_bytes", lambda sizes, cap: 2**31)
    with caplog.at_level(logging.WARNING, logger="ffrecon.splat"):
        splat_stage.check_splat_memory([(640, 480)], SplatOptions(device="cpu"))
    assert "(--max-image-size, default 1234)" in caplog.text


def _printed_entry(command: str, flag: str) -> str:
    """The help `ffrecon COMMAND --help` prints for ``flag`` (argparse's wrapping undone): from its listing
    (``--flag METAVAR``) under options, at most 400 characters."""
    parser = _subparsers()[command]
    action = _flags(parser)[flag]
    printed = " ".join(parser.format_help().split())
    listing = f" {flag} {action.metavar or action.dest.upper()} "
    options = printed[printed.index("options:") :]
    return options[options.index(listing) :][:400]


@pytest.mark.parametrize("command", sorted(FIELDS))
def test_printed_help_shows_each_field_default(command):
    """What `ffrecon COMMAND --help` prints names each flag with its field's default (or its function keyword's)."""
    defaults = {flag: _field_default(*field) for flag, field in FIELDS[command].items()}
    for (keyword_command, flag), (function, name) in KEYWORD_DEFAULTS.items():
        if keyword_command == command:
            defaults[flag] = inspect.signature(function).parameters[name].default
    for flag, default in defaults.items():
        entry = _printed_entry(command, flag)
        assert re.search(rf"\bdefault:? {re.escape(str(default))}(?![\w.])", entry), f"{command} {flag}: {entry}"
