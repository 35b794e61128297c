"""Finished stages are kept and reused, as hloc does it: a stage whose inputs and options are
unchanged is not run again.

Each stage that finishes writes, under ``<run folder>/.ffrecon/stages/``, a typed record of its result
(:mod:`ffrecon.records`): ``<stage>.json`` holds the key, the seconds it took, its options, the keys of
what it read and the result itself, and ``<stage>.npz`` the result's arrays. The JSON is written
last, so a stage interrupted half-way has no record and runs again. A stage's key hashes its name,
ffrecon's version, its options and the keys of its inputs (for files the user gave: their names, sizes and
contents, hashed with BLAKE2b, :func:`file_key`; the keys of the stages it read), so changing anything
upstream recomputes everything that depends on it, also a photo replaced by another of the same size and
modification time (what ``cp -p``, ``rsync -a`` and ``tar`` make). The hashes are cached in
``.ffrecon/file_hashes.json`` by path, inode, size, modification and change time, so unchanged files are
not read again.

Reading a record runs no code: it constructs only ffrecon's own dataclasses and enums, so resuming
into a folder someone else made is safe. A record that does not decode into today's classes, or of
another record format, is refused with a log line and its stage runs again. ``<stage>.pkl`` files
left by versions that pickled results are never read.

Results are stored with their paths relative to the run folder, so a finished ``OUT`` copied
back to the staging folder (``--resume``) reads them as its own. pycolmap reconstructions are not
data: they are dropped on write and read back from the result's ``model_path``.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import logging
import math
import os
import shutil
import stat
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from ffrecon import __version__
from ffrecon.machine import peak_rss_bytes, reset_peak_rss
from ffrecon.records import RecordError, RecordFormatError, read_meta, read_result, write_record
from ffrecon.timing import StageTimer

log = logging.getLogger("ffrecon")
T = TypeVar("T")
_RECORDS = Path(".ffrecon") / "stages"
_HASHES = Path(".ffrecon") / "file_hashes.json"  # content hashes of the user's files (:class:`FileHashes`)
_RUN_ROOT = Path("<run>")  # placeholder root for paths stored in a record


@dataclass(frozen=True)
class StageTiming:
    """Wall-clock seconds of one stage; ``reused`` when it came from an earlier run's record."""

    stage: str
    seconds: float  # this run's seconds (loading the record when reused)
    reused: bool = False
    first_seconds: float | None = None  # what the stage took when it ran, for reused stages
    beside: str | None = None  # the stage that ran at the same time (see :class:`OverlapTiming`)
    # The process's peak resident memory while it ran, in GB (with the stage beside it, if any); None for a
    # reused stage and for the second of two stages side by side (the first's peak covers both).
    peak_rss_gb: float | None = None


@dataclass(frozen=True)
class OverlapTiming:
    """Stages that ran at the same time: the wall-clock seconds of the whole group and the sum of theirs.

    Their :class:`StageTiming` seconds overlap; the run took ``wall_seconds`` for them, not ``sum_seconds``.
    """

    stages: tuple[str, ...]
    wall_seconds: float
    sum_seconds: float


