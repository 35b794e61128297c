"""Two pieces of work at the same time: one in the calling thread, one in a thread beside it.

The feed-forward inference and the COLMAP cross-check read only the capture, so the pipeline runs
them side by side (``POSES`` in :mod:`ffrecon.stages`, a :class:`~ffrecon.state.Beside`). Threads are
enough: onnxruntime and pycolmap release the GIL while they compute. They share the machine's cores through a
:class:`CoreShare`: the feed-forward stage *claims* the threads it keeps busy (one, and onnxruntime's while the network
runs); the work beside asks, at the start of each of its steps (each batch of SIFT extraction,
matching), how many cores are left.

pycolmap cannot be stopped inside a call, and a process must not end while one runs in another
thread (the C++ runtime aborts), so the work beside is stopped between its steps: when either side
fails or is interrupted, the share is cancelled, and the next :meth:`CoreShare.step` raises
:class:`Cancelled`. The calling thread waits for that before raising the first error as it was.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

log = logging.getLogger("ffrecon")
A = TypeVar("A")
B = TypeVar("B")
THREAD_NAME = "ffrecon-beside"  # the thread of the work beside
_RUNNING: set[threading.Event] = set()  # one per run_beside whose work beside has not ended


def available_cores() -> int:
    """The cores this process may run on: its CPU affinity (``taskset``, a container's cpuset) where the system
    says, else every core of the machine. ``os.cpu_count()`` counts the machine's cores whatever the affinity, so
    under ``taskset -c 0`` a 2-core machine's work beside a claim of one core still asked for one more.

    >>> available_cores() >= 1
    True
    """
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


# numpy's OpenBLAS thread-count functions, by the names its builds export (numpy's wheels: scipy-openblas, 64-bit
# integers; a system OpenBLAS: plain names)
_OPENBLAS_THREADS = (
    ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
    ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
    ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
    ("openblas_set_num_threads", "openblas_get_num_threads"),
)


def numpy_openblas() -> tuple[Callable[[int], None], Callable[[], int]] | None:
    """``(set_threads, get_threads)`` of the OpenBLAS that numpy's wheel ships (``numpy.libs``, ``numpy/.dylibs``),
    or None where numpy uses another BLAS or none is found."""
    import numpy

    root = Path(numpy.__file__).resolve().parent
    for folder in (root.parent / "numpy.libs", root / ".dylibs"):
        for path in sorted(folder.glob("*openblas*")) if folder.is_dir() else ():
            try:
                lib = ctypes.CDLL(str(path))  # numpy loaded it already: the same library
            except OSError:
                continue
            for set_name, get_name in _OPENBLAS_THREADS:
                if hasattr(lib, set_name) and hasattr(lib, get_name):
                    return getattr(lib, set_name), getattr(lib, get_name)
    return None


@contextlib.contextmanager
def blas_threads(threads: int = 1) -> Iterator[None]:
    """numpy's OpenBLAS held to ``threads`` threads for the block, as it was after it (nothing where numpy's BLAS
    is not a known OpenBLAS). For the whole process: every thread's numpy matrix products.

    ffrecon's numpy products are tall and thin (``[N, 3] @ [3, 3]`` over a frame's pixels: unprojection, overlap,
    fusion), where OpenBLAS's threads cost more than they give: on the 2-core machine, ``[307200, 3] @ [3, 3]``
    took 3x the wall and CPU on two threads than on one, and ``--quick --no-splat`` at 48 frames used 30-32 CPU s
    instead of 40 (the exports 4.1-4.4 instead of 7.4-8.6) with the same cameras (docs/benchmarks.md, issue 40).
    """
    found = numpy_openblas()
    if found is None:
        yield
        return
    set_threads, get_threads = found
    before = int(get_threads())
    set_threads(threads)
    try:
        yield
    finally:
        set_threads(before)


def map_in_order(fn: Callable[[A], B], items: Iterable[A], workers: int, window: int = 0) -> Iterator[B]:
    """``fn(item)`` for each of ``items``, yielded in their order, computed on ``workers`` threads (in the calling
    thread when ``workers`` <= 1). The items are drawn in the calling thread, at most ``window`` (default twice the
    workers) ahead of the results yielded, so that what they hold (decoded photos) stays bounded. For work that
    releases the GIL (OpenCV, numpy on large arrays, file writes). An error of ``fn`` is raised where its result
    would have been yielded, once the items already drawn have finished."""
    if workers <= 1:
        yield from map(fn, items)
        return
    ahead = window or 2 * workers
    with ThreadPoolExecutor(workers, thread_name_prefix="ffrecon-map") as pool:
        pending: collections.deque[Future[B]] = collections.deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


class Cancelled(Exception):
    """Raised at the next step of the work beside once the other side failed or was interrupted."""


class CoreShare:
    """The machine's cores, shared by work that runs at the same time.

    >>> cores = CoreShare(4)
    >>> with cores.claim(3):
    ...     cores.step()
    1
    >>> cores.step()
    4
    """

    def __init__(self, cores: int | None = None) -> None:
        self.cores = max(1, cores or available_cores())
        self._claimed: list[int] = []
        self._lock = threading.Lock()
        self._cancelled = threading.Event()

    @contextlib.contextmanager
    def claim(self, threads: int) -> Iterator[None]:
        """Hold ``threads`` cores for the duration of the block."""
        with self._lock:
            self._claimed.append(threads)
        try:
            yield
        finally:
            with self._lock:
                self._claimed.remove(threads)

    def step(self) -> int:
        """Threads for the next step of the work beside: the cores nobody claims, at least one.

        Raises :class:`Cancelled` once :meth:`cancel` was called.
        """
        if self._cancelled.is_set():
            raise Cancelled("stopped: the work beside it failed or was interrupted")
        with self._lock:
            return max(1, self.cores - sum(self._claimed))

    def cancel(self) -> None:
        self._cancelled.set()


def run_beside(
    here: Callable[[], A], beside: Callable[[], B], cores: CoreShare, *, label: str = "the work beside"
) -> tuple[A, B]:
    """``(here(), beside())``, ``here`` in this thread and ``beside`` in another, at the same time.

    ``beside`` should call ``cores.step()`` between its steps. When either raises (KeyboardInterrupt
    included), ``cores`` is cancelled and, once ``beside`` has stopped, the first error raised is raised
    again, as it was (:class:`Cancelled` only when nothing else failed). Ctrl-C while this thread waits
    for ``beside`` does the same; a second Ctrl-C stops waiting. ``label`` names ``beside`` in the log.
    """
    outcome: dict[str, object] = {}
    ended = threading.Event()  # not Thread.is_alive(): a join interrupted by Ctrl-C marks a running thread ended

    def run() -> None:
        try:
            outcome["value"] = beside()
        except BaseException as err:  # handed to the calling thread, which raises it
            outcome["error"], outcome["when"] = err, time.monotonic()
            cores.cancel()
        finally:
            ended.set()
            _RUNNING.discard(ended)

    _RUNNING.add(ended)
    threading.Thread(target=run, name=THREAD_NAME, daemon=True).start()
    try:
        value = here()
    except BaseException as err:
        when = time.monotonic()
        cores.cancel()
        interrupted = isinstance(err, KeyboardInterrupt)
        if interrupted and not ended.is_set():
            _say_stopping(label)
        _wait(ended, cores, label, interrupted=interrupted)
        raise _first(err, when, outcome) from None
    if _wait(ended, cores, label):
        raise KeyboardInterrupt
    if "error" in outcome:
        raise outcome["error"]
    return value, outcome["value"]


def work_beside_running() -> bool:
    """Whether work started by :func:`run_beside` still runs (after a second Ctrl-C stopped the wait for it).

    A process must not end normally then: the C++ runtime aborts when the interpreter shuts down
    while pycolmap computes in another thread.
    """
    return bool(_RUNNING)


def _first(err: BaseException, when: float, outcome: dict) -> BaseException:
    """The error raised first of ``err`` (raised here at ``when``) and the one beside, if any; Cancelled last."""
    other = outcome.get("error")
    if other is None or isinstance(other, Cancelled) or (outcome["when"] > when and not isinstance(err, Cancelled)):
        return err
    return other


def _wait(ended: threading.Event, cores: CoreShare, label: str, *, interrupted: bool = False) -> bool:
    """Wait for the work beside to end; whether Ctrl-C came (before, with ``interrupted``, or meanwhile).

    Ctrl-C cancels ``cores`` and waits on for the work to stop; a second one stops waiting (raised).
    Polls with sleeps: an interrupted sleep leaves no lock behind.
    """
    while not ended.is_set():
        try:
            time.sleep(0.05)
        except KeyboardInterrupt:
            if interrupted:
                raise
            interrupted = True
            cores.cancel()
            _say_stopping(label)
    return interrupted


def _say_stopping(label: str) -> None:
    log.warning("stopping: %s ends its current step first (Ctrl-C again to stop at once)", label)


_DEFERRED = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def interrupts_deferred():
    """Hold SIGINT and SIGTERM until the block ends, then raise KeyboardInterrupt if one came.

    Wraps every stretch of numba kernels (the warm-up, each training step, each render_view): numba
    calls back into Python (LLVM while it compiles, ``_numba_unpickle`` while a kernel runs), and a
    KeyboardInterrupt raised in such a callback is swallowed ("Exception ignored on calling ctypes
    callback"), leaving a kernel half-built (the process crashed or hung), or turns into a SystemError
    that escapes the CLI's interrupt handling (both reproduced by a Ctrl-C or SIGTERM during a splat).
    The signal is then taken at the end of the block, a fraction of a second later. The command line holds
    them the same way while it imports (a KeyboardInterrupt inside a C extension's initialisation becomes
    an ImportError, reproduced with open3d). Only the main thread can handle signals; elsewhere the block
    runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []
    held = [sig for sig in _DEFERRED if signal.getsignal(sig) is not signal.SIG_IGN]  # ignored ones stay ignored
    previous = {sig: signal.signal(sig, lambda signum, frame: came.append(signum)) for sig in held}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if came:
        raise KeyboardInterrupt
