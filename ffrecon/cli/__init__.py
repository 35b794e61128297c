"""Command line: thin; parses options and calls the pipeline.

The package: :mod:`~ffrecon.cli.parser` (``run`` and ``demo``) and :mod:`~ffrecon.cli.tool_parsers` (the other
subcommands) declare the flags, with :mod:`~ffrecon.cli.argtypes` checking each value as it is read and
:mod:`~ffrecon.cli.needs` each option's partner; :mod:`~ffrecon.cli.run` turns the flags into
:class:`~ffrecon.options.RunOptions` and runs the pipeline; :mod:`~ffrecon.cli.commands` runs the other commands;
:mod:`~ffrecon.cli.signals` holds Ctrl-C and SIGTERM. :func:`main` chains them.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import traceback
import warnings
from pathlib import Path

from ffrecon.cli import signals
from ffrecon.cli.argtypes import SEED_MAX
from ffrecon.cli.commands import (
    _export_options,
    _view_options,
    export_command,
    inspect_model,
    render_command,
    view_command,
)
from ffrecon.cli.needs import OPTION_NEEDS, VIDEO_SUFFIXES, check_partners
from ffrecon.cli.parser import DEMO_MAX_FRAMES, DEMO_MAX_SIDE, DEMO_MIN_FRAMES, DEMO_MIN_SIDE, build_parser, parse_args
from ffrecon.cli.run import _run_command, _run_options, _scene_options, print_summary, print_verdict
from ffrecon.cli.signals import (
    ignore_sigterm,
    import_native_libraries,
    leave_if_work_beside,
    leave_now,
    sigterm_as_ctrl_c,
)
from ffrecon.cli.tool_parsers import MIN_OPSET, TORCHSCRIPT_MAX_OPSET
from ffrecon.concurrency import interrupts_deferred
from ffrecon.errors import FFReconError, Interrupted
from ffrecon.timing import Clock

__all__ = [
    "DEMO_MAX_FRAMES",
    "DEMO_MAX_SIDE",
    "DEMO_MIN_FRAMES",
    "DEMO_MIN_SIDE",
    "MIN_OPSET",
    "OPTION_NEEDS",
    "SEED_MAX",
    "TORCHSCRIPT_MAX_OPSET",
    "VIDEO_SUFFIXES",
    "Path",
    "_export_options",
    "_run_options",
    "_scene_options",
    "_view_options",
    "build_parser",
    "check_partners",
    "entry",
    "leave",
    "main",
    "parse_args",
]

log = logging.getLogger("ffrecon")


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


def _parse_with_imports(argv: list[str] | None) -> argparse.Namespace:
    """Parse the command line and import what the command runs, with Ctrl-C and SIGTERM held until done
    (:func:`~ffrecon.cli.signals.import_native_libraries` says why, and loads the native libraries first)."""
    import_native_libraries()
    with interrupts_deferred():  # seconds of imports: the option classes, then the pipeline
        args = parse_args(argv)
        _setup_logging(-1 if getattr(args, "quiet", False) else getattr(args, "verbose", 0))
        if args.command in ("run", "demo"):
            import ffrecon.pipeline  # noqa: F401
    return args


def _command(args: argparse.Namespace):
    """Run the command: an exit code (the commands besides ``run`` and ``demo``) or the run's results."""
    if args.command == "inspect-model":
        inspect_model(args.model)
        return 0
    if args.command == "export-model":
        export_command(args)
        return 0
    if args.command == "view":
        return view_command(args)
    if args.command == "render":
        return render_command(args)
    return _run_command(args)


def main(argv: list[str] | None = None, *, started: Clock | None = None) -> int:
    """Run the command line ``argv`` (``sys.argv[1:]`` when None); its exit code (README, "Exit codes").

    ``started``: when the command began, for the run's "startup" time (:func:`entry` passes the process's start);
    this call when None (a command run inside another program, as the tests do)."""
    started = started or Clock.now("ffrecon.cli.main called")
    with sigterm_as_ctrl_c(), _warnings_logged():
        done = _guarded(argv, started)
    if isinstance(done, int):
        return done
    args, results = done
    if not getattr(args, "quiet", False):
        print_summary(results)
    elif results.exit_code != 0:
        print_verdict(results)
    return results.exit_code