def content_hash(path: Path) -> str | None:
    """BLAKE2b of a regular file's bytes, streamed (None for a FIFO, a device or a folder: never opened so that
    it blocks). A sparse file's holes are not read: the hash covers its size and each data extent's offset and
    bytes, so a 20 GB sparse file hashes at once, and the same bytes laid out with other holes at worst run again.

    >>> content_hash(Path("/dev/zero")) is None
    True
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            return None
        digest = hashlib.blake2b(str(info.st_size).encode(), digest_size=20)
        with os.fdopen(fd, "rb", buffering=0, closefd=False) as file:
            for start, end in _data_extents(fd, info.st_size):
                digest.update(f"@{start}:{end}".encode())
                file.seek(start)
                left = end - start
                while left > 0 and (chunk := file.read(min(left, _CHUNK))):
                    digest.update(chunk)
                    left -= len(chunk)
    finally:
        os.close(fd)
    return digest.hexdigest()


_CHUNK = 1 << 20


def _data_extents(fd: int, size: int) -> Iterator[tuple[int, int]]:
    """``(start, end)`` of the parts of a file that hold data (SEEK_DATA/SEEK_HOLE; the whole file where the file
    system does not tell)."""
    if not hasattr(os, "SEEK_DATA"):
        yield 0, size
        return
    offset = 0
    while offset < size:
        try:
            start = os.lseek(fd, offset, os.SEEK_DATA)
        except OSError as err:
            if err.errno == errno.ENXIO:  # no data after offset: a hole to the end
                return
            yield offset, size  # the file system does not say: read it all
            return
        end = os.lseek(fd, start, os.SEEK_HOLE)
        yield start, end
        offset = end


class FileHashes:
    """Content hashes of the user's files, cached in ``<run folder>/.ffrecon/file_hashes.json`` so a rerun
    (``--resume`` copies the cache with the records) does not read unchanged files again. The cache is a first
    filter only: an entry is used while the file's path, device, inode, size, modification time and
    status-change time (ctime, which ``cp -p``, ``rsync -a``, ``tar`` and ``os.utime`` cannot set back) are
    all the same; anything else hashes the bytes. Thread-safe (stages beside each other make keys)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._entries: dict[str, list] = {}
        self._dirty = False
        try:
            loaded = json.loads(path.read_text()) if path is not None and path.is_file() else {}
            self._entries = {k: v for k, v in loaded.items() if isinstance(v, list) and len(v) == 6}
        except (OSError, ValueError, AttributeError) as err:
            log.info("the file hash cache %s cannot be used (%s); hashing the files again", path, err)

    def digest(self, path: Path) -> str | None:
        """The content hash of ``path`` (None unless it is a regular file)."""
        try:
            info = os.stat(path)
        except OSError:
            return None
        if not stat.S_ISREG(info.st_mode):
            return None
        name = os.path.abspath(path)
        fingerprint = [info.st_dev, info.st_ino, info.st_size, info.st_mtime_ns, info.st_ctime_ns]
        with self._lock:
            entry = self._entries.get(name)
        if entry is not None and entry[:5] == fingerprint:
            return entry[5]
        digest = content_hash(Path(path))
        if digest is not None:
            with self._lock:
                self._entries[name] = [*fingerprint, digest]
                self._dirty = True
        return digest

    def save(self) -> None:
        """Write the cache when it changed (a cache that cannot be written costs a rehash next time, nothing else)."""
        if self.path is None:
            return
        with self._lock:
            if not self._dirty or not self.path.parent.is_dir():
                return
            text, self._dirty = json.dumps(self._entries), False
        try:
            partial = self.path.with_name(f"{self.path.name}.{threading.get_ident()}.partial")
            partial.write_text(text)
            partial.replace(self.path)
        except OSError as err:
            log.info("the file hash cache %s cannot be written (%s)", self.path, err)


def file_key(path: Path, hashes: FileHashes | None = None) -> str:
    """A key of a file or folder the user gave: its path, and the names, sizes and content hashes
    (:func:`content_hash`) of the files in it; ``hashes`` caches the hashes by stat (see :class:`FileHashes`).
    A FIFO or a device is keyed by what it is, never read (its reader refuses it).

    >>> file_key(Path("/does/not/exist"))
    'missing:/does/not/exist'
    >>> file_key(Path("/dev/zero"))
    'not a regular file:/dev/zero'
    """
    path = Path(path)
    if not path.exists():
        return f"missing:{path}"
    if not (path.is_dir() or path.is_file()):
        return f"not a regular file:{path}"
    hashes = hashes or FileHashes(None)
    entries = sorted(path.iterdir()) if path.is_dir() else [path]
    extra = [path.with_name(path.name + ".data")] if path.suffix == ".onnx" else []  # external weights
    stats = [(p.name, p.stat().st_size, hashes.digest(p)) for p in entries + extra if p.is_file()]
    hashes.save()
    return hashlib.sha1(repr((str(path.resolve()), stats)).encode()).hexdigest()


