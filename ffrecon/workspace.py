"""The output folder: ffrecon writes, replaces and resumes only folders it made, one run at a time.

Rules (``docs/contracts.md``, README "Exit codes"):

- **Ownership.** Every folder ffrecon writes carries ``.ffrecon/output.json`` (the marker) listing the
  files it wrote. An ``-o`` that is a file, or a non-empty folder without the marker, is refused
  (exit 4) whatever the flags; ``-o`` equal to, inside or around the input is refused before any work.
  When a folder is replaced, files a person added to it after ffrecon wrote it (not in its list) are
  moved into the new one, never deleted.
- **Staging.** Results are built in a staging folder, ``.OUT.partial`` beside ``OUT`` (or
  ``OUT/.ffrecon-partial`` when ``OUT`` is a mount point or its parent cannot be written), and swapped
  in only when the run ends with a report: by one atomic exchange of the two folders where the
  kernel has it (``renameat2(RENAME_EXCHANGE)``), so a kill at any moment leaves ``OUT`` either as it
  was or complete and new. A run that fails before any stage finished leaves no staging folder.
- **One run per folder.** The staging folder is held under an exclusive OS lock (``flock``) for the
  whole run; the kernel releases it on any exit, SIGKILL included. A second run is refused (exit 4)
  with the first one's process id.
- **Filesystem faults** (read-only, no permission, disk full: checked up front against an estimate,
  and again when the operating system reports them) are :class:`ResourceError` (exit 6); what this
  run wrote is removed so that a full disk is left as it was found.
- **A rejected run does not replace good results.** When a verification gate failed and ``OUT``
  holds an earlier run that passed, ``OUT`` is kept and the rejected run stays in the staging folder
  (named in a warning), where ``--force --resume`` picks it up.
"""

from __future__ import annotations

import datetime as dt
import errno
import json
import logging
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from ffrecon import __version__
from ffrecon.errors import FFReconError, Interrupted, OutputExistsError, ResourceError
from ffrecon.folders import (
    IN_PLACE_OLD,
    IN_PLACE_STAGING,
    MARKER,
    OURS_INSIDE,
    OUTPUT_RECORD,
    RECORD_FORMAT,
    RUN_RECORD,
    Busy,
    clear,
    commit_by_rename,
    commit_in_place,
    empty_into,
    files_under,
    is_ffrecon_output,
    listed_files,
    lock_dir,
    read_output_record,
    remove_output,
    retire,
    visible_entries,
)

log = logging.getLogger("ffrecon")

_DISK_ERRNOS = {errno.ENOSPC, errno.EDQUOT}

MIN_FREE_BYTES = 1 << 20  # below this, a failure while writing is taken as the disk being full


def staging_path(out_dir: Path) -> Path:
    """Where a run into ``out_dir`` builds its results when ``out_dir`` can be swapped by renaming."""
    return out_dir.parent / f".{out_dir.name}.partial"


def retired_path(out_dir: Path) -> Path:
    """Where the replaced results wait while files a person added are moved out of them."""
    return out_dir.parent / f".{out_dir.name}.old"


def check_paths(source: Path, out_dir: Path) -> None:
    """Refuse (exit 4) an output that is the input, lies inside it or contains it, or is a file.

    >>> check_paths(Path("/data/photos"), Path("/data/out"))
    >>> check_paths(Path("/data/photos"), Path("/data/photos/out"))
    Traceback (most recent call last):
    ...
    ffrecon.errors.OutputExistsError: the output folder /data/photos/out lies inside the input /data/photos
      fix: choose an output folder outside the input, e.g. -o /data/photos_ffrecon
    """
    src, out = Path(os.path.abspath(source)), Path(os.path.abspath(out_dir))
    if src.exists():
        src = src.resolve()
    if out.exists() or out.is_symlink():
        out = out.resolve()
    fix = f"choose an output folder outside the input, e.g. -o {src.parent / (src.stem + '_ffrecon')}"
    if out == src:
        raise OutputExistsError(f"the output folder {out} is the input itself", fix)
    if out.is_relative_to(src):
        raise OutputExistsError(f"the output folder {out} lies inside the input {src}", fix)
    if src.is_relative_to(out):
        raise OutputExistsError(f"the output folder {out} contains the input {src}", fix)
    if out.exists() and not out.is_dir():
        raise OutputExistsError(
            f"the output {out} is a file, not a folder; ffrecon never replaces files it did not write",
            "choose a folder with -o (a new or empty one, or an earlier ffrecon output)",
        )


