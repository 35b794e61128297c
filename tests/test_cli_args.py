"""Every argument of every subcommand is checked as the command line is read (issue 43): a bad value, an option
without its partner, or argparse's own refusal is one ``ffrecon: error:`` line and its fix, exit 2, before any
work and never a traceback. Python warnings during a command are logged in one line, without a source path."""

import argparse
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from ffrecon import cli

_RUN = ["run", "photos", "-o", "{tmp}/out"]
_DEMO = ["demo", "-o", "{tmp}/out"]
_VIEW = ["view", "{tmp}"]
_EXPORT = ["export-model", "vggt", "-o", "{tmp}/m.onnx", "--tiny"]

# (command line, a text the error line names): each refused as it is read
BAD = {
    "view port 99999": ([*_VIEW, "--port", "99999"], "--port"),
    "view port=-1": ([*_VIEW, "--port=-1"], "--port"),
    "view port text": ([*_VIEW, "--port", "http"], "--port"),
    "view port 80.5": ([*_VIEW, "--port", "80.5"], "--port"),
    "view max-points 0": ([*_VIEW, "--max-points", "0"], "--max-points"),
    "view max-gaussians -3": ([*_VIEW, "--max-gaussians", "-3"], "--max-gaussians"),
    "view empty host": ([*_VIEW, "--host", ""], "--host"),
    "view empty folder": (["view", ""], "output folder"),
    "demo frames 1..7": ([*_DEMO, "--frames", "1..7"], "--frames"),
    "demo frames 0": ([*_DEMO, "--frames", "0"], "--frames"),
    "demo frames 7 (no frame 7 to make wrong)": ([*_DEMO, "--frames", "7"], "--frames"),
    "demo frames 1001": ([*_DEMO, "--frames", "1001"], "--frames"),
    "demo width -5": ([*_DEMO, "--width", "-5"], "--width"),
    "demo width 63": ([*_DEMO, "--width", "63"], "--width"),
    "demo height 5000": ([*_DEMO, "--height", "5000"], "--height"),
    "demo seed -1": ([*_DEMO, "--seed", "-1"], "--seed"),
    "demo seed 2^32": ([*_DEMO, "--seed", str(2**32)], "--seed"),
    "demo chunk-size nan": ([*_DEMO, "--chunk-size", "nan"], "--chunk-size"),
    "run chunk-size 1": ([*_RUN, "--chunk-size", "1"], "--chunk-size"),
    "run chunk-size text": ([*_RUN, "--chunk-size", "many"], "--chunk-size"),
    "run chunk-overlap 0": ([*_RUN, "--chunk-overlap", "0"], "--chunk-overlap"),
    "run threads 2.5": ([*_RUN, "--threads", "2.5"], "--threads"),
    "run ray-workers 0": ([*_RUN, "--ray", "--ray-workers", "0"], "--ray-workers"),
    "run ray-gpus inf": ([*_RUN, "--ray", "--ray-gpus", "inf"], "--ray-gpus"),
    "run max-image-size 10": ([*_RUN, "--max-image-size", "10"], "--max-image-size"),
    "run min-registration 1.5": ([*_RUN, "--min-registration", "1.5"], "--min-registration"),
    "run splat-seconds -1": ([*_RUN, "--splat-seconds", "-1"], "--splat-seconds"),
    "run crop-box x0 >= x1": ([*_RUN, "--crop-box", "1", "0", "0", "1", "1", "1"], "--crop-box 1 0 0 1 1 1 is empty"),
    "run crop-box 5 numbers": ([*_RUN, "--crop-box", "0", "0", "0", "1", "1"], "--crop-box takes 6 numbers"),
    "demo crop-box nan": ([*_DEMO, "--crop-box", "0", "0", "0", "1", "nan", "1"], "not a finite number"),
    "run crop-box no file": ([*_RUN, "--crop-box", "{tmp}/box.json"], "box.json does not exist"),
    "render no camera path": (["render", "{tmp}", "-o", "{tmp}/v.mp4"], "--camera-path"),
    "render empty output": (["render", "{tmp}", "--camera-path", "p.json", "-o", ""], "--output"),
    "render device": (["render", "{tmp}", "--camera-path", "p.json", "-o", "v.mp4", "--device", "gpu"], "--device"),
    "run video-frames 1": (["run", "clip.mp4", "-o", "{tmp}/out", "--video-frames", "1"], "--video-frames"),
    "run pairing unknown": ([*_RUN, "--pairing", "nearest"], "--pairing"),
    "run preprocess unknown": ([*_RUN, "--preprocess", "zoom"], "--preprocess"),
    "run unknown option": ([*_RUN, "--colour"], "--colour"),
    "run without -o": (["run", "photos"], "-o/--out"),
    "run empty -o": (["run", "photos", "-o", ""], "--out"),
    "run empty input": (["run", "", "-o", "{tmp}/out"], "input"),
    "run empty intrinsics": ([*_RUN, "--intrinsics", ""], "--intrinsics"),
    "run empty model": ([*_RUN, "--model", ""], "--model"),
    "export opset 14": ([*_EXPORT, "--opset", "14"], "--opset"),
    "export opset 21": ([*_EXPORT, "--opset", "21"], "--opset"),
    "export frames 0": ([*_EXPORT, "--frames", "0"], "--frames"),
    "export seed -1": ([*_EXPORT, "--seed", "-1"], "--seed"),
    "export height 0": ([*_EXPORT, "--height", "0", "--width", "14"], "--height"),
    "export family unknown": (["export-model", "dust4r", "-o", "{tmp}/m.onnx", "--tiny"], "dust4r"),
    "export empty checkpoint": (["export-model", "vggt", "-o", "{tmp}/m.onnx", "--checkpoint", ""], "--checkpoint"),
    "inspect empty model": (["inspect-model", ""], "model"),
    "no command": ([], "command"),
    "unknown command": (["rebuild"], "rebuild"),
}

