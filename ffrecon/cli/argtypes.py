"""Argument types: every value is checked as the command line is read, before any work.

A value an options class holds is checked by that class (its ``__post_init__``: the CLI and the Python API say the
same); the InputError goes through argparse untouched (argparse catches only ValueError, TypeError and its own) to
:func:`ffrecon.cli.main`, which prints it in one line with the fix (exit 2).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ffrecon.errors import InputError

SEED_MAX = 2**32 - 1  # seeds are 0 to 2^32 - 1 (what numpy's and torch's generators all take)


def _as_number(text: str, integer: bool) -> int | float | str:
    """The text as a number where it reads as one (an int first where a whole number is wanted, so the check
    shows it as given; else a float), else the text itself (the check names it)."""
    for convert in (int, float) if integer else (float,):
        try:
            return convert(text)
        except ValueError:
            pass
    return text


def number_arg(check, *, integer: bool = True):
    """An argparse ``type``: the text as a number that ``check(value)`` accepts (it raises InputError; for a
    value an options class holds, ``check`` builds that class with it)."""

    def parse(text: str) -> int | float:
        value = _as_number(text, integer)
        check(value)
        return int(value) if integer else float(value)

    return parse


def in_range(name: str, flag: str, *, low: float, high: float | None = None, integer: bool = True, note: str = ""):
    """A number no options class checks: ``low`` to ``high`` (``note`` ends the fix)."""

    def check(value) -> None:
        from ffrecon.checks import check_number  # numpy: loaded by main once signals are held

        try:
            check_number(name, value, low=low, high=high, integer=integer, flag=flag)
        except InputError as err:
            raise InputError(err.problem, err.fix + note) from None

    return number_arg(check, integer=integer)


def seed_arg(flag: str):
    return in_range("seed", flag, low=0, high=SEED_MAX)


def text_arg(flag: str):
    """A non-empty string."""

    def parse(text: str) -> str:
        if not text.strip():
            raise InputError(f"{flag} is empty", f"pass {flag} with a value")
        return text

    return parse


def path_arg(flag: str):
    """A non-empty path (``Path("")`` would be the current folder)."""
    text = text_arg(flag)
    return lambda value: Path(text(value))


def model_file_arg(flag: str, usage: str):
    """A model path that is not a folder (the runner says when the file is missing or unreadable); ``usage``
    starts the example the fix gives (``--model``, ``ffrecon inspect-model``)."""
    path = path_arg(flag)

    def parse(text: str) -> Path:
        model = path(text)
        if model.is_dir():
            inside = sorted(model.glob("*.onnx"))
            example = f", e.g. {usage} {inside[0]}" if inside else " (docs/models.md says how to make one)"
            raise InputError(f"{flag} {model} is a folder, not a model file", f"pass the .onnx file itself{example}")
        return model

    return parse


class Parser(argparse.ArgumentParser):
    """argparse's own refusals (an unknown option, a missing argument, a choice not offered) as ffrecon's: an
    InputError, which main prints in one line with the fix (exit 2), instead of the usage text."""

    def error(self, message: str):
        raise InputError(message, f"see `{self.prog} --help`")


class CropBoxAction(argparse.Action):
    """``--crop-box x0 y0 z0 x1 y1 z1`` or ``--crop-box BOX.json``: read and checked as the command line is
    read (:func:`~ffrecon.splat.clean.crop_box_from_args`; an InputError, exit 2)."""

    def __call__(self, parser, namespace, values, option_string=None):
        from ffrecon.splat.clean import crop_box_from_args

        setattr(namespace, self.dest, crop_box_from_args(values, option_string or "--crop-box"))


class Later:
    """A help text made when help is shown, for a default held by an options class whose module loads torch,
    open3d or numba (seconds), which parsing a command line or refusing one does not need: argparse makes the text
    with ``help % params`` then.

    >>> Later(lambda: "%(dest)s: 10%% of the memory") % {"dest": "chunk_size"}
    'chunk_size: 10% of the memory'
    """

    def __init__(self, make) -> None:
        self.make = make

    def __mod__(self, params) -> str:
        return self.make() % params

    def __str__(self) -> str:
        return self.make()

    def strip(self) -> str:  # argparse asks whether the text is blank before making it
        return self.make().strip()


def given(**values) -> dict:
    """The options the user gave (None: not given, so the options class's default stands)."""
    return {k: v for k, v in values.items() if v is not None}


def field_default(options_class, name: str):
    """The default of a field of an options dataclass, for help texts (the value lives in the class alone;
    tests/test_cli_defaults.py checks every help text's default against its field)."""
    return options_class.__dataclass_fields__[name].default


def keyword_default(function, name: str):
    """The default of a function's keyword argument, for help texts (the value lives in the signature alone)."""
    import inspect

    return inspect.signature(function).parameters[name].default