def resource_error(err: OSError, what: str) -> ResourceError | None:
    """The :class:`ResourceError` for an operating-system error about storage, else None."""
    where = f" ({err.filename})" if err.filename else ""
    if err.errno in _DISK_ERRNOS:
        return ResourceError(
            f"no space left on the disk while {what}{where}", "free some space there, or choose -o on another disk"
        )
    if err.errno == errno.EROFS:
        return ResourceError(f"the filesystem is read-only{where} while {what}", "choose -o on a writable disk")
    if err.errno in (errno.EACCES, errno.EPERM):
        return ResourceError(
            f"no permission to write{where} while {what}", "choose -o in a folder you can write, or fix its permissions"
        )
    return None


def estimate_output_bytes(source: Path) -> int:
    """A generous estimate of what a run of ``source`` writes: twice the input's bytes (the frames copied
    to ``images/`` and the COLMAP database), 12 MB a frame (depth maps, features, renders) and 200 MB
    (splat, point cloud, video, report)."""
    source = Path(source)
    if source.is_file():
        return 2 * source.stat().st_size + 48 * 12_000_000 + 200_000_000
    files = [p for p in source.iterdir() if p.is_file()] if source.is_dir() else []
    return 2 * sum(p.stat().st_size for p in files) + 12_000_000 * len(files) + 200_000_000


# --- locks -----------------------------------------------------------------------------------------


def _other_run(path: Path) -> str:
    try:
        record = json.loads((path / MARKER / RUN_RECORD).read_text())
        return f"process {int(record['pid'])} (started {record.get('started', '?')})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


def _busy_error(out_dir: Path, who: str) -> OutputExistsError:
    return OutputExistsError(
        f"another ffrecon run, {who}, is writing to {out_dir}",
        "wait for it to finish (or stop it), or choose another folder with -o",
    )


def _lock_or_refuse(path: Path, out_dir: Path) -> int | None:
    """The lock on folder ``path`` (its descriptor), None when it vanished meanwhile; exit 4 naming the
    other run when one holds it."""
    try:
        return lock_dir(path)
    except Busy:
        raise _busy_error(out_dir, _other_run(path)) from None
    except FileNotFoundError:
        return None


def _peek_lock(path: Path, out_dir: Path) -> None:
    """Refuse when another run holds ``path`` (it is finishing: swapping its results in)."""
    if path.is_dir() and (fd := _lock_or_refuse(path, out_dir)) is not None:
        os.close(fd)


# --- swapping folders ------------------------------------------------------------------------------


