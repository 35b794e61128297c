"""The output folder: results are built in a staging folder and swapped in only on success.

So a failed or interrupted run never destroys earlier results, and an existing OUT is only
replaced when the user asks for it.
"""

from __future__ import annotations

import logging
import shutil
from contextlib import contextmanager
from pathlib import Path

from ffrecon.errors import OutputExistsError

log = logging.getLogger("ffrecon")


def staging_path(out_dir: Path) -> Path:
    return out_dir.parent / f".{out_dir.name}.partial"


def holds_results(out_dir: Path) -> bool:
    return out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir()))


@contextmanager
def staged_output(out_dir: Path, *, overwrite: bool, resume: bool = False, fresh: bool = False):
    """Yield a staging folder; on success it replaces ``out_dir`` atomically-ish (two renames).

    Raises :class:`OutputExistsError` before any work if ``out_dir`` holds files and neither
    ``overwrite`` nor ``resume`` is set. On failure or interruption the staging folder is left as it
    is (its finished stages are reused by the next run into ``out_dir``) and ``out_dir`` is untouched.

    A staging folder left by an interrupted run is kept unless ``fresh``; with ``resume`` and no such
    folder, a finished ``out_dir`` is copied into it so that its stages can be reused.
    """
    out_dir = Path(out_dir).resolve()
    if holds_results(out_dir) and not (overwrite or resume):
        raise OutputExistsError(
            f"the output folder {out_dir} already holds results",
            "pass --resume to reuse its finished stages, --overwrite to replace it, or choose another folder with -o",
        )
    stage = staging_path(out_dir)
    if stage.exists() and fresh:
        shutil.rmtree(stage)
    if not stage.exists() and resume and out_dir.is_dir() and (out_dir / ".ffrecon").is_dir():
        log.info("resuming from the finished stages in %s", out_dir)
        shutil.copytree(out_dir, stage, symlinks=True)
    elif stage.exists():
        log.info("reusing the finished stages of an earlier, unfinished run in %s", stage)
    stage.mkdir(parents=True, exist_ok=True)
    log.debug("building results in %s", stage)
    yield stage
    old = out_dir.parent / f".{out_dir.name}.old"
    if old.exists():
        shutil.rmtree(old)
    if out_dir.exists():
        out_dir.rename(old)
    stage.rename(out_dir)
    if old.exists():
        shutil.rmtree(old)