def stage_key(stage: str, options: object, inputs: Sequence[str]) -> str:
    """The key of a stage run: its name, ffrecon's version, its options' repr and its inputs' keys."""
    text = repr((stage, __version__, repr(options), tuple(inputs)))
    return hashlib.sha1(text.encode()).hexdigest()


def rebase_paths(obj, old: Path, new: Path):
    """``obj`` with every :class:`Path` under ``old`` moved under ``new`` (dataclasses, tuples,
    lists and dicts are rebuilt; anything else is returned as it is).

    >>> rebase_paths({"a": (Path("/x/run/a.ply"), Path("/y"))}, Path("/x/run"), Path("/out"))
    {'a': (PosixPath('/out/a.ply'), PosixPath('/y'))}
    """
    if isinstance(obj, Path):
        return new / obj.relative_to(old) if obj.is_relative_to(old) else obj
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        changes = {}
        for f in dataclasses.fields(obj):
            if not f.init:
                continue
            value = getattr(obj, f.name)
            moved = rebase_paths(value, old, new)
            if moved is not value:
                changes[f.name] = moved
        return dataclasses.replace(obj, **changes) if changes else obj
    if isinstance(obj, (tuple, list)):
        items = [rebase_paths(v, old, new) for v in obj]
        if all(a is b for a, b in zip(items, obj)):
            return obj
        return type(obj)(items) if not hasattr(obj, "_fields") else type(obj)(*items)
    if isinstance(obj, dict):
        items = {k: rebase_paths(v, old, new) for k, v in obj.items()}
        return obj if all(items[k] is obj[k] for k in obj) else items
    return obj


def _drop_reconstruction(obj):
    """pycolmap reconstructions are not data; results that hold one also hold its ``model_path``."""
    if dataclasses.is_dataclass(obj) and getattr(obj, "reconstruction", None) is not None:
        return dataclasses.replace(obj, reconstruction=None)
    return obj


def _reload_reconstruction(obj):
    if dataclasses.is_dataclass(obj) and hasattr(obj, "reconstruction") and getattr(obj, "model_path", None):
        import pycolmap

        return dataclasses.replace(obj, reconstruction=pycolmap.Reconstruction(str(obj.model_path)))
    return obj


