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


@contextmanager
def staged_output(out_dir: Path, *, overwrite: bool):
    """Yield a staging folder; on success it replaces ``out_dir`` atomically-ish (two renames).

    Raises :class:`OutputExistsError` before any work if ``out_dir`` holds files and
    ``overwrite`` is False. On failure the staging folder is left for inspection and ``out_dir``
    is untouched.
    """
    out_dir = Path(out_dir).resolve()
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())) and not overwrite:
        raise OutputExistsError(
            f"the output folder {out_dir} already holds results",
            "pass --overwrite to replace them, or choose another folder with -o",
        )
    stage = staging_path(out_dir)
    if stage.exists():
        shutil.rmtree(stage)
    stage.mkdir(parents=True)
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