# Options given without their partner (every row of cli.OPTION_NEEDS): (command line, the error line)
PARTNERLESS = {
    "intrinsics-prior": ([*_RUN, "--intrinsics-prior"], "--intrinsics-prior needs --intrinsics"),
    "poses-prior": ([*_DEMO, "--poses-prior"], "--poses-prior needs --poses"),
    "ray-workers": ([*_RUN, "--ray-workers", "2"], "--ray-workers needs --ray"),
    "ray-gpus": ([*_DEMO, "--ray-gpus", "1"], "--ray-gpus needs --ray"),
    "video-frames on a folder": ([*_RUN, "--video-frames", "20"], "--video-frames needs a video input"),
    "compare-seeds without a model": ([*_RUN, "--compare-seeds"], "--compare-seeds needs --model"),
    "pairing model without a model": ([*_RUN, "--pairing", "model"], "--pairing model needs --model"),
    "vocab_tree pairing": ([*_DEMO, "--pairing", "vocab_tree"], "--pairing vocab_tree needs --vocab-tree"),
    "compare-seeds, no COLMAP": (
        [*_DEMO, "--compare-seeds", "--quick"],
        "--compare-seeds needs the COLMAP cross-check",
    ),
    "compare-seeds, no splat": ([*_DEMO, "--compare-seeds", "--no-splat"], "--compare-seeds needs the splat"),
    "pairing, no COLMAP": ([*_RUN, "--pairing", "exhaustive", "--no-colmap"], "--pairing needs the COLMAP cross-check"),
    "vocab-tree, quick": ([*_DEMO, "--vocab-tree", "t.bin", "--quick"], "--vocab-tree needs the COLMAP cross-check"),
    "min-registration": ([*_RUN, "--min-registration", "0.5", "--no-colmap"], "--min-registration needs the COLMAP"),
    "sog": ([*_RUN, "--sog", "--no-splat"], "--sog needs the splat"),
    "splat-seconds": ([*_DEMO, "--splat-seconds", "5", "--no-splat"], "--splat-seconds needs the splat"),
    "crop-box": ([*_RUN, "--no-splat", "--crop-box", "0", "0", "0", "1", "1", "1"], "--crop-box needs the splat"),
    "export height": ([*_EXPORT, "--height", "28"], "--height needs --width"),
    "export width": ([*_EXPORT, "--width", "28"], "--width needs --height"),
    "keep-untrained-heads": (
        ["export-model", "vggt", "-o", "m.onnx", "--checkpoint", "c.pt", "--keep-untrained-heads"],
        "--keep-untrained-heads needs random weights",
    ),
}