@dataclass
class Staging:
    """The folder a run builds its results in, locked for the run. Made by :func:`staged_output`."""

    out_dir: Path
    path: Path
    in_place: bool  # inside OUT (a mount point, or a read-only parent)
    created: bool  # this run made the staging folder (so a failed start removes it)
    created_parents: list[Path] = field(default_factory=list)
    keep_earlier: bool = False  # set by the run: a rejected run does not replace OUT (see :meth:`keeps_earlier`)
    verdict: str = "ok"  # the run's verdict (report.json), set by the run before the block ends
    _fd: int | None = None

    def finished_stages(self) -> list[Path]:
        return sorted((self.path / MARKER / "stages").glob("*.json"))

    def keeps_earlier(self, rejected: bool) -> bool:
        """Whether a run whose verdict is ``rejected`` must leave OUT as it is: OUT holds an earlier run
        that was not rejected. Sets :attr:`keep_earlier`."""
        if rejected and self.out_dir.is_dir():
            record = read_output_record(self.out_dir)
            self.keep_earlier = record is not None and record.get("verdict", "ok") != "gate_failed"
            if not visible_entries(self.out_dir):
                self.keep_earlier = False
        return self.keep_earlier

    # -- lifecycle ----------------------------------------------------------------------------------

    def write_record(self, state: str, verdict: str | None = None) -> None:
        marker = self.path / MARKER
        marker.mkdir(parents=True, exist_ok=True)
        record = {
            "format": RECORD_FORMAT,
            "tool": "ffrecon",
            "ffrecon_version": __version__,
            "state": state,  # "partial" while building, "complete" once swapped in, "rejected" when kept aside
            "updated": dt.datetime.now().isoformat(timespec="seconds"),
        }
        if verdict is not None:
            record["verdict"] = verdict
        if state == "complete":
            record["files"] = [f for f in files_under(self.path) if f != f"{MARKER}/{RUN_RECORD}"]
        tmp = marker / f".{OUTPUT_RECORD}.tmp"
        tmp.write_text(json.dumps(record, indent=1))
        os.replace(tmp, marker / OUTPUT_RECORD)

    def commit(self, verdict: str) -> Path:
        """Swap the finished results into OUT (or keep OUT, see :attr:`keep_earlier`); where they are now."""
        (self.path / MARKER / RUN_RECORD).unlink(missing_ok=True)
        if self.keep_earlier:
            self.write_record("rejected", verdict)
            log.warning(
                "a verification gate failed, so the earlier results in %s are kept; this run's results are in %s "
                "(open its report.html); to use them anyway, run again with --force --resume",
                self.out_dir,
                self.path,
            )
            return self.path
        self.write_record("complete", verdict)
        if self.in_place:
            commit_in_place(self.out_dir, self.path)
        else:
            try:
                commit_by_rename(self.out_dir, self.path, retired_path(self.out_dir))
            except Busy:
                raise _busy_error(self.out_dir, "another process") from None
        return self.out_dir

    def discard(self) -> None:
        """Remove the staging folder and the parent folders this run made (they hold nothing of value)."""
        if self.path.exists():
            try:
                remove_output(self.path)  # the marker last: a kill part-way leaves a folder the next run reuses
            except OSError:
                shutil.rmtree(self.path, ignore_errors=True)
        for parent in self.created_parents:
            try:
                parent.rmdir()
            except OSError:
                break

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


# --- opening ----------------------------------------------------------------------------------------


def _choose_staging(out_dir: Path) -> tuple[Path, bool]:
    """The staging folder's path and whether it is inside OUT (mount point, or a parent not writable)."""
    if out_dir.is_dir() and (os.path.ismount(out_dir) or not os.access(out_dir.parent, os.W_OK)):
        return out_dir / IN_PLACE_STAGING, True
    return staging_path(out_dir), False


def _make_parents(folder: Path) -> list[Path]:
    """Create ``folder``'s missing parents; the ones created, deepest first."""
    missing = []
    for parent in [folder, *folder.parents]:
        if parent.exists():
            break
        missing.append(parent)
    for parent in reversed(missing):
        parent.mkdir()
    return missing