def _guarded(argv: list[str] | None, started: Clock):
    """The command's exit code, or ``(args, results)`` of a run; an error or an interruption is one line said
    (and its fix) and its exit code, never a traceback."""
    args = None
    try:
        args = _parse_with_imports(argv)
        args.started = started  # the run's report.json times its "startup" from here
        done = _command(args)
    except Interrupted as err:
        print(f"ffrecon: {err.problem}; {err.fix}", file=sys.stderr)
        leave_if_work_beside(err.exit_code)
        return err.exit_code
    except FFReconError as err:
        print(f"ffrecon: error: {err.problem}", file=sys.stderr)
        if err.fix:
            print(f"  fix: {err.fix}", file=sys.stderr)
        return err.exit_code
    except ImportError:
        if not signals.received:
            raise
        return _interrupted()  # the signal arrived inside a native library's initialisation
    except KeyboardInterrupt:
        return _interrupted()
    except Exception as err:  # a bug in ffrecon: one line and exit 1 too, the traceback only with -v
        return _internal_error(err, verbose=bool(getattr(args, "verbose", 0)))
    return done if isinstance(done, int) else (args, done)


INTERNAL_ERROR = 1  # README, "Exit codes"


def _internal_error(err: Exception, *, verbose: bool) -> int:
    """Say an unexpected error in one line and its fix, the traceback only when asked (``-v``): exit 1. The output
    folder is as the workspace leaves it on any error (``OUT`` untouched; finished stages kept for ``--resume``)."""
    if verbose:
        traceback.print_exception(err, file=sys.stderr)
    print(f"ffrecon: internal error: {type(err).__name__}: {err}", file=sys.stderr)
    print(
        "  fix: this is a bug in ffrecon, not a fault of the input; the output folder was not replaced. "
        + (
            "Please report it with the traceback above."
            if verbose
            else "Run again with -v to see where it happened, and report it with that output."
        ),
        file=sys.stderr,
    )
    return INTERNAL_ERROR


def _interrupted() -> int:
    print("ffrecon: interrupted; earlier results are untouched", file=sys.stderr)
    leave_if_work_beside(Interrupted.exit_code)
    return Interrupted.exit_code


@contextlib.contextmanager
def _warnings_logged():
    """Python warnings as one logged line each (:func:`_log_warning`) while a command runs."""
    showwarning, warnings.showwarning = warnings.showwarning, _log_warning
    try:
        yield
    finally:
        warnings.showwarning = showwarning


def entry() -> int:
    """The ``ffrecon`` command (and ``python -m ffrecon``): :func:`main` timed from the process's start, then
    SIGTERM ignored and the process left at once (:func:`leave`)."""
    started = Clock.process_start() or Clock.now("ffrecon command called")
    try:
        code = main(started=started)
    except SystemExit as done:  # --help and --version: printed, exit 0
        if not isinstance(done.code, int | None):
            raise
        code = done.code or 0
    leave(code)
    return code


def leave(code: int) -> None:
    """End the process with ``code`` once everything is written: SIGTERM ignored from here on (a finished
    command's exit code is not turned into a kill, :func:`~ffrecon.cli.signals.ignore_sigterm`), the output and
    the log flushed, then ``os._exit`` without the interpreter's teardown (unloading torch, numba and open3d
    took 0.4-2.6 s, after every file was closed). Only the command line's own process calls it; under a tracer
    or coverage (whose data is saved at exit) it returns, and the caller exits as usual."""
    ignore_sigterm()
    if sys.gettrace() is not None or "coverage" in sys.modules:
        return
    logging.shutdown()
    leave_now(code)