# The same options with their partner, and the edge values each range keeps: these parse.
GOOD = {
    "view port 0 (any free port)": [*_VIEW, "--port", "0"],
    "view port 65535": [*_VIEW, "--port", "65535", "--max-points", "1", "--max-gaussians", "1"],
    "demo smallest scene": [*_DEMO, "--frames", "8", "--width", "64", "--height", "64", "--seed", "0"],
    "demo largest scene": [*_DEMO, "--frames", "1000", "--width", "4096", "--height", "4096", "--seed", str(2**32 - 1)],
    "run edges": [
        *_RUN,
        *("--max-image-size", "0", "--min-registration", "0", "--splat-seconds", "1e-3", "--chunk-size", "2"),
        *("--chunk-overlap", "1", "--threads", "1e0"),
    ],
    "run partners": [
        "run",
        "clip.MP4",
        *("-o", "{tmp}/out", "--video-frames", "2", "--model", "m.onnx", "--compare-seeds", "--sog"),
        *("--intrinsics", "c.txt", "--intrinsics-prior", "--poses", "p.json", "--poses-prior", "--pairing", "model"),
        *("--ray", "--ray-workers", "1", "--ray-gpus", "0", "--min-registration", "1", "--splat-seconds", "5"),
    ],
    "demo partners": [*_DEMO, "--pairing", "vocab_tree", "--vocab-tree", "t.bin", "--compare-seeds", "--poses", "p"],
    "run crop box": [*_RUN, "--crop-box", "-1", "-2.5", "-3", "1", "2e0", "3", "--sog"],
    "render": ["render", "{tmp}", "--camera-path", "p.json", "-o", "v.mp4", "--device", "cpu", "--overwrite"],
    "export edges": [*_EXPORT, "--opset", "15", "--frames", "1", "--height", "14", "--width", "14", "--seed", "0"],
    "export opset 20": [*_EXPORT, "--opset", "20", "--keep-untrained-heads"],
}


def _argv(args: list[str], tmp_path) -> list[str]:
    return [a.format(tmp=tmp_path) for a in args]


def _main(argv: list[str]) -> int:
    """``ffrecon.cli.main``'s exit code, whether it returns it or argparse exits."""
    try:
        return cli.main(argv)
    except SystemExit as stop:
        return stop.code


def _refused(argv: list[str], capsys) -> list[str]:
    """The stderr lines of a command line refused with exit 2 and ffrecon's one error line and its fix."""
    code = _main(argv)
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 2, captured.err
    assert "Traceback" not in captured.err and not captured.out, captured.err
    assert len(lines) == 2 and lines[0].startswith("ffrecon: error: ") and lines[1].startswith("  fix: "), lines
    return lines


@pytest.mark.parametrize("case", list(BAD))
def test_a_bad_value_is_one_line_before_any_work(case, tmp_path, capsys):
    args, named = BAD[case]
    lines = _refused(_argv(args, tmp_path), capsys)
    assert named in lines[0], lines
    assert sorted(tmp_path.iterdir()) == []  # nothing made, not even a staging folder


@pytest.mark.parametrize("case", list(PARTNERLESS))
def test_an_option_without_its_partner_is_refused(case, tmp_path, capsys):
    args, said = PARTNERLESS[case]
    lines = _refused(_argv(args, tmp_path), capsys)
    assert lines[0].startswith(f"ffrecon: error: {said}"), lines
    option = said.split()[0]
    assert lines[1].endswith(f"or leave out {option}"), lines


def test_every_partner_rule_is_tested():
    """A row added to OPTION_NEEDS needs a case in PARTNERLESS (and each case is a rule's)."""
    rules = {f"{rule.option} needs {rule.partner.label}" for rule in cli.OPTION_NEEDS}
    tested = {said for _, said in PARTNERLESS.values()}
    assert {r for r in rules if not any(r.startswith(s) for s in tested)} == set()
    assert {s for s in tested if not any(r.startswith(s) for r in rules)} == set()


@pytest.mark.parametrize("case", list(GOOD))
def test_edge_values_and_partners_parse(case, tmp_path):
    cli.parse_args(_argv(GOOD[case], tmp_path))