def _open_staging(out_dir: Path) -> Staging:
    path, in_place = _choose_staging(out_dir)
    created_parents = [] if in_place else _make_parents(path.parent)
    for _ in range(10):
        created = False
        try:
            path.mkdir()
            created = True
        except FileExistsError:
            pass
        if not path.is_dir():
            raise OutputExistsError(
                f"{path} is in the way: ffrecon builds its results there, and it is not a folder ffrecon made",
                f"move {path} away, or choose another folder with -o",
            )
        fd = _lock_or_refuse(path, out_dir)
        if fd is None:
            continue
        staging = Staging(out_dir, path, in_place, created, created_parents, _fd=fd)
        if not created and not is_ffrecon_output(path) and any(path.iterdir()):
            staging.release()
            raise OutputExistsError(
                f"{path} holds files ffrecon did not write, where it builds its results",
                f"move {path} away, or choose another folder with -o",
            )
        return staging
    raise OutputExistsError(f"{path} keeps changing under this run", "another program is using it: try again")


def _recover(staging: Staging) -> None:
    """Finish what a killed run left half-done: a swap (``.OUT.old``, a complete staging folder)."""
    out_dir = staging.out_dir
    record = read_output_record(staging.path) or {}
    if staging.in_place:
        if record.get("state") == "complete":  # killed while moving its results up: go on with it
            log.info("finishing the swap of an earlier run into %s", out_dir)
            commit_in_place(out_dir, staging.path, keep_staging=True)
        elif (out_dir / IN_PLACE_OLD).exists():
            retire(out_dir / IN_PLACE_OLD, out_dir)
        _refuse_if_in_the_way(out_dir / IN_PLACE_OLD)
        return
    old = retired_path(out_dir)
    _peek_lock(out_dir, out_dir)
    if old.exists():
        _peek_lock(old, out_dir)
        if not out_dir.exists() and is_ffrecon_output(old):
            old.rename(out_dir)  # killed between the two renames of a swap: the earlier results come back
        else:
            retire(old, out_dir if out_dir.is_dir() else None)
    _refuse_if_in_the_way(old)
    if record.get("state") == "complete":
        # Killed just before or after the swap: this folder is a complete result that is not OUT (the
        # earlier one after an exchange, or a new one whose swap never happened); OUT is whole either way.
        log.info("removing a complete result left beside %s by a run killed while swapping", out_dir)
        empty_into(staging.path, out_dir if is_ffrecon_output(out_dir) else None)


def _refuse_if_in_the_way(old: Path) -> None:
    """Exit 4 up front when the folder a swap moves the earlier results to holds files ffrecon did not
    write (``retire`` leaves those): the swap at the end of the run would fail there, after all the work."""
    if old.exists() or old.is_symlink():
        raise OutputExistsError(
            f"{old} is in the way: ffrecon moves the earlier results there when it replaces them, and it holds "
            "files ffrecon did not write",
            f"move {old} away (or delete it), or choose another folder with -o",
        )


def _check_owner(out_dir: Path, *, overwrite: bool, resume: bool) -> None:
    if not out_dir.is_dir() or not visible_entries(out_dir):
        return
    if not is_ffrecon_output(out_dir):
        raise OutputExistsError(
            f"{out_dir} holds files that ffrecon did not write (it has no {MARKER}/ record), so ffrecon will not "
            "write into it or replace it, whatever the flags",
            "choose a new or empty folder with -o (ffrecon creates it)",
        )
    if not (overwrite or resume):
        raise OutputExistsError(
            f"the output folder {out_dir} already holds the results of an earlier ffrecon run",
            "pass --resume to reuse its finished stages, --overwrite to replace it, or choose another folder with -o",
        )


def _seed_from_output(staging: Staging) -> None:
    """Copy the files ffrecon wrote in OUT into an empty staging folder, so ``--resume`` reuses its stages."""
    out_dir = staging.out_dir
    ours = listed_files(read_output_record(out_dir))
    log.info("resuming from the finished stages in %s", out_dir)
    for rel in files_under(out_dir):
        if rel.split("/")[0] in OURS_INSIDE or (ours is not None and rel not in ours and not rel.startswith(MARKER)):
            continue
        target = staging.path / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(out_dir / rel, target, follow_symlinks=False)