class StageRunner:
    """Runs the stages of one run folder, reusing finished ones whose key is unchanged.

    ``reuse=False`` recomputes everything (records are still written, for a later resume).
    """

    def __init__(self, run_dir: Path, *, reuse: bool, measure_memory: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.reuse = reuse
        self.measure_memory = measure_memory  # each stage's peak memory (one thread at a time may reset it)
        self.timings: list[StageTiming] = []
        self.finished: list[str] = []  # stages finished or reused in this run, in order
        self.current: str | None = None  # the stage running now (named when interrupted)
        self.overlaps: list[OverlapTiming] = []  # groups of stages that ran at the same time
        self.hashes = FileHashes(self.run_dir / _HASHES)  # the user's files' content hashes, for their keys

    def _paths(self, stage: str) -> tuple[Path, Path, Path]:
        """``(record, arrays, legacy pickle)``: ``<stage>.json`` (written last), ``<stage>.npz`` and the
        ``<stage>.pkl`` of earlier versions (never read; removed with the record)."""
        folder = self.run_dir / _RECORDS
        return folder / f"{stage}.json", folder / f"{stage}.npz", folder / f"{stage}.pkl"

    def _load(self, stage: str, key: str) -> tuple[object, float | None] | None:
        """``(result, seconds it took when it ran)`` from the stage's record when its key is ``key``, else None."""
        record, arrays, _ = self._paths(stage)
        if not (self.reuse and record.is_file()):
            return None
        try:
            meta = read_meta(record)
            if meta.get("key") != key:
                return None
            stored = rebase_paths(read_result(meta, arrays), _RUN_ROOT, self.run_dir)
        except RecordFormatError as err:
            log.info("the record of stage %s was %s; running it again", stage, err)
            return None
        except (RecordError, OSError) as err:
            log.warning("the record of stage %s cannot be used (%s); running it again", stage, err)
            return None
        try:
            stored = _reload_reconstruction(stored)
        except (OSError, ValueError, RuntimeError) as err:  # pycolmap: ValueError for a missing or broken model
            log.warning("stage %s's COLMAP model cannot be read (%s); running it again", stage, err)
            return None
        seconds = meta.get("seconds")
        return stored, float(seconds) if type(seconds) in (int, float) else None

    def forget(self, stage: str, outputs: Sequence[str] = ()) -> None:
        """Remove a stage's record and the files it writes (relative to the run folder)."""
        for path in self._paths(stage):  # the JSON first: without it the stage is not finished
            path.unlink(missing_ok=True)
        for rel in outputs:
            target = self.run_dir / rel
            if target.is_dir():
                shutil.rmtree(target)
            elif target.exists():
                target.unlink()

    def run(
        self,
        stage: str,
        fn: Callable[[], T],
        *,
        options: object,
        inputs: Sequence[str],
        outputs: Sequence[str] = (),
    ) -> tuple[T, str]:
        """``(result, key)``: the stored result when its key matches, else ``fn()`` (timed, recorded).

        ``outputs`` are the files and folders the stage writes (relative to the run folder); they are
        removed before the stage runs again, so nothing stale is left beside the new results.
        """
        key = stage_key(stage, options, inputs)
        timer = StageTimer()
        with timer.stage(stage):
            found = self._load(stage, key)
        if found is not None:
            stored, first_seconds = found
            self.timings.append(StageTiming(stage, timer.freeze().total_s, True, first_seconds))
            self.finished.append(stage)
            then = math.nan if first_seconds is None else first_seconds
            log.info("%s: reused from the earlier run (%.1f s then)", stage, then)
            return stored, key
        self.forget(stage, outputs)
        self.current = stage
        measured = self.measure_memory and reset_peak_rss()
        with timer.stage(stage):
            result = fn()
        seconds = timer.freeze().total_s
        peak = peak_rss_bytes() if measured else None
        self.current = None
        self._store(stage, key, result, seconds, options, inputs)
        self.timings.append(StageTiming(stage, seconds, peak_rss_gb=None if peak is None else peak / 2**30))
        self.finished.append(stage)
        return result, key

    @contextmanager
    def side_by_side(self) -> Iterator[StageRunner]:
        """A runner for stages run in another thread beside this runner's own, for the duration of the block.

        It shares this runner's folder and reuse. When the block ends (also by an error) its finished
        stages and timings join this runner's, after those of this runner's stages of the block, in
        order (so the order does not depend on which thread finished first); the stage it stopped in
        joins :attr:`current`; and the group's wall-clock time is recorded in :attr:`overlaps`.
        """
        branch = StageRunner(self.run_dir, reuse=self.reuse, measure_memory=False)
        first, start = len(self.timings), time.perf_counter()
        try:
            yield branch
        finally:
            self._join(branch, first, time.perf_counter() - start)

    def _join(self, branch: StageRunner, first: int, wall_seconds: float) -> None:
        here, beside = self.timings[first:], list(branch.timings)
        if here and beside:
            here = [dataclasses.replace(t, beside=beside[0].stage) for t in here]
            beside = [dataclasses.replace(t, beside=here[0].stage) for t in beside]
            group = tuple(t.stage for t in here + beside)
            self.overlaps.append(OverlapTiming(group, wall_seconds, sum(t.seconds for t in here + beside)))
        self.timings[first:] = here + beside
        self.finished += branch.finished
        if branch.current is not None:
            self.current = branch.current if self.current is None else f"{self.current} and {branch.current}"

    def _store(self, stage: str, key: str, result, seconds: float, options: object, inputs: Sequence[str]) -> None:
        record, arrays, _ = self._paths(stage)
        portable = rebase_paths(_drop_reconstruction(result), self.run_dir, _RUN_ROOT)
        meta = {
            "stage": stage,
            "key": key,
            "seconds": seconds,
            "ffrecon_version": __version__,
            "options": repr(options),
            "inputs": list(inputs),
        }
        try:
            write_record(record, arrays, meta, portable)  # the JSON last: then the stage counts as finished
        except RecordError as err:
            log.warning("the result of stage %s cannot be recorded (%s); a resumed run will run it again", stage, err)