def test_values_come_back_typed(tmp_path):
    args = cli.parse_args(["view", str(tmp_path), "--port", "0", "--max-points", "1e3"])
    assert args.port == 0 and args.max_points == 1000 and isinstance(args.max_points, int)
    args = cli.parse_args(["run", "p", "-o", "o", "--min-registration", "1", "--ray", "--ray-gpus", "1"])
    assert isinstance(args.min_registration, float) and isinstance(args.ray_gpus, float)


def _value_actions():
    """(command, flag, action) for every option and positional that takes a value, in every subcommand."""
    (sub,) = [a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    for command, parser in sub.choices.items():
        for action in parser._actions:
            if action.nargs != 0 and not isinstance(action, argparse._HelpAction):
                yield command, (action.option_strings or [action.dest])[-1], action


FREE_TEXT = {("run", "--ray"), ("demo", "--ray")}  # a Ray address: Ray says what it cannot reach


def test_every_value_is_checked_as_it_is_read():
    """No plain int, float, str or Path: each value has a checking type or a list of choices."""
    unchecked = [
        f"{command} {flag}"
        for command, flag, action in _value_actions()
        if not action.choices and action.type in (None, int, float, str, cli.Path) and (command, flag) not in FREE_TEXT
    ]
    assert unchecked == []


def test_the_cli_constants_match_what_they_stand_for():
    import torch.onnx._constants

    from ffrecon.capture import MIN_IMAGE_SIZE
    from ffrecon.capture.images import VIDEO_EXTENSIONS
    from ffrecon.demo import DemoOptions

    assert cli.VIDEO_SUFFIXES == VIDEO_EXTENSIONS
    assert cli.DEMO_MIN_SIDE == MIN_IMAGE_SIZE
    assert cli.DEMO_MIN_FRAMES == max(DemoOptions().simulation["bad_frames"]) + 1
    assert cli.TORCHSCRIPT_MAX_OPSET == torch.onnx._constants.ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET


@pytest.mark.parametrize("command", ["run", "inspect-model"])
def test_a_model_folder_says_so_and_names_the_file_to_pass(command, tmp_path, capsys):
    folder = tmp_path / "vggt"
    folder.mkdir()
    (folder / "vggt.onnx").write_bytes(b"")
    run = ["run", "photos", "-o", str(tmp_path / "out"), "--model", str(folder)]
    argv, usage = (run, "--model") if command == "run" else (["inspect-model", str(folder)], "ffrecon inspect-model")
    lines = _refused(argv, capsys)
    assert lines[0].endswith(f"{folder} is a folder, not a model file"), lines
    assert lines[1] == f"  fix: pass the .onnx file itself, e.g. {usage} {folder / 'vggt.onnx'}"
    (folder / "vggt.onnx").unlink()
    lines = _refused(argv, capsys)
    assert "docs/models.md" in lines[1]


def test_demo_options_are_checked_before_the_scene_is_rendered(tmp_path, capsys, monkeypatch):
    import ffrecon.demo

    monkeypatch.setattr(ffrecon.demo, "prepare_demo", lambda *a, **k: pytest.fail("the scene was rendered"))
    lines = _refused(["demo", "-o", str(tmp_path / "out"), "--chunk-size", "3", "--chunk-overlap", "3"], capsys)
    assert "--chunk-overlap" in lines[0]


def test_a_warning_in_a_run_is_one_logged_line_without_a_path(tmp_path, capsys, monkeypatch):
    def run_with_a_warning(args):
        with np.errstate(invalid="warn"):
            np.array([0.0]) / np.array([0.0])
        warnings.warn("a second\nline folded", UserWarning, stacklevel=1)
        return SimpleNamespace(exit_code=0)

    monkeypatch.setattr(cli, "_run_command", run_with_a_warning)
    shown = warnings.showwarning
    assert cli.main(["run", str(tmp_path), "-o", str(tmp_path / "out"), "-q"]) == 0
    err = capsys.readouterr().err
    assert err.splitlines() == [
        "RuntimeWarning: invalid value encountered in divide",
        "UserWarning: a second line folded",
    ]
    assert warnings.showwarning is shown  # put back when the command ends