def _check_space(staging: Staging, source: Path) -> None:
    need = estimate_output_bytes(source)
    free = shutil.disk_usage(staging.path).free
    if free < need:
        raise ResourceError(
            f"only {free / 1e6:.0f} MB are free on the disk of {staging.out_dir}; a run of {source} writes about "
            f"{need / 1e6:.0f} MB",
            "free some space there, or choose -o on another disk",
        )


@contextmanager
def staged_output(
    out_dir: Path, source: Path, *, overwrite: bool, resume: bool = False, fresh: bool = False
) -> Iterator[Staging]:
    """Yield the locked :class:`Staging` of a run of ``source`` into ``out_dir``; when the block ends
    normally, its results replace ``out_dir`` (:meth:`Staging.commit` with :attr:`Staging.verdict`).

    Everything that refuses the run happens here, before any work: the paths (:func:`check_paths`),
    the owner of ``out_dir``, the lock, the free space. On an error the staging folder is removed when
    this run made it (a failed start leaves nothing; a folder an interrupted run left is kept), and
    always on a full disk; after Ctrl-C its finished stages are kept for ``--resume``. ``out_dir`` is
    never touched by a failed run.
    """
    out_dir = Path(os.path.abspath(out_dir))
    check_paths(source, out_dir)
    if out_dir.is_symlink():
        out_dir = out_dir.resolve()
    _check_owner(out_dir, overwrite=overwrite, resume=resume)  # before anything is made
    try:
        staging = _open_staging(out_dir)
    except OSError as err:
        raise resource_error(err, f"making the staging folder for {out_dir}") or err from None
    try:
        try:
            _recover(staging)
            _check_owner(out_dir, overwrite=overwrite, resume=resume)  # again, under the lock
            if fresh:
                clear(staging.path)
            if resume and not staging.finished_stages() and is_ffrecon_output(out_dir):
                _seed_from_output(staging)
            elif staging.finished_stages():
                log.info("reusing the finished stages of an earlier, unfinished run in %s", staging.path)
            if Path(source).exists():
                _check_space(staging, Path(source))
            staging.write_record("partial")
            _write_run_record(staging)
            log.debug("building results in %s", staging.path)
            yield staging
        except Interrupted:  # Ctrl-C: the finished stages are kept for --resume
            if not staging.finished_stages() or _disk_full(staging.path):
                staging.discard()
            raise
        except FFReconError:  # bad input or model: nothing is left of a run that made its staging folder
            if staging.created or _disk_full(staging.path):
                staging.discard()
            raise
        except OSError as err:
            wrapped = resource_error(err, "writing the results")
            if wrapped is None and _disk_full(staging.path):
                wrapped = ResourceError("the disk is full", "free some space there, or choose -o on another disk")
            if wrapped is None:
                raise
            staging.discard()
            raise _freed(wrapped) from None
        except Exception:
            if _disk_full(staging.path):  # a library (COLMAP's SQLite, a C++ writer) failed on a full disk
                staging.discard()
                raise _freed(
                    ResourceError(
                        "the disk filled up while writing the results",
                        "free some space there, or choose -o on another disk",
                    )
                ) from None
            raise
        try:
            staging.commit(staging.verdict)
        except OSError as err:  # the results stay complete in the staging folder; OUT is whole
            raise resource_error(err, f"swapping the results into {out_dir}") or err from None
    finally:
        staging.release()


def _freed(err: ResourceError) -> ResourceError:
    err.problem += "; the unfinished results were removed to free the space again"
    return err


def _disk_full(path: Path) -> bool:
    probe = path if path.exists() else path.parent
    try:
        return shutil.disk_usage(probe).free < MIN_FREE_BYTES
    except OSError:
        return False


def _write_run_record(staging: Staging) -> None:
    record = {"pid": os.getpid(), "started": dt.datetime.now().isoformat(timespec="seconds")}
    (staging.path / MARKER / RUN_RECORD).write_text(json.dumps(record))
