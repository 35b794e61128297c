"""Folder operations that never lose a file: ffrecon's marker and file list, an exclusive folder lock,
the atomic exchange of two folders, and retiring replaced results while keeping a person's files.

The policy (which folder may be written, when results are swapped in) is :mod:`ffrecon.workspace`'s.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import fcntl
import json
import logging
import os
import shutil
from pathlib import Path

log = logging.getLogger("ffrecon")

MARKER = ".ffrecon"  # the folder that says "ffrecon wrote this"
OUTPUT_RECORD = "output.json"  # MARKER/OUTPUT_RECORD: format, version, state, verdict, files written
RUN_RECORD = "run.json"  # MARKER/RUN_RECORD in a staging folder: the process that holds it
RECORD_FORMAT = 1
IN_PLACE_STAGING = ".ffrecon-partial"  # inside OUT, when OUT cannot be swapped by renaming
IN_PLACE_OLD = ".ffrecon-old"
OURS_INSIDE = {IN_PLACE_STAGING, IN_PLACE_OLD}


def read_output_record(folder: Path) -> dict | None:
    """``folder``'s ``.ffrecon/output.json`` as a dict, ``{}`` for a folder of an older ffrecon (the marker
    folder without the record), None when ``folder`` is not an ffrecon output."""
    marker = folder / MARKER
    if not marker.is_dir():
        return None
    try:
        record = json.loads((marker / OUTPUT_RECORD).read_text())
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def is_ffrecon_output(folder: Path) -> bool:
    return read_output_record(folder) is not None


def visible_entries(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.name not in OURS_INSIDE]


class Busy(Exception):
    """The folder's lock is held by another process."""


def lock_dir(path: Path) -> int:
    """An exclusive, non-blocking ``flock`` on the folder ``path`` (which exists); its descriptor.

    Raises :class:`Busy` when another process holds it, ``FileNotFoundError`` when the folder was
    renamed or removed between opening and locking (the caller tries again)."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise Busy from None
    now, held = os.stat(path), os.fstat(fd)
    if (now.st_ino, now.st_dev) != (held.st_ino, held.st_dev):
        os.close(fd)
        raise FileNotFoundError(path)
    return fd


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def exchange(a: Path, b: Path) -> bool:
    """Swap two folders atomically (Linux ``renameat2(RENAME_EXCHANGE)``); False where unsupported.

    Called through ctypes because Python's ``os`` has no ``renameat2`` and no package on PyPI that
    ffrecon already depends on wraps it; two renames would leave a moment with no ``OUT`` at all."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError, TypeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(code, os.strerror(code), str(a))


def listed_files(record: dict | None) -> set[str] | None:
    """The files an output record says ffrecon wrote (relative, posix); None: unknown (older ffrecon)."""
    files = (record or {}).get("files")
    return set(files) if isinstance(files, list) else None


def files_under(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file() or p.is_symlink())


def retire(old: Path, new: Path | None) -> None:
    """Delete replaced results ``old`` (an ffrecon output), after moving into ``new`` every file of it
    that ffrecon did not write (a person's notes, say): those are never deleted."""
    if not old.exists():
        return
    if read_output_record(old) is None:
        if old.is_dir() and not old.is_symlink() and not any(old.iterdir()):
            old.rmdir()  # all that a run killed at the last step of deleting it left
        else:
            log.warning("left %s in place: it is not an ffrecon output", old)
        return
    ours = listed_files(read_output_record(old))
    if ours is not None and new is not None:
        for rel in files_under(old):
            if rel in ours or rel.startswith(f"{MARKER}/"):
                continue
            keep_file(old / rel, new / rel)
    remove_output(old)


def commit_by_rename(out_dir: Path, stage: Path, old: Path) -> None:
    """Swap ``stage`` in as ``out_dir``: atomically where the kernel can exchange two folders."""
    if not out_dir.exists():
        stage.rename(out_dir)
        return
    held = lock_dir(out_dir)  # so that no other run treats the old folder as its own mid-swap (Busy if one does)
    link_user_files(out_dir, stage)  # so that OUT holds them at every moment of the swap
    try:
        if exchange(stage, out_dir):
            stage.rename(old)  # the old results, now at the staging path
        else:  # two renames: a kill between them leaves OUT at .OUT.old, which the next run moves back
            out_dir.rename(old)
            stage.rename(out_dir)
        retire(old, out_dir)
    finally:
        os.close(held)


def link_user_files(out_dir: Path, stage: Path) -> None:
    """Hard-link (else copy) into ``stage`` the files of ``out_dir`` that ffrecon did not write."""
    ours = listed_files(read_output_record(out_dir))
    if ours is None:
        return
    for rel in files_under(out_dir):
        target = stage / rel
        if rel in ours or rel.startswith(f"{MARKER}/") or target.exists():
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(out_dir / rel, target)
        except OSError:
            shutil.copy2(out_dir / rel, target)


def commit_in_place(out_dir: Path, stage: Path, *, keep_staging: bool = False) -> None:
    """Move the results of ``OUT/.ffrecon-partial`` up into ``OUT`` (a mount point cannot be renamed).

    Not atomic; it can be repeated after a kill (it moves what is left), which the next run does."""
    old = out_dir / IN_PLACE_OLD
    old.mkdir(exist_ok=True)
    earlier = read_output_record(out_dir)
    ours = listed_files(earlier) if earlier is not None else set()
    for entry in visible_entries(out_dir):  # ffrecon's earlier results move aside
        rel = entry.name
        mine = ours is None or rel == MARKER or any(f == rel or f.startswith(rel + "/") for f in ours)
        if mine or (stage / rel).exists():
            os.replace(entry, old / rel)
    for entry in list(stage.iterdir()):
        os.replace(entry, out_dir / entry.name)
    if not keep_staging:
        shutil.rmtree(stage)
    if (old / MARKER).exists():
        retire(old, out_dir)
    else:
        shutil.rmtree(old)


def empty_into(folder: Path, out_dir: Path | None) -> None:
    """Empty ``folder`` (an ffrecon output), moving the files ffrecon did not write into ``out_dir``."""
    ours = listed_files(read_output_record(folder))
    if ours is not None and out_dir is not None:
        for rel in files_under(folder):
            if rel not in ours and not rel.startswith(f"{MARKER}/"):
                keep_file(folder / rel, out_dir / rel)
    clear(folder)


def keep_file(src: Path, target: Path) -> None:
    """Move a person's file ``src`` to ``target`` (``target.kept`` when another file is there already)."""
    if target.exists() and os.path.samefile(src, target):  # already linked into the new results
        src.unlink()
        return
    if target.exists():
        target = target.with_name(target.name + ".kept")
    target.parent.mkdir(parents=True, exist_ok=True)
    os.replace(src, target)
    log.info("kept %s (not written by ffrecon) in the new results", target)


def clear(folder: Path) -> None:
    """Delete everything in ``folder``, ffrecon's marker last: a kill part-way leaves a folder that is still
    recognisably ffrecon's (so the next run finishes the job) rather than one it must refuse to touch."""
    entries = sorted(folder.iterdir(), key=lambda entry: entry.name == MARKER)
    for entry in entries:
        shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()


def remove_output(folder: Path) -> None:
    """Delete the ffrecon output ``folder``, its marker last (see :func:`clear`)."""
    clear(folder)
    folder.rmdir()
