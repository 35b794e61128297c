"""Typed errors. Each names the problem and the fix, so the CLI can print it and exit non-zero."""

from __future__ import annotations


class FFReconError(Exception):
    """Base class: a problem with the user's input or environment, with a suggested fix."""

    exit_code = 2

    def __init__(self, problem: str, fix: str = "") -> None:
        self.problem = problem
        self.fix = fix
        super().__init__(f"{problem}" + (f"\n  fix: {fix}" if fix else ""))


class InputError(FFReconError):
    """Missing, unreadable or unsuitable images, videos or folders."""


class ModelError(FFReconError):
    """An ONNX model that does not match any supported contract, or produced unusable outputs."""

    exit_code = 3


class CheckError(FFReconError):
    """A check on arrays failed (:mod:`ffrecon.checks`). The check knows what is wrong, not where the values
    came from: the stage that called it supplies the fix (``fix=``, or :meth:`with_fix` on the way up)."""

    exit_code = 3

    def with_fix(self, fix: str) -> CheckError:
        """The same error, of the same class, with the calling stage's fix."""
        return type(self)(self.problem, fix)


class ShapeError(CheckError, ValueError):
    """An array of the wrong shape (also a ``ValueError``, as numpy raises for shapes)."""


class NonFiniteError(CheckError):
    """NaN or infinite values where a step needs finite ones (they can make LAPACK spin forever)."""


class OutputExistsError(FFReconError):
    """The output folder cannot be used: it holds results (without --overwrite/--resume), it holds files
    ffrecon did not write, another run is using it, it is a file, or it overlaps the input."""

    exit_code = 4


class ResourceError(FFReconError):
    """The machine lacks what the run needs: write access, disk space or memory (checked before the work
    where it can be, else when the operating system says so); nothing already there is touched."""

    exit_code = 6


class GateFailed(FFReconError):
    """A verification gate failed and the run stopped before the expensive stages."""

    exit_code = 5


class Interrupted(FFReconError):
    """Ctrl-C or SIGTERM: the finished stages are kept in the staging folder for ``--resume``."""

    exit_code = 130

    def __init__(self, stage: str | None, kept: list[str], staging: str, resume_command: str) -> None:
        self.stage, self.kept, self.staging = stage, kept, staging
        during = f" during {stage}" if stage else ""
        kept_text = f"kept {', '.join(kept)} in {staging}" if kept else "no stage had finished"
        super().__init__(
            f"interrupted{during}; {kept_text}; the output folder is untouched",
            f"resume with: {resume_command}",
        )
